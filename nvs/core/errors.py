"""User-facing errors: one clear message naming the file and line (or config key), no traceback wall.

The entry points turn them into one line and an exit code (``nvs.run.cli.exits_cleanly``).
"""

from __future__ import annotations

import re
from pathlib import Path


class UserError(Exception):
    """A problem with the user's data, config or checkpoint; the entry points print it on one line and exit 2."""


class DataError(UserError):
    """A malformed or missing dataset file; the message names the file (and line)."""

    def __init__(self, path: str | Path, message: str, line: int | None = None):
        where = f"{path}:{line}" if line is not None else str(path)
        super().__init__(f"{where}: {message}")
        self.path, self.line = str(path), line

    def __reduce__(self):  # picklable (DataLoader workers, multiprocessing) although __init__ takes three arguments
        return (_rebuild_data_error, (str(self), self.path, self.line))


def _rebuild_data_error(text: str, path: str, line: int | None) -> DataError:
    err = DataError.__new__(DataError)
    Exception.__init__(err, text)
    err.path, err.line = path, line
    return err


class Interrupted(BaseException):
    """SIGINT/SIGTERM during a run. A BaseException, so that no ``except Exception`` on the way swallows it.

    ``message`` is the one line the entry point prints (where the last checkpoint is, how to resume).
    """

    def __init__(self, signum: int, message: str):
        super().__init__(message)
        self.signum, self.message = signum, message


# "Caught DataError in DataLoader worker process 0.\nOriginal Traceback ...\nnvs.errors.DataError: <message>"
_WORKER = re.compile(r"Caught (\w+) in DataLoader worker process \d+")


def _user_error_names() -> set[str]:
    names, todo = set(), [UserError]
    while todo:
        cls = todo.pop()
        names.add(cls.__name__)
        todo.extend(cls.__subclasses__())
    return names


def user_message(err: BaseException) -> str | None:
    """The one-line message of a user error, wherever it was raised (here, in a DataLoader worker, inside
    Lightning, or as the cause of another exception); None for anything else."""
    seen = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        if isinstance(err, UserError):
            return str(err)
        worker = _WORKER.search(str(err))
        if worker and worker.group(1) in _user_error_names():
            lines = [ln for ln in str(err).splitlines() if ln.strip()]
            last = lines[-1] if lines else str(err)
            return re.sub(r"^[\w.]*(Error|Failed):\s*", "", last.strip())
        # Lightning's configuration errors, recognised by name: the contract layer imports no framework
        if any(cls.__name__ == "MisconfigurationException" for cls in type(err).__mro__):
            lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
            return f"Lightning: {lines[0] if lines else err.__class__.__name__}"
        err = err.__cause__ or err.__context__
    return None
