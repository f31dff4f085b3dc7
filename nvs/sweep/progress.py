"""A sweep's progress on stderr: "job k/N" when each launched job starts and ends, its status, and an ETA.

The jobs of one row run inside one multirun process, so the runner learns of a job's start and end from the files it
leaves in its directory (``nvs.sweep.recorder``'s ``stderr.log`` at its start, ``metrics.json`` or ``failed.txt`` at
its end; the times are the files' own), polled while the multirun runs; what the polling missed is reported once the multirun has returned. The ETA
is the sweep's wall time so far per finished job times the jobs left, so parallel jobs (joblib) shorten it.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TextIO

from nvs.sweep.jobs import Job, Status
from nvs.sweep.recorder import FAILED, STDERR


def _mtime(path) -> float | None:
    try:
        return path.stat().st_mtime
    except OSError:
        return None


def duration(seconds: float) -> str:
    """3725 -> '1h02m', 185 -> '3m05s', 7.2 -> '7s'."""
    s = int(round(seconds))
    if s >= 3600:
        return f"{s // 3600}h{s % 3600 // 60:02d}m"
    return f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s"


class Progress:
    """The launched jobs of one sweep, numbered 1..N in launch order; ``skipped`` counts the planned jobs not run."""

    def __init__(self, launching: list[Job], skipped: int = 0, out: TextIO | None = None,
                 clock: Callable[[], float] = time.time):
        self.number = {job.dir: k for k, job in enumerate(launching, 1)}
        self.total, self.skipped = len(launching), skipped
        self.out, self.clock = out, clock
        self.t0 = clock()
        self.started: dict = {}    # job dir -> start time
        self.outcome: dict = {}    # job dir -> 'done' | 'failed'
        self._lock = threading.Lock()

    def _print(self, text: str) -> None:
        print(f"[sweep] {text}", file=self.out or sys.stderr, flush=True)

    def _name(self, job: Job) -> str:
        return f"job {self.number[job.dir]}/{self.total} {job.row.name} s{job.seed}"

    def begin(self) -> None:
        self._print(f"{self.total} job(s) to run" + (f", {self.skipped} skipped (done or not selected)"
                                                    if self.skipped else ""))

    def start(self, job: Job, at: float | None = None) -> None:
        """Report ``job`` as started (once), at ``at`` (wall time; default now)."""
        with self._lock:
            if job.dir in self.started or job.dir not in self.number:
                return
            self.started[job.dir] = self.clock() if at is None else at
        self._print(f"{self._name(job)}: started")

    def finish(self, job: Job, outcome: str, error: str = "", at: float | None = None) -> None:
        """Report ``job`` as 'done' or 'failed' (once), at ``at``, with its time and the sweep's ETA."""
        with self._lock:
            if job.dir in self.outcome or job.dir not in self.number:
                return
            self.outcome[job.dir] = outcome
            now = self.clock() if at is None else at
            took = now - self.started.get(job.dir, now)
        left = self.total - len(self.outcome)
        eta = max(now - self.t0, 0.0) / len(self.outcome) * left
        tail = f"; {len(self.outcome)}/{self.total} finished" + (f", ETA {duration(eta)}" if left else "")
        self._print(f"{self._name(job)}: {outcome} in {duration(took)}" + (f" ({error})" if error else "") + tail)

    def poll(self, jobs: list[Job]) -> None:
        """Report what the jobs' directories say now, in the order the files were written (their times are the
        jobs' own, however late the polling sees them)."""
        events = []  # (wall time, 0 start | 1 end, job, outcome, error)
        for job in jobs:
            if (at := _mtime(job.dir / STDERR)) is not None:  # cleared before the launch: this launch's
                # stderr.log is written to the job's end; Hydra writes overrides.yaml once, just before the job starts
                events.append((_mtime(job.dir / ".hydra" / "overrides.yaml") or at, 0, job, "", ""))
            if (at := _mtime(job.dir / "metrics.json")) is not None:
                events.append((at, 1, job, "done", ""))
            elif (at := _mtime(job.dir / FAILED)) is not None:
                # failed.txt may be the runner's, written after the multirun: the job ended at its last stderr line
                at = min(at, _mtime(job.dir / STDERR) or at)
                events.append((at, 1, job, "failed", (job.dir / FAILED).read_text(errors="replace").strip()))
        for at, end, job, outcome, error in sorted(events, key=lambda e: e[:2]):
            self.start(job, at)
            if end:
                self.finish(job, outcome, error, at)

    def settle(self, jobs: list[Job]) -> None:
        """After a multirun: each job with a final status (refreshed by the runner) is reported if it was not yet."""
        for job in jobs:
            if job.status in (Status.DONE, Status.FAILED):
                self.start(job)
                self.finish(job, "done" if job.status == Status.DONE else "failed", job.error)

    @contextmanager
    def watch(self, jobs: list[Job], interval: float = 2.0) -> Iterator[None]:
        """Poll ``jobs``' directories every ``interval`` seconds while the block runs."""
        stop = threading.Event()

        def loop() -> None:
            while not stop.wait(interval):
                self.poll(jobs)

        thread = threading.Thread(target=loop, daemon=True)
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join()
            self.poll(jobs)

    def end(self) -> None:
        counts = {o: list(self.outcome.values()).count(o) for o in ("done", "failed")}
        not_run = self.total - len(self.outcome)
        self._print(f"{counts['done']} done, {counts['failed']} failed" + (f", {not_run} not run" if not_run else "")
                    + f", {self.skipped} skipped in {duration(self.clock() - self.t0)}")
