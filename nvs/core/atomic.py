"""Atomic file writes: a killed process never leaves a truncated file that a later reader would trust, and a write
the file system refuses (disk full, a file-size limit, permissions) is one :class:`WriteFailed` naming the file,
with the previous file, if any, left as it was and no temp file behind."""

from __future__ import annotations

import errno
import json
import os
import tempfile
from pathlib import Path
from typing import Any

from nvs.core.errors import UserError

# What a full disk (or a quota, or a file-size limit) answers a write: the user frees space and runs it again
_NO_SPACE = {errno.ENOSPC: "no space left on device (the disk is full)",
             errno.EDQUOT: "disk quota exceeded (the disk is full for this user)",
             errno.EFBIG: "file too large for this process's file-size limit (ulimit -f)"}


def reason(err: OSError) -> str:
    """Why the file system refused a write, in words (a full disk said as such)."""
    return _NO_SPACE.get(err.errno) or err.strerror or str(err) or err.__class__.__name__


def disk_full(err: BaseException) -> bool:
    return isinstance(err, OSError) and err.errno in _NO_SPACE


class WriteFailed(UserError, OSError):
    """A file could not be written. A UserError (the entry points print one line, exit 2) and an OSError (callers
    that catch OSError still do); ``errno`` is the file system's."""

    def __init__(self, path: str | Path, err: OSError):
        kept = "the previous file is unchanged" if Path(path).is_file() else "nothing was written"
        fix = "free space, then run the same command again" if disk_full(err) else "fix it, then run the command again"
        self.message = f"{path}: cannot write: {reason(err)}; {kept} ({fix})"
        super().__init__(self.message)
        self.errno, self.strerror, self.path = err.errno, err.strerror, str(path)

    def __str__(self) -> str:  # OSError's own would print "[Errno 28] ..." and drop the file and the advice
        return self.message

    def __reduce__(self):  # picklable (multiprocessing) although __init__ takes an OSError
        return (_rebuild, (self.path, self.errno, self.strerror, self.message))


def _rebuild(path: str, code: int | None, strerror: str | None, message: str) -> WriteFailed:
    err = WriteFailed.__new__(WriteFailed)
    err.message, err.path, err.errno, err.strerror = message, path, code, strerror
    err.args = (message,)
    return err


def _temp_with(path: Path, data: bytes) -> str:
    """``data`` in a hidden temp file beside ``path``, fsynced, with the permissions a plain open() gives; its name."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        # mkstemp creates 0600; give the file the permissions a plain open() would (0666 minus umask).
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return tmp


def write_files(files: dict[str | Path, bytes]) -> None:
    """Write every file or none: all temp files first (fsynced), then each renamed over its path (a rename takes no
    space). A write that fails (or a kill before the renames) leaves every old file as it was; :class:`WriteFailed`
    names the file."""
    temps: list[tuple[str, Path]] = []
    try:
        for path, data in files.items():
            path = Path(path)
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                temps.append((_temp_with(path, data), path))
            except OSError as err:
                raise WriteFailed(path, err) from None
        for tmp, path in temps:
            try:
                os.replace(tmp, path)
            except OSError as err:
                raise WriteFailed(path, err) from None
    except BaseException:
        for tmp, _ in temps:
            Path(tmp).unlink(missing_ok=True)
        raise


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write to a temp file in the same directory, fsync, then rename over ``path``."""
    write_files({path: data})


def write_text(path: str | Path, text: str) -> None:
    write_bytes(path, text.encode())


def json_text(obj: Any) -> str:
    """The JSON every nvs artifact holds: indented, keys sorted, one final newline."""
    return json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n"


def write_json(path: str | Path, obj: Any) -> None:
    write_text(path, json_text(obj))


def cache_dir() -> Path:
    """Where nvs keeps what a machine measured or derived once: ``$NVS_CACHE_DIR``, else ``$XDG_CACHE_HOME/nvs`` or
    ``~/.cache/nvs``."""
    return Path(os.environ.get("NVS_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "nvs"))
