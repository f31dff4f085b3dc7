"""Fault injection (issue 37): ``nvs.train`` killed (``kill -9`` at a random step, SIGTERM; one process and
2-process DDP), then resumed. After each fault the suite checks that the resume continues from the last completed
step within the checkpoint interval (``callbacks.model_checkpoint.last_every_n_steps``), that the user's files in
the run directory are unchanged, that the training curve (``csv/metrics.csv``) has every step once, and that a run
that exits 0 trained its steps and holds finite weights.

The fast form injects the faults from inside the run (a callback at a random step: SIGKILL in a forked copy of this
process, SIGTERM in this process); the slow form sends them from outside, at a random moment, to ``python -m
nvs.train``, and covers 2-process DDP: the stop, the resume at the stopped step on both ranks, and SIGTERM to one
rank in the test after training. Disk full: tests/test_disk_full.py; evaluate and the sweep runner:
tests/test_fault_evaluate.py, tests/test_fault_sweep.py.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import lightning as L
import pytest
import torch

from nvs.run.checkpoint_files import read_checkpoint
from tests.test_reliability import TRAIN, _cli
from tests.test_run_state import TINY, _rows

REPO = Path(__file__).resolve().parents[1]
INTERVAL = 2  # callbacks.model_checkpoint.last_every_n_steps: a kill -9 redoes at most this many steps
VAL_EVERY = 3
USER_FILES = {"notes.txt": "notes", "csv/mine.csv": "a,b\n1,2\n", "checkpoints/7_net_enc.pth": "weights"}
SEED = int(os.environ.get("NVS_FAULT_SEED", "37"))  # the random steps and moments; printed in every failure


def _args(root: Path, run_dir: Path, steps: int, probe: Path) -> list[str]:
    # LastStep (tests/test_run_state.py) writes "<step> <step last.ckpt holds>" at the start of every step, flushed:
    # where the run was when the fault hit, and where its resume started.
    return [f"data.root={root}", f"hydra.run.dir={run_dir}", *TRAIN, *TINY, f"trainer.max_steps={steps}",
            f"trainer.val_check_interval={VAL_EVERY}", "trainer.log_every_n_steps=1", "test=false",
            f"callbacks.model_checkpoint.last_every_n_steps={INTERVAL}",
            "+callbacks.probe._target_=tests.test_run_state.LastStep",
            f"+callbacks.probe.path={run_dir / 'checkpoints' / 'last.ckpt'}", f"+callbacks.probe.out={probe}"]


def _kill_at(step: int, signum: int) -> list[str]:
    return ["+callbacks.kill._target_=tests.test_reliability.SignalAt", f"+callbacks.kill.step={step}",
            f"+callbacks.kill.signum={int(signum)}"]


def _user_dir(run_dir: Path) -> None:
    for name, text in USER_FILES.items():
        (run_dir / name).parent.mkdir(parents=True, exist_ok=True)
        (run_dir / name).write_text(text)


def _user_files(run_dir: Path) -> dict[str, str | None]:
    return {name: (run_dir / name).read_text() if (run_dir / name).is_file() else None for name in USER_FILES}


def _steps(probe: Path) -> list[int]:
    return [int(line.split()[0]) for line in probe.read_text().splitlines()] if probe.is_file() else []


def _last_step(run_dir: Path) -> int:
    return int(read_checkpoint(run_dir / "checkpoints" / "last.ckpt")["global_step"])  # whole, its hash matching


def check_after_fault(run_dir: Path, completed: int, why: str) -> int:
    """What a fault after ``completed`` training steps may leave: a whole last.ckpt at most INTERVAL steps back, the
    user's files, no results; -> the step last.ckpt holds."""
    held = _last_step(run_dir)
    assert completed - INTERVAL <= held <= completed, f"{why}: last.ckpt at step {held}, {completed} steps done"
    assert _user_files(run_dir) == USER_FILES, why
    assert not (run_dir / "metrics.json").exists(), why
    return held


def check_resumed(run_dir: Path, probe: Path, held: int, steps: int, why: str) -> None:
    """The resume (exit 0) started at the checkpoint's step, trained to ``steps`` with finite weights, kept the
    user's files and logged every step of the curve once."""
    assert _steps(probe)[0] == held, f"{why}: resumed at step {_steps(probe)[0]}, last.ckpt held {held}"
    assert json.loads((run_dir / "metrics.json").read_text())["steps"] == steps > 0, why
    weights = read_checkpoint(run_dir / "checkpoints" / "last.ckpt")["state_dict"]
    assert all(torch.isfinite(w).all() for w in weights.values() if w.is_floating_point()), why
    assert _user_files(run_dir) == USER_FILES, why
    rows = _rows(run_dir / "csv" / "metrics.csv")
    assert sorted(s for s, kind in rows if kind == "train") == list(range(steps)), f"{why}: {rows}"
    assert sorted(s for s, kind in rows if kind == "val") == list(range(VAL_EVERY, steps + 1, VAL_EVERY)), why


# -- the fast form: the fault at a random step, from inside the run ---------------------------------------------------
FAST_STEPS = 5


def _killed_in_a_fork(argv: list[str], monkeypatch) -> int:
    """``nvs.train *argv`` in a forked copy of this process (no second interpreter start) -> its wait status."""
    pid = os.fork()
    if pid == 0:  # the child: it dies by its kill callback, or leaves with its exit code
        code = 1
        try:
            torch.set_num_threads(1)  # as a DataLoader worker does: no OpenMP pool carried across the fork
            code = _cli("train", argv, monkeypatch)[0]
        finally:
            os._exit(code)
    return os.waitpid(pid, 0)[1]


@pytest.mark.parametrize("fault", ["kill -9", "SIGTERM"])
def test_a_fault_at_a_random_step_resumes_within_the_interval(objects_root, tmp_path, monkeypatch, fault):
    """kill -9 at a random step past the first last.ckpt; SIGTERM at a step with a validation due after it (the
    stop waits for it: a checkpoint saved before it resumed past it, and the curve lost its row)."""
    step = random.Random(f"{SEED} {fault}").randint(INTERVAL + 1, FAST_STEPS - 1) if fault == "kill -9" else VAL_EVERY
    why = f"{fault} at step {step} (NVS_FAULT_SEED={SEED})"
    run_dir = tmp_path / "run"
    _user_dir(run_dir)
    argv = _args(objects_root, run_dir, FAST_STEPS, tmp_path / "killed.txt")
    if fault == "kill -9":
        status = _killed_in_a_fork([*argv, *_kill_at(step, signal.SIGKILL)], monkeypatch)
        assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL, f"{why}: wait status {status}"
    else:
        code, stderr = _cli("train", [*argv, *_kill_at(step, signal.SIGTERM)], monkeypatch)
        assert code == 143 and "Traceback" not in stderr, f"{why}: {stderr[-3000:]}"
        assert [ln for ln in stderr.splitlines() if ln.startswith("interrupted by SIGTERM")] == [
            ln for ln in stderr.splitlines() if f"at step {step}: saved" in ln], why
    held = check_after_fault(run_dir, step, why)
    if fault == "SIGTERM":
        assert held == step, why  # SIGTERM saves the step it stopped at: nothing is redone
    code, stderr = _cli("train", _args(objects_root, run_dir, FAST_STEPS, tmp_path / "resumed.txt"), monkeypatch)
    assert code == 0, f"{why}: {stderr[-3000:]}"
    check_resumed(run_dir, tmp_path / "resumed.txt", held, FAST_STEPS, why)


# -- the slow form: the fault from outside, at a random moment --------------------------------------------------------
SLOW_STEPS = 12


def _train(argv: list[str], **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "nvs.train", *argv], cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, **kwargs)


def _wait_for_step(proc: subprocess.Popen, probe: Path, step: int, timeout_s: float = 600) -> None:
    deadline = time.monotonic() + timeout_s
    while (not _steps(probe) or _steps(probe)[-1] < step) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, f"the run ended before step {step}: {proc.stderr.read()[-3000:]}"


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGKILL, signal.SIGTERM], ids=["kill -9", "SIGTERM"])
def test_nvs_train_killed_from_outside_at_a_random_moment_resumes(objects_root, tmp_path, signum):
    rng = random.Random(f"{SEED} {int(signum)}")
    step, delay = rng.randint(1, SLOW_STEPS - 2), rng.uniform(0, 0.5)
    why = f"{signal.Signals(signum).name} {delay:.2f} s into step {step} (NVS_FAULT_SEED={SEED})"
    run_dir, probe = tmp_path / "run", tmp_path / "killed.txt"
    _user_dir(run_dir)
    proc = _train(_args(objects_root, run_dir, SLOW_STEPS, probe))
    _wait_for_step(proc, probe, step)
    time.sleep(delay)  # somewhere in a step, a validation or a checkpoint write
    proc.send_signal(signum)
    stderr = proc.communicate(timeout=300)[1]
    # the run was in this step (or in the validation or checkpoint write after it): it may have completed
    completed = _steps(probe)[-1] + 1
    if signum == signal.SIGKILL:
        assert proc.returncode == -signal.SIGKILL, why
    else:
        assert proc.returncode == 143 and "Traceback" not in stderr, f"{why}: {stderr[-3000:]}"
        saved = re.search(r"interrupted by SIGTERM at step (\d+): saved", stderr.strip().splitlines()[-1])
        assert saved and int(saved.group(1)) == _last_step(run_dir) == completed, f"{why}: {stderr[-3000:]}"
    held = check_after_fault(run_dir, completed, why)
    resumed = _train(_args(objects_root, run_dir, SLOW_STEPS, tmp_path / "resumed.txt"))
    assert resumed.wait(timeout=900) == 0, f"{why}: {resumed.stderr.read()[-3000:]}"
    check_resumed(run_dir, tmp_path / "resumed.txt", held, SLOW_STEPS, why)


def _children(pid: int) -> list[int]:
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # the process ended meanwhile
            continue
        if int(fields[1]) == pid:
            kids.append(int(stat.parent.name))
    return kids


def _alive(pid: int) -> bool:
    try:  # a zombie (ended, not yet reaped) counts as ended
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads the process table in /proc")
@pytest.mark.parametrize("target", ["rank 0", "rank 1", "both"])
def test_sigterm_stops_both_ranks_of_a_ddp_run_promptly(objects_root, tmp_path, target):
    """A cluster's preemption: SIGTERM to a 2-process DDP run (CPU, gloo) ends both ranks within seconds, rank 0
    saves a whole last.ckpt at the step the one resume line names, exit 143 (they used to wait in a collective)."""
    run_dir, probe = tmp_path / "run", tmp_path / "probe.txt"
    _user_dir(run_dir)
    argv = [*_args(objects_root, run_dir, 10_000, probe), "trainer.accelerator=cpu", "trainer.devices=2",
            "trainer.strategy=ddp", "data.loader.batch_size=1"]
    proc = _train(argv, start_new_session=True)
    _wait_for_step(proc, probe, 3)  # rank 0's steps (the probe writes on every rank; both at the same steps)
    ranks = [proc.pid, *_children(proc.pid)]
    assert len(ranks) == 2, ranks
    sent = time.monotonic()
    if target == "both":
        os.killpg(proc.pid, signal.SIGTERM)  # as a scheduler signals a job's processes
    else:
        os.kill(ranks[0 if target == "rank 0" else 1], signal.SIGTERM)
    try:
        stderr = proc.communicate(timeout=120)[1]
    finally:
        for pid in ranks:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
    while any(_alive(pid) for pid in ranks) and time.monotonic() - sent < 120:
        time.sleep(0.1)
    took = time.monotonic() - sent
    assert not any(_alive(pid) for pid in ranks) and took < 60, f"ranks alive {took:.0f} s after SIGTERM"
    assert proc.returncode == 143 and "Traceback" not in stderr, stderr[-3000:]
    lines = [ln for ln in stderr.splitlines() if ln.startswith("interrupted by")]
    assert len(lines) == 1 and "resume with: python -m nvs.train " in lines[0], stderr[-3000:]
    step = int(re.search(r"at step (\d+): saved", lines[0]).group(1))
    assert step == _last_step(run_dir) >= 3
    assert _user_files(run_dir) == USER_FILES


# -- DDP: the resume after the agreed stop, and a signal to one rank in the test after training -----------------------
class RankSteps(L.Callback):
    """Appends "<rank> <global step>" at the start of every training step of every rank (one write each)."""

    def __init__(self, out: str):
        self.out = Path(out)

    def on_train_batch_start(self, trainer, *args):
        with self.out.open("a") as f:
            f.write(f"{trainer.global_rank} {trainer.global_step}\n")


class SignalRankAt(L.Callback):
    """Sends ``signum`` to this process if it is rank ``rank``: at the end of training step ``step``, or (``step``
    None) at the start of its first test batch (the test after training)."""

    def __init__(self, rank: int, signum: int, step: int | None = None):
        self.rank, self.signum, self.step = rank, signum, step

    def on_train_batch_end(self, trainer, *args):
        if self.step is not None and trainer.global_step == self.step and trainer.global_rank == self.rank:
            os.kill(os.getpid(), self.signum)

    def on_test_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0):
        if self.step is None and batch_idx == 0 and trainer.global_rank == self.rank:
            os.kill(os.getpid(), self.signum)


def _ddp_args(root: Path, run_dir: Path, steps: int, probe: Path, *extra: str) -> list[str]:
    return [f"data.root={root}", f"hydra.run.dir={run_dir}", *TRAIN, *TINY, f"trainer.max_steps={steps}",
            f"trainer.val_check_interval={VAL_EVERY}", "trainer.log_every_n_steps=1",
            f"callbacks.model_checkpoint.last_every_n_steps={INTERVAL}", "trainer.accelerator=cpu",
            "trainer.devices=2", "trainer.strategy=ddp", "data.loader.batch_size=1",
            "+callbacks.steps._target_=tests.test_fault_injection.RankSteps", f"+callbacks.steps.out={probe}", *extra]


def _rank_steps(probe: Path) -> dict[int, list[int]]:
    steps: dict[int, list[int]] = {}
    for line in probe.read_text().splitlines() if probe.is_file() else []:
        rank, step = map(int, line.split())
        steps.setdefault(rank, []).append(step)
    return steps


def _ddp_run(argv: list[str], timeout_s: float = 600) -> tuple[int, str]:
    """``python -m nvs.train *argv`` under 2-process DDP -> (exit code, stderr); every rank is gone after it."""
    proc = _train(argv, start_new_session=True)
    try:
        stderr = proc.communicate(timeout=timeout_s)[1]
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)  # a rank left behind (the hang this guards against) ends with it
    return proc.returncode, stderr


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="2-process DDP on CPU (gloo)")
def test_a_ddp_run_stopped_by_sigterm_resumes_at_the_stopped_step_on_both_ranks(objects_root, tmp_path):
    steps, stop = 7, 4  # SIGTERM to rank 1 after step 4 (no validation follows it: the stop is at step 4)
    run_dir = tmp_path / "run"
    _user_dir(run_dir)
    kill = ["+callbacks.kill._target_=tests.test_fault_injection.SignalRankAt", "+callbacks.kill.rank=1",
            f"+callbacks.kill.signum={int(signal.SIGTERM)}", f"+callbacks.kill.step={stop}"]
    code, stderr = _ddp_run(_ddp_args(objects_root, run_dir, steps, tmp_path / "first.txt", "test=false", *kill))
    lines = [ln for ln in stderr.splitlines() if ln.startswith("interrupted by")]
    assert code == 143 and "Traceback" not in stderr and len(lines) == 1, stderr[-3000:]
    assert f"at step {stop}: saved" in lines[0] and _last_step(run_dir) == stop
    assert _rank_steps(tmp_path / "first.txt") == {0: list(range(stop)), 1: list(range(stop))}

    code, stderr = _ddp_run(_ddp_args(objects_root, run_dir, steps, tmp_path / "resumed.txt", "test=false"))
    assert code == 0, stderr[-3000:]
    # both ranks restored the stopped step: neither redid a step nor skipped one
    assert _rank_steps(tmp_path / "resumed.txt") == {0: list(range(stop, steps)), 1: list(range(stop, steps))}
    assert json.loads((run_dir / "metrics.json").read_text())["steps"] == steps == _last_step(run_dir)
    rows = _rows(run_dir / "csv" / "metrics.csv")
    assert sorted(s for s, kind in rows if kind == "train") == list(range(steps)), rows
    assert sorted(s for s, kind in rows if kind == "val") == list(range(VAL_EVERY, steps + 1, VAL_EVERY)), rows
    assert _user_files(run_dir) == USER_FILES


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="2-process DDP on CPU (gloo)")
def test_sigterm_to_rank_1_in_the_test_after_training_stops_both_ranks_and_the_printed_command_finishes(
        objects_root, tmp_path):
    """Before, rank 1 left at once and rank 0 waited for it in the gather of the test rows."""
    steps = 3
    run_dir = tmp_path / "run"
    kill = ["+callbacks.kill._target_=tests.test_fault_injection.SignalRankAt", "+callbacks.kill.rank=1",
            f"+callbacks.kill.signum={int(signal.SIGTERM)}"]
    # one test pair per batch: each rank has two test batches, the signal lands in the first
    argv = _ddp_args(objects_root, run_dir, steps, tmp_path / "first.txt", "data.loader.eval_batch_size=1", *kill)
    code, stderr = _ddp_run(argv, timeout_s=300)
    lines = [ln for ln in stderr.splitlines() if ln.startswith("interrupted by")]
    assert code == 143 and "Traceback" not in stderr and len(lines) == 1, stderr[-3000:]
    assert lines[0].startswith(f"interrupted by SIGTERM at step {steps}: saved {run_dir / 'checkpoints' / 'last.ckpt'}"
                               "; resume with: python -m nvs.train "), lines
    assert not (run_dir / "metrics.json").exists() and not (run_dir / "test_per_image.csv").exists()
    assert _last_step(run_dir) == steps

    # the printed command (without the test's kill callback): nothing left to train, the test, the results
    command = [a for a in shlex.split(lines[0].split("resume with: ", 1)[1])[3:] if "callbacks.kill" not in a]
    code, stderr = _ddp_run(command)
    assert code == 0, stderr[-3000:]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["steps"] == steps and metrics["test"]["n_pairs"] == 4
