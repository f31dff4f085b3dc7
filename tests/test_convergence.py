"""The stopping rule (nvs.run.convergence): the rule by hand, the callback inside a real Lightning fit, the config."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import lightning as L
import pytest
import torch

from nvs.core.errors import UserError
from nvs.run.convergence import RECORD, Convergence, converged, read_record
from tests.conftest import compose_train

REPO = Path(__file__).resolve().parents[1]


def test_rule_by_hand():
    # At step 400 the window is steps 300..400: best up to 300 is 0.50, best overall 0.497 -> 0.6% < 1%: stop.
    assert "0.60%" in converged([(100, 0.6), (200, 0.52), (300, 0.50), (400, 0.497)])
    # 0.49 is 2% better than 0.50: keep going.
    assert converged([(100, 0.6), (200, 0.52), (300, 0.50), (400, 0.49)]) == ""
    # At step 500 the cut is 375: the reference is min(0.6, 0.52, 0.50) and 0.495 is 1% better: not below 1%.
    assert converged([(100, 0.6), (200, 0.52), (300, 0.50), (500, 0.495)]) == ""
    # A worse last value still compares the bests: no improvement at all -> stop.
    assert converged([(100, 0.6), (200, 0.5), (300, 0.5), (400, 0.7)]) != ""
    # One validation, or none before the window: nothing to compare with.
    assert converged([(100, 0.5)]) == ""
    assert converged([]) == ""
    # min_steps holds the stop back; window and min_improvement are the knobs.
    flat = [(100, 0.5), (200, 0.5), (300, 0.5), (400, 0.5)]
    assert converged(flat, min_steps=500) == "" and converged(flat, min_steps=400) != ""
    assert converged([(100, 0.6), (200, 0.52), (300, 0.50), (400, 0.49)], min_improvement=0.05) != ""
    # window 0.5 at step 400: reference is the best up to 200 (0.52); 0.49 is 5.8% better.
    assert converged([(100, 0.6), (200, 0.52), (300, 0.50), (400, 0.49)], window=0.5, min_improvement=0.05) == ""
    # NaN validations are ignored, not taken as improvements.
    assert converged([(100, 0.5), (200, float("nan")), (300, 0.5), (400, 0.5)]) != ""


@pytest.mark.parametrize("kwargs, message", [({"window": 1.5}, "window"), ({"min_improvement": -1}, "min_improvement"),
                                             ({"min_steps": -3}, "min_steps")])
def test_bad_settings_are_one_clear_error(tmp_path, kwargs, message):
    with pytest.raises(UserError, match=f"callbacks.convergence.{message}"):
        Convergence(str(tmp_path), **kwargs)


class _Scripted(L.LightningModule):
    """Logs a scripted val/l1 at each validation: the callback decides on exactly these numbers."""

    def __init__(self, values):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(1))
        self.values, self.i = list(values), 0

    def training_step(self, batch, batch_idx):
        return (self.w - 1).pow(2).sum()

    def validation_step(self, batch, batch_idx):
        pass

    def on_validation_epoch_end(self):
        if self.trainer.sanity_checking:
            return
        self.log("val/l1", self.values[min(self.i, len(self.values) - 1)])
        self.i += 1

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


def _fit(tmp_path, values, max_steps, **kwargs):
    data = torch.utils.data.DataLoader(torch.zeros(1000, 1), batch_size=1)
    cb = Convergence(str(tmp_path), **kwargs)
    trainer = L.Trainer(max_steps=max_steps, val_check_interval=10, check_val_every_n_epoch=None, limit_val_batches=1,
                        callbacks=[cb], logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, num_sanity_val_steps=0)
    trainer.fit(_Scripted(values), train_dataloaders=data, val_dataloaders=data)
    return trainer, read_record(tmp_path)


def test_the_callback_stops_a_fit_and_records_why_and_when(tmp_path):
    # validations at 10, 20, 30, 40: at 40 the best up to 30 is 0.5 and 0.499 is 0.2% better -> stop at step 40.
    trainer, record = _fit(tmp_path, [0.8, 0.6, 0.5, 0.499, 0.3], max_steps=200)
    assert trainer.global_step == 40 and record["outcome"] == "converged" and record["step"] == 40
    assert [h["step"] for h in record["history"]] == [10, 20, 30, 40] and "0.20%" in record["reason"]
    assert record["max_steps"] == 200 and record["monitor"] == "val/l1"
    walls = [h["wall_s"] for h in record["history"]]
    assert walls == sorted(walls) and walls[0] > 0  # training wall time at each validation: the curves' x axis


def test_the_budget_ends_a_run_that_keeps_improving(tmp_path):
    trainer, record = _fit(tmp_path, [0.8 * 0.9 ** k for k in range(20)], max_steps=50)
    assert trainer.global_step == 50 and record["outcome"] == "max_steps" and "max_steps=50" in record["reason"]
    assert len(record["history"]) == 5


def test_history_survives_a_resume(tmp_path):
    cb = Convergence(str(tmp_path))
    cb.history = [(10, 0.5), (20, 0.4)]
    other = Convergence(str(tmp_path))
    other.load_state_dict(cb.state_dict())
    assert other.history == cb.history and other.stopped_step is None
    # resumed from the checkpoint written at the stop: training stops again instead of running to max_steps
    cb.stopped_step, cb.reason = 20, "converged"
    resumed = Convergence(str(tmp_path))
    resumed.load_state_dict(cb.state_dict())
    trainer = type("T", (), {"should_stop": False})()
    resumed.on_train_start(trainer, None)
    assert trainer.should_stop and resumed.stopped_step == 20


def test_the_config_option_adds_the_callback_to_the_defaults():
    cfg = compose_train(["experiment=nvs_chairs", "callbacks=convergence"])
    assert list(cfg.callbacks) == ["model_checkpoint", "progress_bar", "validation_images", "convergence"]
    assert cfg.callbacks.convergence._target_ == "nvs.run.convergence.Convergence"
    assert (cfg.callbacks.convergence.window, cfg.callbacks.convergence.min_improvement) == (0.25, 0.01)
    assert "convergence" not in compose_train(["experiment=nvs_chairs"]).callbacks  # off by default


@pytest.mark.slow
def test_a_real_training_run_stops_early(objects_root, tmp_path):
    """nvs.train with callbacks=convergence and a rule loose enough to fire: metrics.json's steps is the stop step."""
    out = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "nvs.train", "experiment=nvs_chairs", f"data.root={objects_root}",
                          "callbacks=convergence", "callbacks.convergence.min_improvement=10.0", "loss=[recon]",
                          "trainer.max_steps=40", "trainer.val_check_interval=2", "trainer.limit_val_batches=1",
                          "data.loader.batch_size=2", "trainer.enable_progress_bar=false", f"hydra.run.dir={out}"],
                         cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    record = json.loads((out / RECORD).read_text())
    metrics = json.loads((out / "metrics.json").read_text())
    assert record["outcome"] == "converged" and record["step"] == 4 and metrics["steps"] == 4
    assert "[convergence] stopping at step 4" in res.stderr


def test_a_run_resumed_after_the_stop_does_not_train_on(tmp_path):
    values = [0.8, 0.6, 0.5, 0.499, 0.3, 0.2, 0.1]
    data = torch.utils.data.DataLoader(torch.zeros(1000, 1), batch_size=1)

    def fit(ckpt_path=None):
        ckpt = L.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
        trainer = L.Trainer(max_steps=200, val_check_interval=10, check_val_every_n_epoch=None, limit_val_batches=1,
                            callbacks=[Convergence(str(tmp_path)), ckpt], logger=False, enable_progress_bar=False,
                            enable_model_summary=False, num_sanity_val_steps=0)
        trainer.fit(_Scripted(values), train_dataloaders=data, val_dataloaders=data, ckpt_path=ckpt_path)
        return trainer

    assert fit().global_step == 40
    walls = [h["wall_s"] for h in read_record(tmp_path)["history"]]
    assert fit(str(tmp_path / "ckpt" / "last.ckpt")).global_step == 40
    record = read_record(tmp_path)
    assert record["step"] == 40 and [h["wall_s"] for h in record["history"]] == walls  # restored, not restarted
