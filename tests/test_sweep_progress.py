"""The sweep's progress lines: job k/N at each start and end, its status, the ETA from the finished jobs."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

from nvs.sweep.jobs import Status
from nvs.sweep.progress import Progress, duration
from tests.test_sweep import failing_study

REPO = Path(__file__).resolve().parents[1]


def _job(tmp_path: Path, name: str, seed: int) -> SimpleNamespace:
    d = tmp_path / f"{name}_s{seed}"
    d.mkdir()
    return SimpleNamespace(dir=d, row=SimpleNamespace(name=name), seed=seed, status=Status.MISSING, error="")


def _write(path: Path, at: float, text: str = "") -> None:
    path.write_text(text)
    os.utime(path, (at, at))


def test_progress_numbers_the_jobs_reports_each_once_and_estimates_from_the_finished_ones(tmp_path):
    t0 = 1_000_000.0
    now = [t0]
    out = io.StringIO()
    jobs = [_job(tmp_path, "full", 0), _job(tmp_path, "full", 1), _job(tmp_path, "noskip", 0)]
    progress = Progress(jobs, skipped=2, out=out, clock=lambda: now[0])
    progress.begin()
    _write(jobs[0].dir / "stderr.log", t0 + 1)
    progress.poll(jobs)
    progress.poll(jobs)  # nothing new: nothing printed twice
    # seen late, in one poll: the files' own times order and time the reports
    _write(jobs[1].dir / "failed.txt", t0 + 130, "error: data.root: no such directory\n")
    _write(jobs[1].dir / "stderr.log", t0 + 130)  # written to the job's end; Hydra's overrides.yaml at its start
    (jobs[1].dir / ".hydra").mkdir()
    _write(jobs[1].dir / ".hydra" / "overrides.yaml", t0 + 100)
    _write(jobs[0].dir / "metrics.json", t0 + 100)
    now[0] = t0 + 150
    progress.poll(jobs)
    jobs[2].status = Status.DONE  # the runner's refresh after the multirun, where the polling saw nothing
    now[0] = t0 + 190
    progress.settle(jobs)
    progress.settle(jobs)
    progress.end()
    assert out.getvalue().splitlines() == [
        "[sweep] 3 job(s) to run, 2 skipped (done or not selected)",
        "[sweep] job 1/3 full s0: started",
        "[sweep] job 2/3 full s1: started",
        "[sweep] job 1/3 full s0: done in 1m39s; 1/3 finished, ETA 3m20s",  # 100 s per finished job, 2 left
        "[sweep] job 2/3 full s1: failed in 30s (error: data.root: no such directory); 2/3 finished, ETA 1m05s",
        "[sweep] job 3/3 noskip s0: started",
        "[sweep] job 3/3 noskip s0: done in 0s; 3/3 finished",
        "[sweep] 2 done, 1 failed, 2 skipped in 3m10s",
    ]
    assert [duration(s) for s in (7.2, 185, 3725)] == ["7s", "3m05s", "1h02m"]


def test_a_sweep_prints_job_k_of_n_with_each_status(tmp_path):
    study = failing_study(tmp_path)
    res = subprocess.run([sys.executable, "-m", "nvs.sweep", str(study), "--runs", str(tmp_path / "runs"),
                          "--results", str(tmp_path / "results")], cwd=REPO, capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 1, res.stderr[-3000:]
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("[sweep] job ") or " skipped in " in ln]
    # A job that exits without Hydra's failure hook is known to have failed only once its multirun has returned, so
    # the second job's start may be reported before the first one's failure.
    assert lines.index("[sweep] job 1/2 nodata s0: started") < lines.index("[sweep] job 2/2 nodata s1: started")
    failed = [ln for ln in lines if ": failed in " in ln]
    assert [ln.split(":")[0] for ln in failed] == ["[sweep] job 1/2 nodata s0", "[sweep] job 2/2 nodata s1"]
    assert "does not exist" in failed[0] and "1/2 finished, ETA " in failed[0] and "; 2/2 finished" in failed[1]
    assert lines[-1].startswith("[sweep] 0 done, 2 failed, 0 skipped in ")
