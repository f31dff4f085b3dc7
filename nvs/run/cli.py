"""The entry points' exit contract: a user error is one line and exit 2, an interruption one line and 128 + signal.

Exit codes: 2 for a problem the user can fix (data, config, checkpoint, a write that the file system refused),
128 + signal for an interrupted run (SIGINT 130, SIGTERM 143), 1 for anything else (a bug: its traceback is printed).
"""

from __future__ import annotations

import functools
import sys

from nvs.core.errors import Interrupted, user_message


def _multirun() -> bool:
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    except Exception:  # noqa: BLE001 - outside a Hydra app: a plain run
        return False


def exits_cleanly(main):
    """Wrap an entry point: a user error becomes one line on stderr and exit code 2, an interruption one line and
    exit 128 + signal. In a multirun a user error fails that job only (:class:`nvs.run.multirun.MultirunReport` reports
    the failed jobs at the end)."""

    @functools.wraps(main)
    def wrapper(*args, **kwargs):
        try:
            return main(*args, **kwargs)
        except Interrupted as sig:
            from nvs.run.artifacts import is_global_zero

            if is_global_zero():  # under DDP every rank stops, one prints how to resume
                print(sig.message, file=sys.stderr)
            sys.exit(128 + sig.signum)
        except Exception as err:
            message = user_message(err)
            if message is None:
                raise  # not the user's: Hydra prints the traceback, exit 1
            print(f"error: {message}", file=sys.stderr)
            if _multirun():  # this job failed; the multirun goes on and lists it at its end
                from nvs.run.multirun import record_failure

                record_failure(f"error: {message}", user_error=True)
                return None
            sys.exit(2)

    return wrapper
