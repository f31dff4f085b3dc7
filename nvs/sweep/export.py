"""Committed job files: a finished job's small files copied to ``<results>/jobs/<scale>/<run>_s<seed>/``.

What a table needs from a job, and nothing heavy: ``EXPORTED`` (the metrics, the job record with its key and config,
the per-image results, the resolved config and overrides, the CSV log with the training curves, the convergence
record, an evaluation's fitted route rule), never checkpoints or logs of stderr. ``nvs.sweep.jobs.plan`` treats an exported job whose record still
stands for the job (the same key and staleness rule as a job in ``runs/``) as done, so a fresh clone rebuilds every
table from the committed files alone (``python -m nvs.sweep STUDY --collect-only``).
"""

from __future__ import annotations

import ctypes
import os
import shutil
import sys
from pathlib import Path

from nvs.core.atomic import WriteFailed, write_bytes
from nvs.sweep.jobs import JOB_RECORD, Job, Status

EXPORTED = ("metrics.json", JOB_RECORD, "test_per_image.csv", ".hydra/config.yaml", ".hydra/overrides.yaml",
            "csv/metrics.csv", "convergence.json", "route_rule.json")  # the last: nvs.run.routing.RULE_FILE
# A small file stays small: anything above this is left out (and named), so a commit never carries a large blob.
MAX_BYTES = 8 * 1024 * 1024


def export_root(results: str | Path, scale: str) -> Path:
    """Where a scale's committed jobs live: ``<results>/jobs/<scale>``."""
    return Path(results) / "jobs" / scale


def _copy_small(src: Path, dst: Path, final: Path) -> list[str]:
    """Copy the EXPORTED files of ``src`` that exist into ``dst`` (a failure named as the file of ``final`` it would
    have become); returns the ones left out for their size."""
    too_big = []
    for name in EXPORTED:
        f = src / name
        if not f.is_file():
            continue
        if f.stat().st_size > MAX_BYTES:
            too_big.append(name)
            continue
        try:
            write_bytes(dst / name, f.read_bytes())  # fsynced: a crash after the swap finds whole files
        except OSError as err:
            raise WriteFailed(final / name, err) from None
    return too_big


def _exchange(a: Path, b: Path) -> bool:
    """Swap two directories in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where that is not offered."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):  # a C library without it
        return False
    at_cwd, exchange = -100, 2  # AT_FDCWD, RENAME_EXCHANGE (linux/fcntl.h, linux/fs.h)
    return renameat2(at_cwd, os.fsencode(a), at_cwd, os.fsencode(b), exchange) == 0


def _replace_dir(new: Path, final: Path) -> None:
    """``new`` becomes ``final``; at no moment is there no ``final`` where the swap can be one step."""
    if final.exists() and _exchange(new, final):
        shutil.rmtree(new)  # now the old files
        return
    old = final.with_name(f".{final.name}.old-{os.getpid()}")
    if final.exists():
        final.rename(old)
    new.rename(final)
    shutil.rmtree(old, ignore_errors=True)


def _alive(pid: str) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (ValueError, OSError):  # not a number, or another user's process: leave its files alone
        return True
    return True


def _recover(dest: Path) -> None:
    """What a killed runner left in ``dest``: an old export between the two renames of :func:`_replace_dir`'s
    fallback (``.<job>.old-<pid>``, no ``<job>``) is put back (its files are whole); a half-filled
    ``.<job>.export-<pid>`` of a process that is gone is removed."""
    for old in dest.glob(".*.old-*"):
        final = dest / old.name[1:].rsplit(".old-", 1)[0]
        if old.is_dir() and not final.exists():
            old.rename(final)
    for tmp in dest.glob(".*.export-*"):
        if tmp.is_dir() and not _alive(tmp.name.rsplit("-", 1)[1]):
            shutil.rmtree(tmp, ignore_errors=True)


def export_jobs(jobs: list[Job], dest: str | Path) -> list[Path]:
    """Copy every done job's small files to ``dest/<job dir name>/``, replacing an earlier export of that job.

    Jobs already read from ``dest`` are left as they are. The new directory is filled beside the old one and then
    swapped with it in one step, so an interrupted export (a kill, a full disk) leaves the old files or the new ones,
    never a mix; a disk that fills is one :class:`~nvs.core.atomic.WriteFailed`. Returns the directories written.
    """
    dest = Path(dest)
    if dest.is_dir():
        _recover(dest)
    written = []
    for job in jobs:
        if job.status != Status.DONE or job.dir.resolve().parent == dest.resolve():
            continue
        final = dest / job.dir.name
        tmp = dest / f".{job.dir.name}.export-{os.getpid()}"
        shutil.rmtree(tmp, ignore_errors=True)
        try:
            tmp.mkdir(parents=True)
            too_big = _copy_small(job.dir, tmp, final)
            _replace_dir(tmp, final)
        except BaseException as err:  # a full disk, a kill: the earlier export of this job stays as it was
            shutil.rmtree(tmp, ignore_errors=True)
            if isinstance(err, OSError) and not isinstance(err, WriteFailed):
                raise WriteFailed(final, err) from None
            raise
        if too_big:
            print(f"[sweep] {job.dir.name}: left out of the export (over {MAX_BYTES >> 20} MiB): "
                  f"{', '.join(too_big)}", file=sys.stderr)
        written.append(final)
    return written
