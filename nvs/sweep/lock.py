"""One sweep per job at a time: ``<runs>/<scale>/.locks/<job>.lock``, held while the sweep may train that job.

Two ``python -m nvs.sweep`` on the same study and directories would otherwise both train every job (``-v1``
checkpoints, one ``metrics.json`` naming the other's checkpoint). The lock is an exclusive ``flock`` on the file,
which the kernel releases when its process ends in any way, ``kill -9`` included: a dead sweep never blocks the
next one, and no PID is trusted after its process is gone (PIDs are reused). The file also names the holder (PID,
host, start time) for the message of the sweep that finds it taken. Lock files are never deleted (deleting one
while another process opens it would let two hold "the" lock); they are a few bytes each.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
from pathlib import Path

LOCKS = ".locks"


class JobLocks:
    """The locks this sweep holds, by job directory name; released on :meth:`release` or when the process ends."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self._held: dict[str, int] = {}

    def path(self, name: str) -> Path:
        return self.root / LOCKS / f"{name}.lock"

    def acquire(self, name: str) -> str | None:
        """Take the lock of job ``name``: None when taken, else who holds it ('pid 123 on host, since ...')."""
        if name in self._held:
            return None
        path = self.path(name)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return _holder(path)
        os.ftruncate(fd, 0)
        record = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%d %H:%M:%S")}
        os.write(fd, (json.dumps(record) + "\n").encode())
        self._held[name] = fd
        return None

    def fds(self, names) -> tuple[int, ...]:
        """The descriptors of the named held locks, for a child process to inherit (``Popen(pass_fds=...)``)."""
        return tuple(self._held[n] for n in names if n in self._held)

    def release(self, name: str | None = None) -> None:
        """Release one job's lock (None: every lock this sweep holds)."""
        for key in [name] if name is not None else list(self._held):
            fd = self._held.pop(key, None)
            if fd is not None:
                os.ftruncate(fd, 0)  # the file no longer names a holder
                os.close(fd)  # closing the descriptor releases the flock

    def __enter__(self) -> JobLocks:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _holder(path: Path) -> str:
    try:
        record = json.loads(path.read_text() or "{}")
    except (OSError, ValueError):
        record = {}
    if not record:
        return "another sweep"
    return f"pid {record.get('pid')} on {record.get('host')}, since {record.get('since')}"
