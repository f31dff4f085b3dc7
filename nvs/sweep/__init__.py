"""The sweep runner: ``python -m nvs.sweep sweeps/<study>.yaml`` runs a study's jobs, then tabulates them.

One module per idea: ``study`` (the typed study-file schema, read by ``schema``), ``jobs`` (a job, its status,
identity and planning; ``fingerprint``: its stored config and what makes it stale; ``eval_rows``: the jobs of an
evaluation row, nvs.evaluate on another row's checkpoints), ``launch`` (Hydra multiruns in a subprocess),
``recorder`` (the Hydra callback inside every job), ``collect`` (one record per job, the CSV), ``bootstrap`` (the
two-level bootstrap over seeds and test groups), ``verdict_trace`` (a verdict per test group: wins, sign test, the
groups that undo it), ``testset`` (the test set a job was measured on), ``goal_lines`` (the converged studies'
goals, rows against a base row), ``paper_order`` (the rows against the paper's order), ``per_model_plot`` (their
per-model figure), ``tables`` (the Markdown tables, cost tables; ``eval_table``: their route and timed-size columns,
evaluation rows against their trained rows), ``pick`` (a cost table's pick, by the interval), ``paper_tally`` (the
committed tables' count of the paper's orderings) and ``__main__`` (the command line). Names are also reachable as
``nvs.sweep.<name>``, loaded on first use, so that importing ``nvs.sweep.recorder`` inside a training job loads
nothing else.
"""

from __future__ import annotations

import importlib
from pathlib import Path

# The modules whose public names are reachable as nvs.sweep.<name>, searched in this order: the recorder first (a
# training job that names nvs.sweep.JobRecorder loads nothing else), the command line last (it loads everything).
# A name is public when it does not start with "_".
MODULES = ("recorder", "study", "jobs", "launch", "collect", "goal_lines", "tables", "pick", "paper_order",
           "bootstrap", "verdict_trace", "per_model_plot", "paper_tally", "__main__")


def __getattr__(name: str):
    if (Path(__file__).parent / f"{name}.py").is_file():  # a submodule (``from nvs.sweep import recorder``)
        return importlib.import_module(f"{__name__}.{name}")
    if not name.startswith("_"):
        for module in MODULES:
            found = getattr(importlib.import_module(f"{__name__}.{module}"), name, _MISSING)
            if found is not _MISSING:
                return found
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


_MISSING = object()
