"""Faults in the sweep runner (issue 37): killed while it writes its tables or exports, it leaves the previous ones
whole; a job killed with its runner is incomplete and the next run resumes it from its last.ckpt; a second runner on
the same study while the first runs every job is refused in one line.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import lightning as L
import pytest

from nvs.core import atomic
from nvs.core.errors import UserError
from tests.test_fault_evaluate import _killed_in_a_fork, _visible, linux_only
from tests.test_fault_injection import _alive
from tests.test_reliability import REPO


@pytest.fixture(autouse=True)
def _real_disk(monkeypatch):
    monkeypatch.setattr(atomic, "os", os)


def _fabricated(tmp_path):
    from nvs import sweep
    from tests.test_sweep import _fake_result, _study

    study = _study(tmp_path)
    root = tmp_path / "runs" / study.scale
    jobs = sweep.plan(study, root)
    _fake_result(jobs[0], root, 0.10)
    _fake_result(jobs[-1], root, 0.40)
    return study, root, jobs


@linux_only
@pytest.mark.parametrize("name", ["fab.csv", "fab.md"])
def test_the_runner_killed_while_writing_its_tables_leaves_the_previous_ones(tmp_path, name):
    from nvs import sweep
    from nvs.sweep.tables import write_results
    from tests.test_sweep import _fake_result

    study, root, jobs = _fabricated(tmp_path)
    results = tmp_path / "results"
    write_results(study, sweep.plan(study, root), results, "first")
    before = _visible(results)
    _fake_result(jobs[1], root, 0.20)  # a new result: the next tables differ
    _killed_in_a_fork(name, lambda: write_results(study, sweep.plan(study, root), results, "second"))
    assert _visible(results) == before  # both tables the old ones, not a new CSV beside an old Markdown
    write_results(study, sweep.plan(study, root), results, "third")
    assert _visible(results)["fab.csv"] != before["fab.csv"]


@linux_only
def test_the_runner_killed_while_exporting_leaves_the_previous_export(tmp_path):
    from nvs import sweep
    from nvs.sweep.export import export_jobs

    study, root, jobs = _fabricated(tmp_path)
    dest = tmp_path / "results" / "jobs" / study.scale
    done = [sweep.refresh(j) for j in jobs if sweep.refresh(j).status == "done"]
    assert len(export_jobs(done, dest)) == 2
    before = {p.relative_to(dest).as_posix(): p.read_bytes() for p in dest.rglob("*") if p.is_file()}
    (done[0].dir / "metrics.json").write_text('{"test": {"l1": 0.05}}')
    _killed_in_a_fork("sweep_job.json", lambda: export_jobs(done, dest))  # the first job's second file
    assert {p.relative_to(dest).as_posix(): p.read_bytes() for p in dest.rglob("*") if p.is_file()
            if not p.relative_to(dest).as_posix().startswith(".")} == before
    assert len(export_jobs(done, dest)) == 2  # the next export completes and clears what the killed one left
    assert sorted(p.name for p in dest.iterdir()) == sorted(j.dir.name for j in done)
    assert json.loads((dest / done[0].dir.name / "metrics.json").read_text())["test"]["l1"] == 0.05


def test_a_second_runner_on_a_study_whose_every_job_is_held_is_refused(tmp_path, monkeypatch, capsys):
    """Another sweep (its own process, holding the jobs' flocks) runs the study: this one launches nothing, writes
    no table, and says so in one line (exit 2)."""
    from nvs.sweep import __main__ as sweep_main

    study = tmp_path / "ref.yaml"
    study.write_text(json.dumps({"name": "ref", "title": "t", "paper_source": "none", "seeds": [0], "size": 64,
                                 "steps": 2, "rows": [{"name": "copy", "reference": "copy_source", "data": "chairs"},
                                                      {"name": "warp", "reference": "gt_warp", "data": "chairs"}]}))
    root = tmp_path / "runs" / "64px_2steps"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from nvs.sweep.lock import JobLocks; "
                               "locks = JobLocks(sys.argv[1]); "
                               "assert all(locks.acquire(n) is None for n in ('copy_s0', 'warp_s0')); "
                               "print('held', flush=True); time.sleep(120)", str(root)], cwd=REPO,
                              stdout=subprocess.PIPE, text=True)
    launched = []
    monkeypatch.setattr(sweep_main, "launch_row", lambda study, jobs, *a, **k: launched.extend(jobs) or jobs)
    monkeypatch.setattr(sweep_main, "check_launch", lambda *a: None)
    results = tmp_path / "results"
    args = [str(study), "--runs", str(tmp_path / "runs"), "--results", str(results)]
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(UserError) as err:  # (main prints it as one line "error: ...", exit 2)
            sweep_main.run(args)
    finally:
        holder.kill()
        holder.wait()
    assert launched == [] and "Traceback" not in capsys.readouterr().err
    assert str(err.value).startswith(f"{root}: another sweep is running every job this one would launch (copy s0: "
                                     f"pid {holder.pid} on "), err.value
    assert "\n" not in str(err.value)
    assert "refused: nothing launched, the tables and exports left as they are" in str(err.value)
    assert not results.exists() or not any(results.iterdir())  # no table written
    # its holder gone (kill -9 included), the same command runs the jobs
    code = sweep_main.run(args)
    assert [j.dir.name for j in launched] == ["copy_s0", "warp_s0"] and code == 1  # (launch_row is a stub)


class HoldUntilTheSweepIsGone(L.Callback):
    """At training step ``step``: wait (at most ``timeout_s``) until the process that launched this one has ended,
    i.e. the sweep runner was killed while this job ran."""

    def __init__(self, step: int, path: str, timeout_s: float = 300):
        self.step, self.path, self.timeout_s, self.parent = step, Path(path), timeout_s, os.getppid()

    def on_train_batch_end(self, trainer, *args):
        if trainer.global_step != self.step:
            return
        self.path.write_text(str(os.getpid()))  # where the test learns that the job is held here
        deadline = time.monotonic() + self.timeout_s
        while os.getppid() == self.parent and time.monotonic() < deadline:
            time.sleep(0.05)


@pytest.mark.slow
@linux_only
def test_a_job_killed_with_its_runner_is_incomplete_and_the_next_run_resumes_it(objects_root, tmp_path):
    from nvs import sweep
    from nvs.sweep.lock import JobLocks
    from tests.test_run_state import _rows

    steps = 4
    runs, results = tmp_path / "runs", tmp_path / "results"
    job = runs / f"64px_{steps}steps" / "small_s0"
    study = tmp_path / "tiny.yaml"
    study.write_text(json.dumps({
        "name": "tiny", "seeds": [0], "size": 64, "steps": steps,
        "overrides": [f"data.root={objects_root}", "trainer.val_check_interval=4", "data.loader.batch_size=2",
                      "trainer.limit_val_batches=1", "trainer.enable_progress_bar=false", "trainer.log_every_n_steps=1",
                      "callbacks.model_checkpoint.last_every_n_steps=1",
                      "+callbacks.hold._target_=tests.test_fault_sweep.HoldUntilTheSweepIsGone", "+callbacks.hold.step=2",
                      f"+callbacks.hold.path={tmp_path / 'holding'}"],
        "rows": [{"name": "small", "experiment": "nvs_chairs",
                  "overrides": ["model=tatarchenko", "loss=[recon_final]", "model.fc_dim=64"]}]}))
    args = [sys.executable, "-m", "nvs.sweep", str(study), "--runs", str(runs), "--results", str(results)]
    runner = subprocess.Popen(args, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 600
    while not (tmp_path / "holding").exists() and runner.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert runner.poll() is None, runner.stderr.read()[-3000:]
    child = int((tmp_path / "holding").read_text())
    runner.kill()  # kill -9 of the runner: its training child gets SIGTERM (PR_SET_PDEATHSIG), saves and stops
    runner.wait()
    locks = JobLocks(job.parent)
    deadline = time.monotonic() + 120
    while locks.acquire(job.name) is not None and time.monotonic() < deadline:  # the child holds it until it ends
        time.sleep(0.1)
    locks.release()
    while _alive(child) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive(child), "the job's training process outlived its sweep"
    planned = sweep.plan(sweep.load_study(study), job.parent)
    assert [(j.dir, j.status) for j in planned] == [(job, "incomplete")]
    assert not (job / "metrics.json").exists() and not (job / sweep.FAILED).exists()
    from nvs.run.checkpoint_files import read_checkpoint

    assert read_checkpoint(job / "checkpoints" / "last.ckpt")["global_step"] == 2  # the step it was stopped at

    again = subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=900)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "1 incomplete; launching 1" in again.stderr
    assert f"Restored all states from the checkpoint at {job / 'checkpoints' / 'last.ckpt'}" in again.stdout
    assert json.loads((job / "metrics.json").read_text())["steps"] == steps
    rows = _rows(job / "csv" / "metrics.csv")  # the curve of both segments, every step once
    assert sorted(s for s, kind in rows if kind == "train") == list(range(steps)), rows
    assert "| small | 1/1 |" in (results / "tiny.md").read_text()


def test_a_job_whose_runner_is_gone_still_writes_its_stderr_log(tmp_path):
    """The runner killed, the job's stderr pipe has no reader: its lines (the resume line of its SIGTERM stop) reach
    stderr.log instead of failing the job with BrokenPipeError."""
    from nvs.sweep.recorder import _Tee

    class Gone:
        def write(self, s):
            raise BrokenPipeError(32, "Broken pipe")

        flush = write

    tee = _Tee(Gone(), tmp_path / "stderr.log")
    print("interrupted by SIGTERM at step 2: saved ...", file=tee)
    tee.flush()
    print("and after", file=tee)
    tee.file.close()
    assert (tmp_path / "stderr.log").read_text() == "interrupted by SIGTERM at step 2: saved ...\nand after\n"
