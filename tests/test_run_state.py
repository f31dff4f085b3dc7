"""Nothing lost, nothing silently wrong (issue 37, items 1-5): the user's files in a run directory, a fresh
``last.ckpt``, resume by recorded step in a moved directory with the whole training curve, diverged runs stopped,
and the weights' content hash checked on every load."""

from __future__ import annotations

import csv
import os
import shutil
import signal
import warnings
import zipfile
from pathlib import Path

import lightning as L
import pytest
import torch
from omegaconf import OmegaConf, open_dict

from nvs.core.errors import Interrupted, UserError
from nvs.core.weights_digest import KEY, digest
from nvs.module.lightning_module import NonFiniteLossError
from nvs.run.build import build_module
from nvs.run.checkpoint_files import newest_checkpoint, resume_checkpoint
from nvs.run.checkpoints import restore_run_config
from nvs.run.compose import compose
from tests.conftest import compose_train, fixture_batch
from tests.test_reliability import SMALL, TRAIN, _cli, _error_lines

# Tatarchenko with a narrow merge layer: 2M weights, a 24 MB checkpoint (its default is 13M and 156 MB)
TINY = [*SMALL, "model.fc_dim=64"]


# -- 1. the user's files ---------------------------------------------------------------------------------------------
def test_a_run_that_fails_before_its_first_step_keeps_the_users_files(objects_root, tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    mine = {"csv/mine.csv": "a,b\n1,2\n", "checkpoints/7_net_enc.pth": "weights", "notes.txt": "notes"}
    for name, text in mine.items():
        (run_dir / name).parent.mkdir(parents=True, exist_ok=True)
        (run_dir / name).write_text(text)
    code, stderr = _cli("train", [f"data.root={objects_root}", f"hydra.run.dir={run_dir}", *TRAIN,
                                  "data.loader.batch_size=0"], monkeypatch)
    assert code == 2 and len(_error_lines(stderr)) == 1, stderr[-3000:]
    assert {name: (run_dir / name).read_text() for name in mine if (run_dir / name).is_file()} == mine
    left = sorted(p.relative_to(run_dir).as_posix() for p in run_dir.rglob("*"))
    assert left == ["checkpoints", "checkpoints/7_net_enc.pth", "csv", "csv/mine.csv", "notes.txt"]  # ours gone


# -- 2. last.ckpt every N steps and at the end -----------------------------------------------------------------------
class LastStep(L.Callback):
    """Writes the step ``last.ckpt`` holds at the start of every training step (what a kill -9 there would leave)."""

    def __init__(self, path: str, out: str):
        self.path, self.out = Path(path), Path(out)

    def on_train_batch_start(self, trainer, *args):
        step = torch.load(self.path, weights_only=False, mmap=True)["global_step"] if self.path.is_file() else None
        with self.out.open("a") as f:
            f.write(f"{trainer.global_step} {step}\n")


def _cfg(objects_root, tmp_path, run_dir, *extra, callbacks=None):
    c = compose_train([f"data.root={objects_root}", f"paths.root_dir={tmp_path}", *TRAIN, *TINY, *extra])
    c.paths.output_dir = str(run_dir)
    with open_dict(c.callbacks):
        c.callbacks.update(callbacks or {})
    OmegaConf.resolve(c)
    return c


def test_last_ckpt_is_written_every_n_steps_after_each_validation_and_at_the_end(objects_root, tmp_path):
    from nvs.run.training import run

    run_dir = tmp_path / "run"
    last = run_dir / "checkpoints" / "last.ckpt"
    seen = tmp_path / "seen.txt"
    probe = {"probe": {"_target_": "tests.test_run_state.LastStep", "path": str(last), "out": str(seen)}}
    run(_cfg(objects_root, tmp_path, run_dir, "trainer.max_steps=5", "trainer.val_check_interval=2",
             "callbacks.model_checkpoint.last_every_n_steps=3", "test=false", callbacks=probe), run_dir)
    # validations at 2 and 4, every 3 steps, the end at 5; a stale last (step 2 until the end) before
    assert seen.read_text().splitlines() == ["0 None", "1 None", "2 2", "3 3", "4 4"]
    assert torch.load(last, weights_only=False)["global_step"] == 5


def test_last_every_n_steps_must_be_positive():
    from nvs.run.checkpoints import ModelCheckpoint

    with pytest.raises(UserError, match="callbacks.model_checkpoint.last_every_n_steps=0: expected a positive"):
        ModelCheckpoint(last_every_n_steps=0)


# -- 3. resume in a moved directory, by recorded step, with the whole curve -----------------------------------------
class KillAt(L.Callback):
    def __init__(self, step: int):
        self.step = step

    def on_train_batch_end(self, trainer, *args):
        if trainer.global_step == self.step:
            os.kill(os.getpid(), signal.SIGTERM)


def _rows(path: Path) -> list[tuple[int, str]]:
    with path.open(newline="") as f:
        # the loss and validation rows (the learning rate has rows of its own)
        return [(int(r["step"]), "val" if r.get("val/l1") else "train") for r in csv.DictReader(f)
                if r.get("val/l1") or r.get("train/loss/total")]


def test_a_moved_run_resumes_its_newest_checkpoint_and_keeps_its_curve(objects_root, tmp_path):
    from nvs.run.training import run

    steps = ["trainer.max_steps=4", "trainer.val_check_interval=2", "trainer.log_every_n_steps=1", "test=false"]
    first = tmp_path / "first"
    kill = {"kill": {"_target_": "tests.test_run_state.KillAt", "step": 3}}
    with pytest.raises(Interrupted):
        run(_cfg(objects_root, tmp_path, first, *steps, callbacks=kill), first)
    moved = tmp_path / "moved"
    shutil.move(first, moved)
    assert not first.exists()
    result = run(_cfg(objects_root, tmp_path, moved, *steps), moved)
    assert result["steps"] == 4
    ckpts = moved / "checkpoints"
    names = sorted(p.name for p in ckpts.glob("*.ckpt"))  # no last-v1.ckpt; the best followed the directory
    assert len(names) == 2 and names[0].startswith("best-") and "-v" not in names[0] and names[1] == "last.ckpt"
    assert torch.load(ckpts / "last.ckpt", weights_only=False)["global_step"] == 4
    # every step's row once, the first segment's kept: train rows 0..3 (global steps 1..4), validations at 2 and 4
    # (the steps of their checkpoints)
    assert _rows(moved / "csv" / "metrics.csv") == [(0, "train"), (1, "train"), (2, "val"), (2, "train"),
                                                   (3, "train"), (4, "val")]


def test_a_resumed_auto_run_keeps_the_mode_it_started_in(objects_root, tmp_path, monkeypatch):
    """The probe picks cl for the first segment and fp32 by the resume (a busy probe taken again, other threads): the
    run trains its remaining steps in cl, records that, and says why; an explicit precision is not overridden."""
    from nvs.run import precision
    from nvs.run.training import run

    monkeypatch.setattr(precision.torch.cuda, "is_available", lambda: False)
    fastest = {"ms": {"fp32": 2.0, "cl": 1.0, "bf16_cl": 9.0}}
    monkeypatch.setattr(precision, "probe", lambda refresh=False: dict(fastest["ms"]))
    steps = ["trainer.max_steps=4", "trainer.val_check_interval=2", "test=false", "trainer.precision=auto",
             "channels_last=auto"]
    kill = {"kill": {"_target_": "tests.test_run_state.KillAt", "step": 3}}
    with pytest.raises(Interrupted):
        run(_cfg(objects_root, tmp_path, tmp_path / "run", *steps, callbacks=kill), tmp_path / "run")
    held = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)["callbacks"]
    assert held["PrecisionRecord"]["mode"] == "cl"
    fastest["ms"] = {"fp32": 1.0, "cl": 2.0, "bf16_cl": 9.0}
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        result = run(_cfg(objects_root, tmp_path, tmp_path / "run", *steps), tmp_path / "run")
    assert not [w for w in seen if "exists and is not empty" in str(w.message)]  # a resume is no surprise
    choice = result["precision_choice"]
    assert result["steps"] == 4 and choice["mode"] == "cl" and choice["channels_last"]
    assert "the mode of the run it resumes" in choice["reason"] and "now picks fp32" in choice["reason"]
    fresh = run(_cfg(objects_root, tmp_path, tmp_path / "fresh", *steps[:3], "channels_last=auto"), tmp_path / "fresh")
    assert fresh["precision_choice"]["mode"] == "fp32"  # a new run takes the probe's pick
    # an explicit precision and layout stay as asked, whatever the checkpoint recorded
    assert precision.kept_through_resume(precision.choose("32-true", False), held["PrecisionRecord"]).mode == "fp32"


def test_resume_picks_the_newest_checkpoint_by_its_step_not_its_name(tmp_path):
    for name, step in [("last.ckpt", 2), ("last-v1.ckpt", 8), ("best-6.ckpt", 6)]:
        torch.save({"global_step": step, "state_dict": {"w": torch.zeros(2)}}, tmp_path / name)
    assert newest_checkpoint(tmp_path) == (tmp_path / "last-v1.ckpt", 8)
    assert resume_checkpoint("auto", tmp_path) == (str(tmp_path / "last-v1.ckpt"), 8)
    torch.save({"global_step": 8, "state_dict": {}}, tmp_path / "best-8.ckpt")
    assert newest_checkpoint(tmp_path)[0].name == "last-v1.ckpt"  # a tie goes to a last
    assert resume_checkpoint("null", tmp_path) is None and resume_checkpoint("auto", tmp_path / "none") is None


# -- 4. diverged runs ------------------------------------------------------------------------------------------------
def _module(tmp_path, nonfinite="stop"):
    cfg = compose_train([*TINY, f"paths.root_dir={tmp_path}", f"nonfinite={nonfinite}"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    module = build_module(cfg)
    module.log = lambda *a, **k: None
    return module


def test_a_diverged_run_stops_with_one_line_and_writes_no_checkpoint(objects_root, tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    code, stderr = _cli("train", [f"data.root={objects_root}", f"hydra.run.dir={run_dir}", *TRAIN,
                                  "trainer.max_steps=4", "optim.lr=1e6"], monkeypatch)
    lines = _error_lines(stderr)
    assert code == 2 and len(lines) == 1 and "Traceback" not in stderr, stderr[-3000:]
    assert "non-finite" in lines[0] and "Lower optim.lr" in lines[0], lines[0]
    assert not list(run_dir.glob("checkpoints/*.ckpt")) and not (run_dir / "metrics.json").exists()


@pytest.mark.parametrize("nonfinite", ["stop", "skip"])
def test_a_non_finite_gradient_stops_or_is_dropped(tmp_path, nonfinite):
    module = _module(tmp_path, nonfinite)
    params = list(module.net.parameters())
    for p in params:
        p.grad = torch.zeros_like(p)
    params[0].grad[(0,) * params[0].dim()] = float("nan")
    if nonfinite == "stop":
        with pytest.raises(NonFiniteLossError, match="non-finite gradient at step 0"):
            module.on_before_optimizer_step(None)
        return
    module.on_before_optimizer_step(None)
    assert all(p.grad is None for p in params)  # the optimiser steps nothing
    module.on_train_batch_end(None, fixture_batch(), 0)  # the weights are finite: no error


def test_non_finite_weights_stop_even_with_skip_and_are_never_saved(tmp_path):
    module = _module(tmp_path, "skip")
    with torch.no_grad():
        p = next(module.net.parameters())
        p[(0,) * p.dim()] = float("inf")
    with pytest.raises(NonFiniteLossError, match="non-finite weights after step 0"):
        module.on_train_batch_end(None, fixture_batch(), 0)
    with pytest.raises(NonFiniteLossError, match="checkpoint not written"):
        module.on_save_checkpoint({"state_dict": module.state_dict()})


# -- 5. the content hash ---------------------------------------------------------------------------------------------
@pytest.fixture()
def saved(tmp_path):
    """A checkpoint as training writes it (through the module's on_save_checkpoint), without training."""
    module = _module(tmp_path)
    ckpt = {"state_dict": module.state_dict(), "global_step": 3}
    module.on_save_checkpoint(ckpt)
    ckpt["nvs_config"] = module.run_config
    path = tmp_path / "run.ckpt"
    torch.save(ckpt, path)
    return path


def _edit(path: Path, change) -> None:
    """Change a checkpoint's contents and write it again: every zip CRC is valid, only the hash can tell."""
    ckpt = torch.load(path, weights_only=False)
    change(ckpt)
    torch.save(ckpt, path)


def test_a_checkpoint_whose_weights_fail_their_hash_is_refused_everywhere(objects_root, saved, tmp_path,
                                                                          monkeypatch):
    ckpt = torch.load(saved, weights_only=False)
    assert ckpt[KEY] == digest(ckpt["state_dict"])

    def flip(c):
        key = next(k for k, v in c["state_dict"].items() if v.is_floating_point())
        c["state_dict"][key][(0,) * c["state_dict"][key].dim()] += 1.0

    _edit(saved, flip)
    with zipfile.ZipFile(saved) as zf:
        assert zf.testzip() is None
    message = f"{saved}: corrupt checkpoint (its weights do not match the content hash stored when it was written)"
    code, stderr = _cli("evaluate", [f"ckpt_path={saved}", f"data.root={objects_root}", f"out_dir={tmp_path / 'e'}",
                                     f"hydra.run.dir={tmp_path / 'h'}"], monkeypatch)
    assert code == 2 and len(_error_lines(stderr)) == 1 and message in stderr, stderr[-3000:]
    assert not (tmp_path / "e" / "metrics.json").exists()
    cfg = compose("evaluate", [f"paths.root_dir={tmp_path}", f"ckpt_path={saved}"])
    cfg.paths.output_dir = cfg.out_dir = str(tmp_path)
    with pytest.raises(UserError, match="do not match the content hash"):  # the viewer's and the figures' way in
        restore_run_config(cfg)
    with pytest.raises(UserError, match="do not match the content hash"):  # and the resume's
        resume_checkpoint(str(saved), tmp_path)


def test_a_checkpoint_without_a_hash_loads_with_one_notice(objects_root, saved, tmp_path, monkeypatch):
    _edit(saved, lambda c: c.pop(KEY))  # as written before the hash, or by an older nvs.convert
    code, stderr = _cli("evaluate", [f"ckpt_path={saved}", f"data.root={objects_root}", f"out_dir={tmp_path / 'e'}",
                                     f"hydra.run.dir={tmp_path / 'h'}"], monkeypatch)
    assert code == 0, stderr[-3000:]
    notes = [ln for ln in stderr.splitlines() if "content hash" in ln]
    assert notes == [f"note: {saved} holds no content hash of its weights (written before nvs stored one): loaded "
                     "unverified"]
