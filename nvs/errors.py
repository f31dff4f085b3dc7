"""User-facing errors: one clear message naming the file and line (or config key), no traceback wall."""

from __future__ import annotations

import functools
import sys
from pathlib import Path


class UserError(Exception):
    """A problem with the user's data, config or checkpoint; the entry points print it on one line and exit 2."""


class DataError(UserError):
    """A malformed or missing dataset file; the message names the file (and line)."""

    def __init__(self, path: str | Path, message: str, line: int | None = None):
        where = f"{path}:{line}" if line is not None else str(path)
        super().__init__(f"{where}: {message}")
        self.path, self.line = str(path), line


def exits_cleanly(main):
    """Wrap an entry point: a UserError becomes one line on stderr and exit code 2."""

    @functools.wraps(main)
    def wrapper(*args, **kwargs):
        try:
            return main(*args, **kwargs)
        except UserError as err:
            print(f"error: {err}", file=sys.stderr)
            sys.exit(2)

    return wrapper
