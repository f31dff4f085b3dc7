"""Launching a row's jobs: one ``python -m nvs.train -m`` (or ``nvs.evaluate -m``) subprocess per row over its seeds;
an evaluation row's (``nvs.sweep.eval_rows``) one ``nvs.evaluate -m ckpt_path=...`` per job, each on its checkpoint.

Each job lands in its fixed directory through ``hydra.sweep.dir=<runs>/<scale>`` and
``hydra.sweep.subdir=<run>_s${seed}``, whatever Hydra launcher is selected (basic, joblib, submitit), and loads the
``nvs.sweep.recorder`` callback. A job that died without an exception Hydra could catch gets its error line from its
own ``stderr.log``.
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

from nvs.core.atomic import write_text
from nvs.core.errors import UserError
from nvs.run.overrides import hydra_value
from nvs.sweep import recorder
from nvs.sweep.eval_rows import tested_checkpoint
from nvs.sweep.jobs import Job, Status, is_hydra, refresh, row_overrides
from nvs.sweep.progress import Progress
from nvs.sweep.recorder import FAILED, STDERR
from nvs.sweep.study import Row, Study

REPO = Path(__file__).resolve().parents[2]


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


@dataclass(frozen=True)
class Launch:
    """How jobs run: the Hydra launcher overrides and the torch threads each job may use."""

    jobs: int = 1
    threads: int = 1
    hydra_overrides: tuple[str, ...] = ()

    @classmethod
    def local(cls, jobs: int = 1, threads: int | None = None, extra: tuple[str, ...] = ()) -> Launch:
        cores = available_cores()
        if jobs < 1:
            raise UserError(f"--jobs must be >= 1, got {jobs}")
        threads = threads or max(1, cores // jobs)
        if jobs * threads > cores:
            raise UserError(f"{jobs} jobs x {threads} threads > {cores} cores: lower --jobs or --threads")
        launcher = ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={jobs}"] if jobs > 1 else []
        return cls(jobs=jobs, threads=threads, hydra_overrides=tuple(launcher + [o for o in extra if is_hydra(o)]))


def multirun_command(study: Study, row: Row, seeds: list[int], root: Path, launch: Launch,
                     extra: tuple[str, ...] = (), source: Job | None = None) -> list[str]:
    """``python -m nvs.train -m ...`` (or nvs.evaluate) for one row over the given seeds; for an evaluation row, one
    seed and ``source`` (the job it evaluates), whose tested checkpoint it is given."""
    head = []
    if row.evaluates:
        ckpt = tested_checkpoint(source.dir) if source is not None else None
        if ckpt is None or len(seeds) != 1:
            raise ValueError(f"{row.name}: an evaluation job runs alone, on its evaluated job's checkpoint")
        head = [f"ckpt_path={hydra_value(str(ckpt.resolve()))}"]
    module = "nvs.train" if row.kind == "train" else "nvs.evaluate"
    return [sys.executable, "-m", module, "-m", *head, *row_overrides(study, row, extra),
            "seed=" + ",".join(str(s) for s in seeds),
            f"hydra.sweep.dir={hydra_value(str(root.resolve()))}", f"hydra.sweep.subdir={row.run}_s${{seed}}",
            f"+hydra.callbacks.nvs_sweep._target_={recorder.TARGET}",
            f"+hydra.callbacks.nvs_sweep.threads={launch.threads}", *launch.hydra_overrides]


_ERROR_LINE = re.compile(r"^(error:|[\w.]*(Error|Exception|Interrupt|Exit)\b)|Killed|out of memory", re.IGNORECASE)


def last_error_line(text: str, fallback: bool = True) -> str:
    """The last line that reads like an error (``error: ...``, ``pkg.ValueError: ...``), else the last line."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    for ln in reversed(lines):
        if _ERROR_LINE.search(ln):
            return ln
    return lines[-1] if lines and fallback else ""


def interrupt_on_signal(signum, frame):
    """SIGTERM handler: raise KeyboardInterrupt, so a running job is stopped as Ctrl-C stops it."""
    raise KeyboardInterrupt(f"signal {signum}")


def _die_with_parent():
    """For ``Popen(preexec_fn=...)`` on Linux: the child gets SIGTERM when this process dies, ``kill -9`` included
    (``prctl(PR_SET_PDEATHSIG)``), so no orphaned ``nvs.train`` keeps training a job the next sweep re-runs; SIGTERM
    lets it save ``last.ckpt`` first. None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    try:  # resolved here, in the parent: the child between fork and exec only calls it
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    parent = os.getpid()

    def preexec() -> None:
        prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent:  # the parent died before the request took effect
            os.kill(os.getpid(), signal.SIGTERM)

    return preexec


_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def run_streaming(cmd: list[str], env: dict, keep_fds: tuple[int, ...] = ()) -> tuple[int, str]:
    """Run ``cmd``; its stdout/stderr pass through, the last stderr lines are kept for the error line.

    ``keep_fds``: descriptors the child inherits (the jobs' locks, nvs.sweep.lock); it dies with this process.
    """
    tail: collections.deque[str] = collections.deque(maxlen=200)
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, env=env, bufsize=1, pass_fds=keep_fds,
                            preexec_fn=_die_with_parent())

    def pump():
        for line in proc.stderr:
            sys.stderr.write(line)
            tail.append(line)

    t = threading.Thread(target=pump, daemon=True)
    t.start()
    try:
        rc = proc.wait()
    except KeyboardInterrupt:
        proc.terminate()
        proc.wait()
        raise
    t.join()
    return rc, "".join(tail)


def _fail(job: Job, error: str) -> None:
    job.error, job.status = error, Status.FAILED
    write_text(job.dir / FAILED, error + "\n")


def launch_row(study: Study, jobs: list[Job], root: Path, launch: Launch, extra: tuple[str, ...] = (),
               keep_fds: tuple[int, ...] = (), progress: Progress | None = None) -> list[Job]:
    """Launch one row's pending jobs until each has run once; returns them with their new status.

    ``keep_fds``: the jobs' lock descriptors, inherited by the training process (nvs.sweep.lock); ``progress``
    (nvs.sweep.progress) reports each job's start and end while the multirun runs."""
    row = jobs[0].row
    env = dict(os.environ, OMP_NUM_THREADS=str(launch.threads), MKL_NUM_THREADS=str(launch.threads),
               PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]))
    pending = list(jobs)
    while pending:
        batch = pending[:1] if row.evaluates else pending  # an evaluation job has a checkpoint of its own
        cmd = multirun_command(study, row, [j.seed for j in batch], root, launch, extra, batch[0].source)
        print(f"[sweep] {row.name}: seeds {[j.seed for j in batch]}\n[sweep] $ {shlex.join(cmd)}", file=sys.stderr)
        with progress.watch(batch) if progress else contextlib.nullcontext():
            rc, tail = run_streaming(cmd, env, keep_fds)
        started = [j for j in batch if (j.dir / STDERR).exists() or (j.dir / "metrics.json").exists()]
        for j in batch:
            refresh(j)
            if j in started and j.status in (Status.INCOMPLETE, Status.MISSING):
                # Died without an exception Hydra could catch (sys.exit, a killed worker): its own stderr says why.
                log = (j.dir / STDERR).read_text(errors="replace") if (j.dir / STDERR).exists() else ""
                _fail(j, last_error_line(log, fallback=False) or last_error_line(tail, fallback=False)
                      or f"no result (multirun exit code {rc}{'; killed by a signal' if rc < 0 else ''})")
        if not started:
            # Nothing ran (the multirun failed before its first job, e.g. a config error): all of them failed.
            for j in batch:
                _fail(j, last_error_line(tail) or f"multirun exit code {rc}")
        if progress:
            progress.settle(batch)
        # Jobs the multirun never reached (an earlier job ended the process) get their own turn.
        pending = [j for j in pending if j not in batch or (j not in started and j.status != Status.FAILED)]
    return jobs
