"""The sweep runner: ``python -m nvs.sweep sweeps/<study>.yaml`` runs a study's jobs, then tabulates them.

One module per idea: ``study`` (the typed study-file schema, read by ``schema``), ``jobs`` (a job, its status,
identity and planning), ``launch`` (Hydra multiruns in a subprocess), ``recorder`` (the Hydra callback inside every
job), ``collect`` (one record per job, the CSV), ``bootstrap`` (the two-level bootstrap over seeds and test groups),
``verdict_trace`` (a verdict per test group: wins, sign test, the groups that undo it), ``testset`` (the test set a
job was measured on), ``goal_lines`` (the converged studies' goals, rows against a base row), ``paper_order`` (the
rows against the paper's order), ``per_model_plot`` (their per-model figure), ``tables`` (the Markdown tables, cost
tables), ``paper_tally`` (the committed tables' count of the paper's orderings) and ``__main__`` (the command
line). Names are also reachable as ``nvs.sweep.<name>``, loaded on first use, so that importing
``nvs.sweep.recorder`` inside a training job loads nothing else.
"""

from __future__ import annotations

import importlib

_WHERE = {
    "study": ("REFERENCE_MODELS", "REFERENCES", "TABLES", "Row", "Study", "StudyFile",
              "load_study"),
    "jobs": ("JOB_RECORD", "NEUTRAL_KEYS", "Job", "Status", "row_overrides", "row_seeds", "compose_job",
             "config_fingerprint", "config_digest", "config_changes", "job_key", "job_status", "plan", "to_launch",
             "prepare_job_dir"),
    "recorder": ("FAILED", "STDERR", "JobRecorder"),
    "launch": ("Launch", "multirun_command", "launch_row", "last_error_line", "_cores", "_run_streaming",
               "_interrupt"),
    # (the function collect is nvs.sweep.collect.collect: the attribute nvs.sweep.collect is its module)
    "collect": ("CSV_COLUMNS", "COSTS", "SKIP_LEVELS", "SKIP_FRACTIONS", "render_csv", "mean_std", "summarize"),
    "goal_lines": ("GOALS", "against_base", "goals", "test_sets_cell"),
    "tables": ("PICK_COST", "PICK_L1_TOLERANCE", "pick_cheapest", "render", "render_markdown", "provenance",
               "write_results"),
    "paper_order": ("Ordering", "decide", "ordering_lines", "orderings"),
    "bootstrap": ("Gap", "Paired", "group_of", "pair_up", "paired_gap", "read_seeds", "seed_mean",
                  "verdict"),
    "verdict_trace": ("Trace", "sign_test", "flip_set", "trace"),
    "per_model_plot": ("per_model_png",),
    "paper_tally": ("tally", "read_orderings"),
    "__main__": ("run", "main"),
}
_MODULE_OF = {name: module for module, names in _WHERE.items() for name in names}
_SHARED = {"UserError": "nvs.core.errors", "CONF_DIR": "nvs.run.compose", "METRICS": "nvs.core.metric_spec",
           "IMAGE_METRICS": "nvs.core.metric_spec", "DEPTH_METRICS": "nvs.core.metric_spec"}


def __getattr__(name: str):
    if name in _MODULE_OF:
        return getattr(importlib.import_module(f"{__name__}.{_MODULE_OF[name]}"), name)
    if name in _SHARED:
        return getattr(importlib.import_module(_SHARED[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_MODULE_OF, *_SHARED])
