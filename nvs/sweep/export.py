"""Committed job files: a finished job's small files copied to ``<results>/jobs/<scale>/<run>_s<seed>/``.

What a table needs from a job, and nothing heavy: ``EXPORTED`` (the metrics, the job record with its key and config,
the per-image results, the resolved config and overrides, the CSV log with the training curves, the convergence
record), never checkpoints or logs of stderr. ``nvs.sweep.jobs.plan`` treats an exported job whose record still
stands for the job (the same key and staleness rule as a job in ``runs/``) as done, so a fresh clone rebuilds every
table from the committed files alone (``python -m nvs.sweep STUDY --collect-only``).
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from nvs.sweep.jobs import JOB_RECORD, Job, Status

EXPORTED = ("metrics.json", JOB_RECORD, "test_per_image.csv", ".hydra/config.yaml", ".hydra/overrides.yaml",
            "csv/metrics.csv", "convergence.json")
# A small file stays small: anything above this is left out (and named), so a commit never carries a large blob.
MAX_BYTES = 8 * 1024 * 1024


def export_root(results: str | Path, scale: str) -> Path:
    """Where a scale's committed jobs live: ``<results>/jobs/<scale>``."""
    return Path(results) / "jobs" / scale


def _copy_small(src: Path, dst: Path) -> list[str]:
    """Copy the EXPORTED files of ``src`` that exist into ``dst``; returns the ones left out for their size."""
    too_big = []
    for name in EXPORTED:
        f = src / name
        if not f.is_file():
            continue
        if f.stat().st_size > MAX_BYTES:
            too_big.append(name)
            continue
        (dst / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(f, dst / name)
    return too_big


def export_jobs(jobs: list[Job], dest: str | Path) -> list[Path]:
    """Copy every done job's small files to ``dest/<job dir name>/``, replacing an earlier export of that job.

    Jobs already read from ``dest`` are left as they are. The new directory is filled beside the old one and then
    renamed over it, so an interrupted export leaves either the old files or the new ones. Returns the directories
    written.
    """
    dest = Path(dest)
    written = []
    for job in jobs:
        if job.status != Status.DONE or job.dir.resolve().parent == dest.resolve():
            continue
        final = dest / job.dir.name
        tmp = dest / f".{job.dir.name}.export-{os.getpid()}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        too_big = _copy_small(job.dir, tmp)
        if too_big:
            print(f"[sweep] {job.dir.name}: left out of the export (over {MAX_BYTES >> 20} MiB): "
                  f"{', '.join(too_big)}", file=sys.stderr)
        old = dest / f".{job.dir.name}.old-{os.getpid()}"
        if final.exists():
            final.rename(old)
        tmp.rename(final)
        shutil.rmtree(old, ignore_errors=True)
        written.append(final)
    return written
