"""User-facing errors: one clear message naming the file and line (or config key), no traceback wall.

Exit codes of the entry points: 2 for a problem the user can fix (data, config, checkpoint, a write that the file
system refused), 128 + signal for an interrupted run (SIGINT 130, SIGTERM 143), 1 for anything else (a bug: its
traceback is printed).
"""

from __future__ import annotations

import functools
import re
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
        from lightning.fabric.utilities.exceptions import MisconfigurationException

        if isinstance(err, MisconfigurationException):
            lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
            return f"Lightning: {lines[0] if lines else err.__class__.__name__}"
        err = err.__cause__ or err.__context__
    return None


def _multirun() -> bool:
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    except Exception:  # noqa: BLE001 - outside a Hydra app: a plain run
        return False


def exits_cleanly(main):
    """Wrap an entry point: a user error becomes one line on stderr and exit code 2, an interruption one line and
    exit 128 + signal. In a multirun a user error fails that job only (:class:`nvs.multirun.MultirunReport` reports
    the failed jobs at the end)."""

    @functools.wraps(main)
    def wrapper(*args, **kwargs):
        try:
            return main(*args, **kwargs)
        except Interrupted as sig:
            print(sig.message, file=sys.stderr)
            sys.exit(128 + sig.signum)
        except Exception as err:
            message = user_message(err)
            if message is None:
                raise  # not the user's: Hydra prints the traceback, exit 1
            print(f"error: {message}", file=sys.stderr)
            if _multirun():  # this job failed; the multirun goes on and lists it at its end
                from nvs.multirun import record_failure

                record_failure(f"error: {message}", user_error=True)
                return None
            sys.exit(2)

    return wrapper
