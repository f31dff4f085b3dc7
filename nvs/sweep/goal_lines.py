"""The lines a table adds beyond the paper's layout: the converged studies' goals per trained row, each trained row
against a base row of the study (``against:``), and the test sets its jobs were measured on."""

from __future__ import annotations

from pathlib import Path

from nvs.core.metric_spec import SPECS
from nvs.sweep.bootstrap import LEVEL, interval_words, one_seed_note, paired_gap, read_seeds, verdict
from nvs.sweep.paper_order import signed
from nvs.sweep.testset import job_test_set


def md_cell(text: str) -> str:
    """Text safe inside a Markdown table cell."""
    return text.replace("|", "\\|").replace("\n", " ")


# The converged studies' goals: a trained model's L1 at least 25% below copying the source, its depth L1-all at
# least 30% below the constant depth at the training mean (the depth floor that reads no test ground truth).
GOALS = (("l1", "copy_source", 0.25, "copying the source"),
         ("depth_l1", "mean_depth", 0.30, "the constant-depth floor"))


def goals(rows: list[dict]) -> list[str]:
    """Markdown lines: each trained, non-oracle row against the floors of ``GOALS``, with the two-level bootstrap's
    interval of the relative gap. **met**: the whole interval is at least the goal below the floor; **not met**:
    the whole interval is short of it; **unresolved**: the interval holds the goal, or an end is within Monte-Carlo
    error of it."""
    floors = {ref: r for r in rows if r["kind"] == "reference" and (ref := r.get("reference"))}
    trained = [r for r in rows if r["kind"] == "train" and not r["oracle"]]
    cells: list[str] = []
    per_image: dict[str, list[dict]] = {}
    for r in trained:
        parts = []
        for metric, ref, goal, what in GOALS:
            floor = floors.get(ref)
            if floor is None or floor[metric][0] is None or r[metric][0] is None:
                continue
            for x in (r, floor):
                if x["row"] not in per_image:
                    per_image[x["row"]] = read_seeds(list(x.get("dirs") or []))
            base = floor[metric][0]
            if base <= 0:  # an exact floor (e.g. a scene whose depth is one plane): no relative gap to reach
                parts.append(f"{SPECS[metric].label} {r[metric][0]:.4f} against {what} {base:.4f}: the floor is "
                             "exact, no goal")
                continue
            gap = paired_gap(per_image[r["row"]], per_image[floor["row"]], metric, threshold=-goal * base)
            rel = (gap.diff if gap.diff is not None else r[metric][0] - base) / base
            text = f"{SPECS[metric].label} {r[metric][0]:.4f} against {what} {base:.4f}: {100 * rel:+.1f}%"
            if gap.lo is not None:
                lo, hi = 100 * gap.lo / base, 100 * gap.hi / base
                text += f" [{lo:+.1f}%, {hi:+.1f}%]"
                state = ("unresolved" if gap.near else "met" if hi <= -100 * goal else "not met" if lo > -100 * goal
                         else "unresolved")
            else:
                state = "met" if rel <= -goal else "not met"
                text += f" ({gap.why or 'no interval'})"
            parts.append(f"{text}, goal ≤ −{100 * goal:g}%: **{state}**{one_seed_note(gap, r['row'], None)}")
        if parts:
            cells.append(f"- {md_cell(r['label'])}: " + "; ".join(parts))
    if not cells:
        return []
    head = (f"Goals of the converged studies: L1 at least 25% below copying the source, depth L1-all at least 30% "
            f"below the constant depth at the training mean. Relative gap on the test pairs both rows were tested "
            f"on, with its {100 * LEVEL:g}% interval from a two-level bootstrap: the trained row's seeds, then the "
            f"test models (objects) or sequences (scenes); {interval_words()}. **met** / **not met**: the interval "
            "lies beyond / short of the goal; **unresolved**: it holds the goal, or an end is within Monte-Carlo error "
            "of it. (1 seed: x): row x has one seed, so its seed spread is missing from the interval.")
    return [head, "", *cells, ""]


def against_base(rows: list[dict], bases: tuple[str, ...], metrics: list[str]) -> list[str]:
    """Markdown lines: every other trained row of one table against its base row (the first of ``bases`` the table
    holds), per metric, Δ = row − base on the test pairs both were tested on, with the two-level bootstrap's interval:
    **better** / **worse** when the interval lies on one side of zero, **unresolved** when it holds zero. [] when
    the table holds no base or the base has no results."""
    base = next((r for name in bases for r in rows if r["row"] == name and r["kind"] == "train"), None)
    if base is None or all(base[m][0] is None for m in metrics):
        return []
    per_image = {base["row"]: read_seeds(list(base.get("dirs") or []))}
    cells: list[str] = []
    for r in rows:
        if r is base or r["kind"] != "train" or all(r[m][0] is None for m in metrics):
            continue
        per_image[r["row"]] = read_seeds(list(r.get("dirs") or []))
        parts = []
        for m in metrics:
            if r[m][0] is None or base[m][0] is None:
                continue
            spec = SPECS[m]
            gap = paired_gap(per_image[r["row"]], per_image[base["row"]], m)
            d = spec.decimals + 1
            if gap.diff is None:
                parts.append(f"{spec.label} {r[m][0]:.{spec.decimals}f}: {gap.why}")
                continue
            text = f"{spec.label} {r[m][0]:.{spec.decimals}f} ({spec.arrow}) Δ {signed(gap.diff, d)}"
            if gap.lo is not None:
                text += f" [{signed(gap.lo, d)}, {signed(gap.hi, d)}]"
            state = {"agree": "better", "swap": "worse", "unresolved": "unresolved"}[
                verdict(gap, spec.higher_is_better)]
            parts.append(f"{text} **{state}**{one_seed_note(gap, r['row'], base['row'])}")
        if parts:
            cells.append(f"- {md_cell(r['label'])}: " + "; ".join(parts))
    if not cells:
        return []
    head = (f"Against {md_cell(base['label'])} (`{base['row']}`): Δ = row − base on the test pairs both were "
            f"tested on, with its {100 * LEVEL:g}% interval from a two-level bootstrap: each row's seeds, then the "
            f"test models (objects) or sequences (scenes); {interval_words()}. **better** / **worse**: the interval "
            "lies on one side of zero (↓: lower is better, ↑: higher); **unresolved**: it holds zero, or an end is "
            "within Monte-Carlo error of it. (1 seed: x): row x has one seed, so its seed spread is missing from the "
            "interval.")
    return [head, "", *cells, ""]


def test_sets_cell(records: list[dict]) -> str:
    """Per dataset, the test set its finished jobs were measured on (``nvs.sweep.testset``); where they differ, each
    set with its jobs, flagged: such rows were not measured on the same data and do not compare."""
    by_data: dict[str, dict] = {}
    for r in records:
        if r["status"] == "done" and r.get("dir") and r.get("data"):
            ts = job_test_set(r["dir"])
            if ts is not None:
                by_data.setdefault(r["data"], {}).setdefault(ts, []).append(Path(r["dir"]).name)
    cells = []
    for data, sets in by_data.items():
        if len(sets) == 1:
            cells.append(f"{data}: {next(iter(sets))}")
        else:
            cells.append(f"**{data}: mixed**, " + "; ".join(f"{ts} ({', '.join(sorted(d))})" for ts, d in sets.items()))
    return md_cell("; ".join(cells)) or "—"
