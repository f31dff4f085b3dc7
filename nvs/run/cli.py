"""The entry points' exit contract: a user error is one line and exit 2, an interruption one line and 128 + signal.

Exit codes: 2 for a problem the user can fix (data, config, checkpoint, a write that the file system refused),
128 + signal for an interrupted run (SIGINT 130, SIGTERM 143), 1 for anything else (a bug: its traceback is printed).
"""

from __future__ import annotations

import contextlib
import functools
import sys
from pathlib import Path

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


def before_hydra(task: str, *checks, rewrite=None) -> None:
    """What a Hydra command checks before ``main()``: Hydra creates the run directory and composes the config with
    tracebacks of its own, so the directory must be creatable and ``checks`` (each ``check(argv)``) must pass first;
    ``rewrite(argv) -> argv`` runs before them. A UserError is one line on stderr and exit 2."""
    from nvs.core.errors import UserError
    from nvs.run.artifacts import check_creatable, run_dir_of

    try:
        if rewrite is not None:
            sys.argv[1:] = rewrite(sys.argv[1:])
        check_creatable(run_dir_of(sys.argv[1:], task))
        for check in checks:
            check(sys.argv[1:])
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)


@contextlib.contextmanager
def hydra_task(task: str, cfg, existing: frozenset[str] = frozenset()):
    """Inside a Hydra command's ``main()``: its composed config ``cfg`` checked against the command's schema
    (``nvs.run.config_check``: a wrong type or unknown key, on the command line or in a YAML file), the known
    third-party noise silenced, and, when the block fails, the run directory Hydra made removed, only what this run
    wrote in it (``existing``: what was there before; a multirun job's directory stays: the multirun reports it).
    Yields the run directory."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from nvs.run.artifacts import is_global_zero, remove_unstarted_run
    from nvs.run.config_check import check_config
    from nvs.run.quiet import silence_known_noise

    hc = HydraConfig.get()
    out_dir = Path(hc.runtime.output_dir)
    try:
        check_config(task, cfg, hc.overrides.task)
        silence_known_noise()
        yield out_dir
    except BaseException:
        if hc.mode == RunMode.RUN and is_global_zero():
            remove_unstarted_run(out_dir, hc.job.name, existing)
        raise
