"""Faults in ``nvs.evaluate`` (issue 37): stopped by SIGTERM/SIGINT or ``kill -9`` mid-run (also while writing its
results) it leaves the previous metrics.json and per-image CSV as they were, and a re-run completes; a truncated or
corrupt checkpoint is one error naming it.
"""

from __future__ import annotations

import json
import os
import signal
import sys
from pathlib import Path

import pytest
import torch

from nvs.core import atomic
from nvs.module.lightning_module import NVSModule
from tests.test_disk_full import FullDisk, _Writer
from tests.test_reliability import _cli, _error_lines
from tests.test_run_state import saved  # noqa: F401 - the fixture: a checkpoint as training writes it


@pytest.fixture(autouse=True)
def _real_disk(monkeypatch):
    monkeypatch.setattr(atomic, "os", os)


def _files(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in d.iterdir() if p.is_file()} if d.is_dir() else {}


def _visible(d: Path) -> dict[str, bytes]:
    return {name: data for name, data in _files(d).items() if not name.startswith(".")}


class KillingWriter(_Writer):
    """Writes half of what it is given, then the process is killed (``kill -9`` in the middle of a write)."""

    def write(self, data: bytes) -> int:
        self.f.write(data[: len(data) // 2])
        self.f.flush()
        os.kill(os.getpid(), signal.SIGKILL)
        return 0


class KilledWhileWriting(FullDisk):
    """``nvs.core.atomic``'s os module where the write of a file named ``name`` (its temp file) kills the process."""

    def __init__(self, name: str):
        super().__init__(0)
        self.name = name

    def fdopen(self, fd, mode):
        path = os.readlink(f"/proc/self/fd/{fd}")  # mkstemp's name: .<final name>.<random>.tmp
        f = os.fdopen(fd, mode)
        return KillingWriter(self, f) if Path(path).name.startswith(f".{self.name}.") else f


linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fork and /proc/self/fd")


def _killed_in_a_fork(name: str, work) -> None:
    """``work()`` in a forked copy of this process whose write of a file named ``name`` kills it (kill -9)."""
    pid = os.fork()
    if pid == 0:
        try:
            torch.set_num_threads(1)  # as a DataLoader worker does: no OpenMP pool carried across the fork
            atomic.os = KilledWhileWriting(name)
            work()
        finally:
            os._exit(1)  # (not reached: the write kills it)
    status = os.waitpid(pid, 0)[1]
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL, f"wait status {status}"


def _evaluate_args(root: Path, out: Path, tmp_path: Path) -> list[str]:
    # a reference model (no training), one test pair per batch: 4 batches, a signal can land between them
    return ["model=copy_source", "data=chairs", f"data.root={root}", f"out_dir={out}", f"hydra.run.dir={tmp_path / 'h'}",
            "data.loader.eval_batch_size=1", "+trainer.enable_progress_bar=false"]


def _earlier_results(out: Path) -> dict[str, bytes]:
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text('{"test": {"l1": 0.5}}\n')
    (out / "test_per_image.csv").write_text("index,l1\n0,0.5\n")
    return _files(out)


@pytest.mark.parametrize("signum, batch", [(signal.SIGTERM, 1), (signal.SIGINT, 0), (signal.SIGTERM, 3)],
                         ids=["SIGTERM mid-test", "SIGINT at the first batch", "SIGTERM at the last batch"])
def test_evaluate_stopped_by_a_signal_writes_nothing_and_a_rerun_completes(objects_root, tmp_path, monkeypatch,
                                                                          signum, batch):
    """Before: SIGTERM at the last (or only) batch was ignored and the run exited 0; before it, Lightning's stop
    (a SystemExit) left without a line."""
    out = tmp_path / "eval"
    before = _earlier_results(out)
    real_step = NVSModule.test_step
    handler = signal.getsignal(signum)

    def signalled_step(self, b, batch_idx, *args, **kwargs):
        if batch_idx == batch:
            os.kill(os.getpid(), signum)
        return real_step(self, b, batch_idx, *args, **kwargs)

    monkeypatch.setattr(NVSModule, "test_step", signalled_step)
    code, stderr = _cli("evaluate", _evaluate_args(objects_root, out, tmp_path), monkeypatch)
    name = signal.Signals(signum).name
    assert code == 128 + signum and "Traceback" not in stderr, stderr[-3000:]
    assert [ln for ln in stderr.splitlines() if "interrupted" in ln] == [
        f"interrupted by {name} during the evaluation: nothing written (metrics.json and test_per_image.csv are "
        "written when it completes); run the same command again"], stderr[-3000:]
    assert _files(out) == before  # the earlier evaluation's files, no temp file
    assert signal.getsignal(signum) is handler  # the evaluation's handler is gone with it

    monkeypatch.setattr(NVSModule, "test_step", real_step)
    code, stderr = _cli("evaluate", _evaluate_args(objects_root, out, tmp_path), monkeypatch)
    assert code == 0, stderr[-3000:]
    assert json.loads((out / "metrics.json").read_text())["test"]["n_pairs"] == 4
    assert len((out / "test_per_image.csv").read_text().splitlines()) == 1 + 4


@linux_only
@pytest.mark.parametrize("name", ["test_per_image.csv", "metrics.json"])
def test_evaluate_killed_while_writing_its_results_leaves_the_previous_ones(objects_root, tmp_path, monkeypatch,
                                                                            name):
    out = tmp_path / "eval"
    before = _earlier_results(out)

    _killed_in_a_fork(name, lambda: _cli("evaluate", _evaluate_args(objects_root, out, tmp_path), monkeypatch))
    assert _visible(out) == before  # a killed writer leaves only hidden temp files, never a prefix in place
    code, stderr = _cli("evaluate", _evaluate_args(objects_root, out, tmp_path), monkeypatch)
    assert code == 0, stderr[-3000:]
    assert json.loads((out / "metrics.json").read_text())["test"]["n_pairs"] == 4


def _truncated(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


@pytest.mark.parametrize("damage, says", [
    (_truncated, "not a readable checkpoint: incomplete (no zip directory: a write cut short, e.g. by a kill)"),
    (lambda p: p.write_bytes(b""), "not a readable checkpoint: incomplete"),
    (lambda p: p.write_bytes(b"not a checkpoint at all"), "not a readable checkpoint: incomplete"),
], ids=["truncated", "zero bytes", "not a zip"])
def test_evaluate_of_a_damaged_checkpoint_is_one_error_naming_it(objects_root, saved, tmp_path, monkeypatch,  # noqa: F811
                                                                 damage, says):
    out = tmp_path / "eval"
    before = _earlier_results(out)
    damage(saved)
    code, stderr = _cli("evaluate", [f"ckpt_path={saved}", f"data.root={objects_root}", f"out_dir={out}",
                                     f"hydra.run.dir={tmp_path / 'h'}"], monkeypatch)
    lines = _error_lines(stderr)
    assert code == 2 and "Traceback" not in stderr and len(lines) == 1, stderr[-3000:]
    assert lines[0].startswith(f"error: {saved}: {says}") and _files(out) == before, lines
