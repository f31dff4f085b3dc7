"""Disk full (issue 37): every artifact writer, given a disk that fills while it writes, stops with one error naming
the file and saying the disk is full, leaves the previous file (or none) in place and no temp file; a training run
whose checkpoint write fails keeps its previous checkpoint loadable, and the same command resumes from it.

The fast form fills nvs's one way of writing files (``nvs.core.atomic``: its ``os.fdopen``) with ENOSPC after a
number of bytes, as a disk does; the slow form lowers the real file-size limit (``RLIMIT_FSIZE``: EFBIG from the
kernel) of a ``python -m nvs.train`` process at a step.
"""

from __future__ import annotations

import errno
import json
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import lightning as L
import pytest
import torch

from nvs.core import atomic
from nvs.core.errors import UserError, user_message
from nvs.run.artifacts import write_run_results
from nvs.run.checkpoint_files import read_checkpoint
from nvs.run.checkpoints import AtomicCheckpointIO, CheckpointWriteError
from tests.test_fault_injection import USER_FILES, _args, _user_dir, _user_files, check_resumed
from tests.test_reliability import REPO, _cli, _error_lines

FULL = "no space left on device (the disk is full)"


class _Writer:
    """A file of a disk with ``disk.free`` bytes left: what fits is written, then ENOSPC (as write(2) answers)."""

    def __init__(self, disk: FullDisk, f):
        self.disk, self.f = disk, f

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()

    def write(self, data: bytes) -> int:
        n = min(len(data), self.disk.free)
        self.f.write(data[:n])
        self.disk.free -= n
        if n < len(data):
            self.f.flush()
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return n

    def __getattr__(self, name):
        return getattr(self.f, name)


class FullDisk:
    """``nvs.core.atomic``'s os module on a disk with ``free`` bytes left; ``install`` puts it in place."""

    def __init__(self, free: int):
        self.free = free

    def __getattr__(self, name):
        return getattr(os, name)

    def fdopen(self, fd, mode):
        return _Writer(self, os.fdopen(fd, mode))

    def install(self) -> FullDisk:
        atomic.os = self
        return self


@pytest.fixture(autouse=True)
def _real_disk(monkeypatch):
    monkeypatch.setattr(atomic, "os", os)  # whatever a test installs, the real os module is back after it


def _hidden(d: Path) -> list[str]:
    return sorted(p.name for p in d.rglob(".*"))


def _assert_one_disk_full_error(err: BaseException, path: Path) -> None:
    message = user_message(err)  # what the entry points print as the one line
    assert message is not None and str(path) in message and FULL in message, message


# -- each writer ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("free", [0, 100], ids=["nothing fits", "the start fits"])
def test_metrics_and_per_image_csv_are_written_both_or_neither(tmp_path, free):
    rows = [{"id_src": "a", "id_tgt": "b", "l1": 0.1}]
    write_run_results(tmp_path, {"l1": 0.1}, rows)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    FullDisk(free).install()
    with pytest.raises(UserError) as err:
        write_run_results(tmp_path, {"l1": 0.2, "pad": "x" * 500}, rows * 50)
    failed = tmp_path / ("test_per_image.csv" if free < 400 else "metrics.json")
    _assert_one_disk_full_error(err.value, failed)
    assert "the previous file is unchanged" in str(err.value)
    assert isinstance(err.value, OSError) and err.value.errno == errno.ENOSPC  # callers catching OSError still do
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # the old pair, no temp file


def test_a_second_file_that_does_not_fit_keeps_the_first_one_old_too(tmp_path):
    write_run_results(tmp_path, {"l1": 0.1}, [{"l1": 0.1}])
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    csv_bytes = len(b"l1\n0.2\n")
    FullDisk(csv_bytes + 5).install()  # the new CSV fits, metrics.json does not
    with pytest.raises(UserError) as err:
        write_run_results(tmp_path, {"l1": 0.2}, [{"l1": 0.2}])
    _assert_one_disk_full_error(err.value, tmp_path / "metrics.json")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_a_checkpoint_that_does_not_fit_keeps_the_previous_one(tmp_path):
    path = tmp_path / "last.ckpt"
    AtomicCheckpointIO().save_checkpoint({"state_dict": {"w": torch.zeros(10)}, "global_step": 2}, path)
    FullDisk(10_000).install()
    with pytest.raises(CheckpointWriteError) as err:
        AtomicCheckpointIO().save_checkpoint({"state_dict": {"w": torch.ones(100_000)}, "global_step": 4}, path)
    _assert_one_disk_full_error(err.value, path)
    assert "training stopped, the previous one is unchanged" in str(err.value)
    assert read_checkpoint(path)["global_step"] == 2 and _hidden(tmp_path) == []


def test_the_training_curve_is_cut_back_to_whole_rows(tmp_path, monkeypatch):
    from lightning.pytorch.loggers import CSVLogger

    from nvs.run.csv_log import continue_from

    logger = CSVLogger(tmp_path, name="csv", version="")
    continue_from(logger, None)
    logger.log_metrics({"train/loss/total": 0.5}, step=0)
    logger.save()
    path = tmp_path / "csv" / "metrics.csv"
    before = path.read_bytes()
    real_open = logger.experiment._fs.open
    disk = FullDisk(7)

    def full_open(name, mode="r", **kwargs):  # Lightning appends the rows through its file system's open
        f = real_open(name, mode, **kwargs)  # (text modes open the binary one through this too: left as it is)
        return _Writer(disk, f) if mode in ("a", "w") else f

    monkeypatch.setattr(logger.experiment._fs, "open", full_open)  # (fsspec shares the instance: put back after)
    for step in range(1, 4):
        logger.log_metrics({"train/loss/total": 0.123456789}, step=step)
    with pytest.raises(UserError) as err:
        logger.save()
    _assert_one_disk_full_error(err.value, path)
    assert path.read_bytes() == before  # no partial row, which a resume would read as a number


def test_the_sweep_record_and_the_exported_jobs_keep_their_previous_files(tmp_path):
    from nvs import sweep
    from nvs.sweep.export import export_jobs
    from tests.test_sweep import _fake_result, _study

    study = _study(tmp_path)
    root = tmp_path / "runs" / study.scale
    job = next(j for j in sweep.plan(study, root) if j.row.name == "copy")
    _fake_result(job, root, 0.40)  # writes sweep_job.json
    record = job.dir / sweep.JOB_RECORD
    old_record = record.read_bytes()
    dest = tmp_path / "results" / "jobs" / study.scale
    assert [p.name for p in export_jobs([sweep.refresh(job)], dest)] == ["copy_s0"]
    exported = {p.relative_to(dest).as_posix(): p.read_bytes() for p in dest.rglob("*") if p.is_file()}

    FullDisk(10).install()
    with pytest.raises(UserError) as err:
        sweep.prepare_job_dir(job, root)
    _assert_one_disk_full_error(err.value, record)
    assert record.read_bytes() == old_record and _hidden(job.dir) == [".hydra"]

    (job.dir / "metrics.json").write_text(json.dumps({"test": {"l1": 0.3}}))  # a newer result to export
    FullDisk(len(old_record) + 10).install()  # the first file fits, the second does not
    with pytest.raises(UserError) as err:
        export_jobs([job], dest)
    _assert_one_disk_full_error(err.value, dest / "copy_s0")
    assert {p.relative_to(dest).as_posix(): p.read_bytes() for p in dest.rglob("*") if p.is_file()} == exported
    assert [p.name for p in dest.iterdir()] == ["copy_s0"]  # no half-filled export beside it


def test_the_tables_are_replaced_all_or_none(tmp_path):
    from nvs import sweep
    from nvs.sweep.collect import collect
    from nvs.sweep.tables import render_csv, write_results
    from tests.test_sweep import _fake_result, _study

    study = _study(tmp_path)
    root = tmp_path / "runs" / study.scale
    jobs = sweep.plan(study, root)
    _fake_result(jobs[0], root, 0.10)
    results = tmp_path / "results"
    write_results(study, sweep.plan(study, root), results, "first")
    before = {p.name: p.read_bytes() for p in results.iterdir()}
    _fake_result(jobs[1], root, 0.12)
    FullDisk(len(render_csv(collect(sweep.plan(study, root))).encode()) + 10).install()  # the CSV fits, not the rest
    with pytest.raises(UserError) as err:
        write_results(study, sweep.plan(study, root), results, "second")
    _assert_one_disk_full_error(err.value, results / "fab.md")
    assert {p.name: p.read_bytes() for p in results.iterdir()} == before  # the CSV too: not a new one beside the old


# -- a training run ------------------------------------------------------------------------------------------------
class DiskFillsAt(L.Callback):
    """At the end of training step ``step`` the disk has ``free`` bytes left (for nvs's writes: the checkpoints)."""

    def __init__(self, step: int, free: int):
        self.step, self.free = step, free

    def on_train_batch_end(self, trainer, *args):
        if trainer.global_step == self.step:
            FullDisk(self.free).install()


STEPS = 3


def test_a_disk_that_fills_in_a_checkpoint_write_stops_the_run_and_the_same_command_resumes(objects_root, tmp_path,
                                                                                           monkeypatch):
    """last.ckpt every step; the one of step 2 does not fit: one line naming last.ckpt, exit 2; last.ckpt still
    holds step 1, whole; then, with space again, the same command resumes from step 1 to the end."""
    run_dir = tmp_path / "run"
    _user_dir(run_dir)
    every_step = ["callbacks.model_checkpoint.last_every_n_steps=1"]
    fill = ["+callbacks.fill._target_=tests.test_disk_full.DiskFillsAt", "+callbacks.fill.step=2",
            "+callbacks.fill.free=1000000"]
    code, stderr = _cli("train", [*_args(objects_root, run_dir, STEPS, tmp_path / "filled.txt"), *every_step, *fill],
                        monkeypatch)
    last = run_dir / "checkpoints" / "last.ckpt"
    assert code == 2 and "Traceback" not in stderr and _error_lines(stderr) == [
        f"error: cannot write checkpoint {last}: {FULL}; training stopped, the previous one is unchanged (free "
        "space or fix the permissions, then resume with the same command)"], stderr[-3000:]
    assert read_checkpoint(last)["global_step"] == 1  # whole: zip, CRCs, content hash
    assert _hidden(run_dir / "checkpoints") == [] and not (run_dir / "metrics.json").exists()
    assert _user_files(run_dir) == USER_FILES

    atomic.os = os  # space again
    code, stderr = _cli("train", [*_args(objects_root, run_dir, STEPS, tmp_path / "resumed.txt"), *every_step],
                        monkeypatch)
    assert code == 0, stderr[-3000:]
    check_resumed(run_dir, tmp_path / "resumed.txt", 1, STEPS, "disk full at step 2")


# -- the real kernel: a file-size limit ----------------------------------------------------------------------------
class FileSizeLimitAt(L.Callback):
    """At the end of training step ``step``: no file of this process may grow past ``limit`` bytes (EFBIG)."""

    def __init__(self, step: int, limit: int):
        self.step, self.limit = step, limit

    def on_train_batch_end(self, trainer, *args):
        if trainer.global_step == self.step:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails with EFBIG instead of killing us
            resource.setrlimit(resource.RLIMIT_FSIZE, (self.limit, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(resource, "RLIMIT_FSIZE"), reason="no file-size limit on this platform")
def test_the_kernel_refusing_a_checkpoint_write_stops_the_run_and_the_same_command_resumes(objects_root, tmp_path):
    run_dir = tmp_path / "run"
    _user_dir(run_dir)
    argv = [*_args(objects_root, run_dir, STEPS, tmp_path / "limited.txt"),
            "callbacks.model_checkpoint.last_every_n_steps=1"]
    limit = ["+callbacks.limit._target_=tests.test_disk_full.FileSizeLimitAt", "+callbacks.limit.step=2",
             "+callbacks.limit.limit=1000000"]  # the CSV log and Hydra's log stay far below it
    res = subprocess.run([sys.executable, "-m", "nvs.train", *argv, *limit], cwd=REPO, capture_output=True,
                         text=True, timeout=900)
    last = run_dir / "checkpoints" / "last.ckpt"
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr[-3000:]
    assert _error_lines(res.stderr) == [
        f"error: cannot write checkpoint {last}: file too large for this process's file-size limit (ulimit -f); "
        "training stopped, the previous one is unchanged (free space or fix the permissions, then resume with the "
        "same command)"], res.stderr[-3000:]
    assert read_checkpoint(last)["global_step"] == 1 and _hidden(run_dir / "checkpoints") == []
    resumed = subprocess.run([sys.executable, "-m", "nvs.train", *_args(objects_root, run_dir, STEPS,
                                                                         tmp_path / "resumed.txt"),
                              "callbacks.model_checkpoint.last_every_n_steps=1"], cwd=REPO, capture_output=True,
                             text=True, timeout=900)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    check_resumed(run_dir, tmp_path / "resumed.txt", 1, STEPS, "file-size limit at step 2")


def test_the_run_config_that_does_not_fit_is_one_line(tmp_path, monkeypatch):
    from lightning.pytorch.loggers import CSVLogger
    from omegaconf import OmegaConf

    from nvs.run.loggers import log_run_config

    logger = CSVLogger(tmp_path, name="csv", version="")

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(logger.experiment, "log_hparams", full)  # Lightning's own write of hparams.yaml
    with pytest.raises(UserError) as err:
        log_run_config([logger], OmegaConf.create({"seed": 0}))
    _assert_one_disk_full_error(err.value, tmp_path / "csv" / "hparams.yaml")
