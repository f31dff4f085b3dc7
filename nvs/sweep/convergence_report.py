"""The convergence layout of a study (``table: convergence``): validation L1 against steps and training wall time.

Each trained job of such a study runs with the stopping rule (``callbacks=convergence``), whose ``convergence.json``
holds every validation: (step, val/l1, training wall seconds). Per row the table gives where the rule stopped (or that
the budget ran out), the wall time, the best validation L1, and the first step within ``NEAR`` of that best: the
budget a study needs for the row to have learned what it will learn at this size. The figure draws the curves.
"""

from __future__ import annotations

import math
from pathlib import Path

from nvs.report.png import figure_png
from nvs.sweep.collect import CONVERGENCE
from nvs.sweep.jobs import read_json

NEAR = 0.01  # "converged": within 1% of the row's best validation L1


def history(job_dir: Path) -> list[dict]:
    """The job's validations in step order: [{'step', 'value', 'wall_s'}] (empty without a record)."""
    rec = read_json(Path(job_dir) / CONVERGENCE) or {}
    rows = [h for h in rec.get("history", []) if h.get("value") is not None and math.isfinite(h["value"])]
    return sorted(rows, key=lambda h: h["step"])


def first_step_near_best(hist: list[dict], near: float = NEAR) -> int | None:
    """The first validation step whose value is within ``near`` (relative) of the best of the whole curve."""
    if not hist:
        return None
    best = min(h["value"] for h in hist)
    return next(h["step"] for h in hist if h["value"] <= best * (1 + near))


def _cell(v, fmt: str) -> str:
    return "—" if v is None else format(v, fmt)


def convergence_tables(records: list[dict], budget: int) -> list[str]:
    """Markdown: one table per dataset, one line per trained job (reference rows have no curve)."""
    jobs = [r for r in records if r["kind"] != "reference" and r["status"] == "done" and r.get("dir")]
    lines = [f"Every trained job ran with the stopping rule (validation L1 improved < 1% over the last 25% of its "
             f"steps), within a budget of {budget} steps. *Near best*: the first validation within "
             f"{NEAR:.0%} of the job's best validation L1, the steps a study needs at this size.", ""]
    if not jobs:
        return lines + ["No trained job has finished yet.", ""]
    by_data: dict[str, list[dict]] = {}
    for r in jobs:
        by_data.setdefault(r["data"] or "—", []).append(r)
    for data, recs in by_data.items():
        lines += [f"### Convergence: {data}", "",
                  "| row | seed | stopped | at step | train wall min | best val L1 | near best at step |",
                  "|---|---:|---|---:|---:|---:|---:|"]
        for r in recs:
            hist = history(r["dir"])
            best = min((h["value"] for h in hist), default=None)
            wall = r.get("train_wall_s")
            lines.append(f"| {r['label'] or r['row']} | {r['seed']} | {r.get('stop') or '—'} | "
                         f"{_cell(r.get('steps'), 'd')} | {_cell(wall / 60 if wall else None, '.1f')} | "
                         f"{_cell(best, '.4f')} | {_cell(first_step_near_best(hist), 'd')} |")
        lines.append("")
    return lines


def curves_png(records: list[dict]) -> bytes | None:
    """Validation L1 against steps (left) and training wall minutes (right), one row of panels per dataset."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves: dict[str, list[tuple[str, list[dict]]]] = {}
    for r in records:
        if r["kind"] != "reference" and r["status"] == "done" and r.get("dir"):
            hist = history(r["dir"])
            if hist:
                curves.setdefault(r["data"] or "—", []).append((f"{r['label'] or r['row']} s{r['seed']}", hist))
    if not curves:
        return None
    fig, axes = plt.subplots(len(curves), 2, figsize=(11, 3.4 * len(curves)), squeeze=False)
    for (data, runs), (ax_s, ax_t) in zip(curves.items(), axes):
        for label, hist in runs:
            ax_s.plot([h["step"] for h in hist], [h["value"] for h in hist], marker=".", label=label)
            ax_t.plot([h["wall_s"] / 60 for h in hist], [h["value"] for h in hist], marker=".", label=label)
        ax_s.set(title=f"{data}: validation L1 against steps", xlabel="step", ylabel="val L1")
        ax_t.set(title=f"{data}: against training wall time", xlabel="minutes", ylabel="val L1")
        ax_s.legend(fontsize=7)
    fig.tight_layout()
    return figure_png(fig, dpi=90)
