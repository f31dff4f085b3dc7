"""Loggers (csv, tensorboard, wandb offline; multi-select), the validation image grid, the step progress bar, and
the start-up noise that is silenced (and only that)."""

from __future__ import annotations

import csv
import logging
import re
import subprocess
import sys
import warnings
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
import yaml
from hydra.utils import instantiate
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger, WandbLogger
from PIL import Image

from nvs.run.display_callbacks import PairTestBar, StepProgressBar
from nvs.run.quiet import silence_known_noise
from nvs.run.visuals import image_grid
from tests.conftest import compose_train

REPO = Path(__file__).resolve().parents[1]


def test_loggers_multi_select_and_wandb_is_offline(tmp_path):
    cfg = compose_train([f"paths.output_dir={tmp_path}", "logger=[csv,tensorboard,wandb]"])
    assert list(cfg.logger) == ["csv", "tensorboard", "wandb"]
    assert cfg.logger.wandb.offline is True and cfg.logger.wandb.log_model is False
    loggers = [instantiate(c) for c in cfg.logger.values()]
    assert [type(lg) for lg in loggers][:2] == [CSVLogger, TensorBoardLogger] and isinstance(loggers[2], WandbLogger)
    assert compose_train(["logger=tensorboard"]).logger.keys() == {"tensorboard"}


def test_image_grid_rows_are_samples_and_columns_source_target_prediction_depth():
    src, tgt, pred = (torch.full((2, 3, 8, 8), v) for v in (0.0, 0.5, 1.0))
    depth = torch.arange(64.0).view(1, 1, 8, 8).repeat(2, 1, 1, 1)  # far at the bottom right
    grid = image_grid([src, tgt, pred, depth], scale=2, pad=2)
    assert grid.shape == (3, 2 * (16 + 2) + 2, 4 * (16 + 2) + 2)
    tile = lambda row, col: grid[:, 2 + row * 18:2 + row * 18 + 16, 2 + col * 18:2 + col * 18 + 16]  # noqa: E731
    assert torch.all(tile(1, 0) == 0) and torch.all(tile(1, 1) == 0.5) and torch.all(tile(0, 2) == 1)
    d = tile(0, 3)
    assert d[:, 0, 0].tolist() == [1.0, 1.0, 1.0] and d[:, -1, -1].tolist() == [0.0, 0.0, 0.0]  # near = bright


class _Tiny(L.LightningModule):
    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(2, 1)

    def training_step(self, batch, batch_idx):
        return self.lin(batch[0]).pow(2).mean()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.01)


def test_progress_bar_counts_steps_toward_max_steps_across_epochs(tmp_path, capsys):
    silence_known_noise()
    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(6, 2)), batch_size=2)  # 3 per epoch
    trainer = L.Trainer(max_steps=7, max_epochs=-1, callbacks=[StepProgressBar()], logger=False,
                        enable_checkpointing=False, enable_model_summary=False, default_root_dir=tmp_path)
    trainer.fit(_Tiny(), data)
    out = capsys.readouterr().out
    assert trainer.current_epoch >= 2  # three epochs ran ...
    assert "train steps" in out and "7/7" in out  # ... on one bar, counting steps toward max_steps
    assert "3/3" not in out and "Epoch 1" not in out and "Training" not in out  # not Lightning's per-epoch bar
    assert re.search(r"train steps:[^\r]*? [1-6]/7 \[\d\d:\d\d<\d\d:\d\d", out)  # elapsed<remaining: an ETA


class _TinyTest(L.LightningModule):
    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(1, 1)

    def test_step(self, batch, batch_idx):
        return self.lin(batch["src"].mean((1, 2, 3))[:, None]).mean()


def _pairs_loader(n: int, batch_size: int):
    pairs = [{"src": torch.rand(3, 4, 4), "tgt": torch.rand(3, 4, 4)} for _ in range(n)]
    return torch.utils.data.DataLoader(pairs, batch_size=batch_size)  # 7 pairs at 3: batches of 3, 3 and 1


@pytest.mark.parametrize("bar", [PairTestBar, StepProgressBar])
@pytest.mark.parametrize("limit, pairs", [(1.0, 7), (2, 6)])
def test_the_test_bar_counts_pairs_not_batches(bar, limit, pairs, tmp_path, capsys, monkeypatch):
    silence_known_noise()
    monkeypatch.setattr(PairTestBar, "_terminal", staticmethod(lambda: True))  # the test bar is a terminal's
    trainer = L.Trainer(callbacks=[bar()], logger=False, enable_model_summary=False, limit_test_batches=limit,
                        default_root_dir=tmp_path)
    trainer.test(_TinyTest(), _pairs_loader(7, 3), verbose=False)
    out = capsys.readouterr().out
    counts = re.findall(r"test pairs: [^\r\n]*?\| (\d+)/(\d+) \[", out)
    assert counts and {int(total) for _, total in counts} == {pairs}  # the total is the pairs, not 3 (2) batches
    assert [int(n) for n, _ in counts][-1] == pairs and {3, 6} & {int(n) for n, _ in counts}  # one batch: 3 pairs
    assert "Testing" not in out and "pairs/s" in out  # not Lightning's bar of batches


@pytest.mark.parametrize("bar, lines", [(PairTestBar, True), (StepProgressBar, False)])
def test_in_a_log_file_the_test_bar_is_plain_lines_or_nothing(bar, lines, tmp_path, capsys, monkeypatch):
    silence_known_noise()
    monkeypatch.setattr(PairTestBar, "_terminal", staticmethod(lambda: False))
    monkeypatch.setattr(PairTestBar, "LINES", 3)  # a line per third of the 21 pairs: at 9, 18 and 21
    trainer = L.Trainer(callbacks=[bar()], logger=False, enable_model_summary=False, default_root_dir=tmp_path)
    trainer.test(_TinyTest(), _pairs_loader(21, 3), verbose=False)
    out = capsys.readouterr().out
    assert "\r" not in out and "\x1b[" not in out
    counts = re.findall(r"^test pairs: [^\n]*?\| (\d+)/21 \[", out, flags=re.M)
    assert counts == (["9", "18", "21"] if lines else []), out


def test_lightning_lines_print_once_where_the_root_logger_prints_them(monkeypatch):
    """Under Hydra the root logger has a handler: Lightning's own console handler goes (each line printed once);
    without one (a library caller that set up no logging) Lightning keeps its handler, or its lines would vanish."""
    from nvs.run import quiet

    light, root = logging.getLogger("lightning"), logging.getLogger()
    own = logging.StreamHandler()
    monkeypatch.setattr(light, "handlers", [own])
    monkeypatch.setattr(light, "propagate", True)
    monkeypatch.setattr(root, "handlers", [])
    quiet._one_line_per_lightning_record()
    assert light.handlers == [own]
    monkeypatch.setattr(root, "handlers", [logging.StreamHandler()])
    quiet._one_line_per_lightning_record()
    assert light.handlers == []


def test_silence_drops_exactly_the_listed_noise(caplog):
    silence_known_noise()
    rank_zero = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    with warnings.catch_warnings(record=True) as seen, caplog.at_level(logging.INFO):
        silence_known_noise()  # catch_warnings reset the filters: install them again inside
        warnings.simplefilter("always")
        silence_known_noise()
        rank_zero.info("💡 Tip: For seamless cloud logging, try installing [litlogger](...)")
        rank_zero.info("💡 Tip: For seamless cloud uploads and versioning, try installing [litmodels](...)")
        rank_zero.info("Restoring states from the checkpoint path")
        warnings.warn("`isinstance(treespec, LeafSpec)` is deprecated, use ...", FutureWarning)
        warnings.warn("Found 13 module(s) in eval mode at the start of training. This may ...", UserWarning)
        warnings.warn("The dataloader does not have many workers", UserWarning)
    assert [r.getMessage() for r in caplog.records if r.name == rank_zero.name] == [
        "Restoring states from the checkpoint path"]
    assert [str(w.message) for w in seen] == ["The dataloader does not have many workers"]


def test_a_run_logs_to_tensorboard_wandb_offline_and_csv_with_the_image_grid(objects_root, tmp_path):
    """A real ``python -m nvs.train`` with all three loggers, stdout a file: scalars under the same names in each,
    the resolved config as hyperparameters, the learning rate, the test metrics, val/grid and the checkpoint at the
    validation scalars' steps, the training loss of a run shorter than log_every_n_steps, and a console without
    W&B's banner, escape codes or the logger version."""
    cmd = [sys.executable, "-m", "nvs.train", f"data.root={objects_root}", f"paths.log_dir={tmp_path}",
           "logger=[csv,tensorboard,wandb]", "trainer.max_steps=4", "trainer.val_check_interval=2",
           "data.loader.batch_size=2", "loss=[recon,vgg]", "scheduler=onecycle"]
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    run_dir = next(tmp_path.rglob("metrics.json")).parent
    scalars = {"train/loss/recon", "train/loss/vgg", "train/loss/total", "val/l1", "val/ssim_paper", "lr-Adam",
               "test/l1", "test/ssim_paper", "test/psnr"}
    assert [p.name for p in (run_dir / "checkpoints").glob("best-*.ckpt")] == ["best-4.ckpt"]

    # TensorBoard: the event files' tags (the test metrics come after the fit, in a second file of the same run)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir / "tensorboard"), size_guidance={"images": 0})
    acc.Reload()
    assert scalars <= set(acc.Tags()["scalars"]) and acc.Tags()["images"] == ["val/grid"]
    assert [e.step for e in acc.Images("val/grid")] == [2, 4]  # each validation, not the sanity check
    assert [e.step for e in acc.Scalars("val/l1")] == [2, 4]  # the grid's and the checkpoint's steps
    assert len(acc.Scalars("train/loss/total")) == 1  # 4 steps < log_every_n_steps=25: logged once all the same
    assert "_hparams_/experiment" in acc.PluginTagToContent("hparams")
    tb_hparams = yaml.safe_load((run_dir / "tensorboard" / "hparams.yaml").read_text())
    assert tb_hparams["trainer"]["max_steps"] == 4 and tb_hparams["data"]["root"] == str(objects_root)

    # W&B offline: the run's files, the same keys and the config in its record log, the grid as media
    (wandb_run,) = (run_dir / "wandb").glob("offline-run-*")
    (record,) = wandb_run.glob("run-*.wandb")
    data = record.read_bytes()
    assert all(key.encode() in data for key in scalars | {"val/grid", "trainer/global_step"})
    assert b"val_check_interval" in data and b"max_delta_azimuth" in data  # config keys
    grids = sorted((wandb_run / "files" / "media" / "images" / "val").glob("grid_*.png"))
    assert len(grids) == 2

    # CSV: the same scalar names, the config as hparams.yaml, and the grid as PNGs beside it
    rows = list(csv.DictReader((run_dir / "csv" / "metrics.csv").open()))
    assert scalars <= set(rows[0])
    assert [int(r["step"]) for r in rows if r["val/l1"]] == [2, 4]
    assert [int(r["step"]) for r in rows if r["test/l1"]] == [4]
    assert yaml.safe_load((run_dir / "csv" / "hparams.yaml").read_text())["trainer"]["val_check_interval"] == 2
    pngs = sorted((run_dir / "csv" / "images").glob("val_grid_step*.png"))
    assert [p.name for p in pngs] == ["val_grid_step0000002.png", "val_grid_step0000004.png"]
    grid = np.asarray(Image.open(pngs[0]))
    assert grid.shape == (4 * (128 + 2) + 2, 4 * (128 + 2) + 2, 3)  # 4 pairs x 4 columns, 64² tiles upscaled 2x
    assert not np.array_equal(np.asarray(Image.open(pngs[1])), grid)  # the prediction changed with training

    # the bar counts steps toward max_steps with an ETA; the listed noise is gone, other output stays
    assert "train steps" in res.stdout and "4/4" in res.stdout and re.search(r"[1-3]/4 \[\d\d:\d\d<", res.stdout)
    assert "\r" not in res.stdout  # a log file: one line per event, no carriage-return updates
    noise = ("litlogger", "litmodels", "LeafSpec", "module(s) in eval mode", "wandb:", "anonymous", "v_num",
             "\x1b", "Validation")
    assert not [n for n in noise if n in res.stdout + res.stderr]
    # each Lightning line once: the root logger Hydra configures prints it (and files it), Lightning's own handler not
    assert (res.stdout + res.stderr).count("`Trainer.fit` stopped: `max_steps=4` reached.") == 1
    assert "`Trainer.fit` stopped" in (run_dir / "train.log").read_text()


def test_the_validation_grid_takes_pairs_spread_over_the_split_one_per_model():
    from types import SimpleNamespace

    from nvs.run.display_callbacks import ValidationImages

    # 4 models x 4 pairs, listed model by model as the objects format lists its validation pairs
    items = [{"src": torch.full((3, 2, 2), float(i)), "id_src": f"m{i // 4}_{i}", "index": i} for i in range(16)]
    loader = torch.utils.data.DataLoader(items, batch_size=8)
    callback = ValidationImages(samples=4)
    callback.on_validation_start(SimpleNamespace(val_dataloaders=loader), None)
    assert callback.batch["index"].tolist() == [0, 4, 8, 12]
    assert [i.split("_")[0] for i in callback.batch["id_src"]] == ["m0", "m1", "m2", "m3"]
    few = ValidationImages(samples=4)
    few.on_validation_start(SimpleNamespace(val_dataloaders=[torch.utils.data.DataLoader(items[:3])]), None)
    assert few.batch["index"].tolist() == [0, 1, 2]


def test_log_interval_is_capped_at_a_shorter_run_and_wandb_is_quiet(tmp_path):
    from nvs.run.loggers import QuietWandbLogger
    from nvs.run.training import _short_run

    cfg = compose_train([f"paths.output_dir={tmp_path}", "trainer.max_steps=10"])
    assert cfg.trainer.log_every_n_steps == 25 and cfg.trainer.val_check_interval == 500
    assert _short_run(cfg) == {"log_every_n_steps": 10, "val_check_interval": 10}
    assert _short_run(compose_train([f"paths.output_dir={tmp_path}", "trainer.max_steps=100"])) == {
        "val_check_interval": 100}
    assert _short_run(compose_train([f"paths.output_dir={tmp_path}", "trainer.max_steps=1000"])) == {}
    logger = QuietWandbLogger(save_dir=str(tmp_path), offline=True)
    assert "anonymous" not in logger._wandb_init and logger._wandb_init["settings"].silent is True
