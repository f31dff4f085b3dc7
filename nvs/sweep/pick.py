"""A cost table's pick: the cheapest trained configuration whose L1 is within a margin of the best, decided by the
interval of its L1 against the best (``nvs.sweep.bootstrap``), the point estimate only without per-image results."""

from __future__ import annotations

from pathlib import Path

from nvs.sweep.bootstrap import Gap, paired_gap, read_seeds
from nvs.sweep.paper_order import gap_text

PICK_L1_TOLERANCE = 0.01
PICK_COST = "eval_forward_ms_per_image"


def pick_cheapest(rows: list[dict], cost: str = PICK_COST,
                  tolerance: float = PICK_L1_TOLERANCE) -> tuple[dict | None, dict | None]:
    """(best, pick) among one table's trained, non-oracle rows that have a mean L1.

    best has the lowest mean L1; pick has the lowest mean ``cost`` among the rows within ``tolerance`` of best's L1
    (ties go to the lower L1). "Within" is decided by the interval where both rows have per-image results: the upper
    end of the two-level bootstrap interval of Δ = row - best is at most ``tolerance`` x best's L1 (the row is shown
    to be no more than the margin worse). Rows without per-image results fall back to the point estimate
    (``within_margin``). Rows are ``summarize`` entries; (None, None) without any.
    """
    return pick_with_gap(rows, cost, tolerance)[:2]


def pick_with_gap(rows: list[dict], cost: str = PICK_COST,
          tolerance: float = PICK_L1_TOLERANCE) -> tuple[dict | None, dict | None, Gap | None]:
    """``pick_cheapest``'s (best, pick) and the interval that put the pick within the margin (None: see
    ``within_margin``); the best row's per-image results are read once."""
    eligible = [r for r in rows if r["kind"] == "train" and not r["oracle"] and r["l1"][0] is not None]
    if not eligible:
        return None, None, None
    best = min(eligible, key=lambda r: r["l1"][0])
    best_seeds = read_seeds(best.get("dirs") or [])
    within = [(r, gap) for r in eligible if r[cost][0] is not None
              for ok, gap in [within_margin(r, best, tolerance, best_seeds)] if ok]
    pick, gap = min(within, key=lambda x: (x[0][cost][0], x[0]["l1"][0]), default=(None, None))
    return best, pick, gap


def within_margin(row: dict, best: dict, tolerance: float = PICK_L1_TOLERANCE,
                  best_seeds: list[dict] | None = None) -> tuple[bool, Gap | None]:
    """Whether ``row``'s L1 is within ``tolerance`` of ``best``'s, and the interval that decided it (None: decided
    by the point estimate, for rows without per-image results; always within for ``best`` itself).
    ``best_seeds``: ``read_seeds`` of best's jobs, when the caller has read them already."""
    if row is best:
        return True, None
    margin = tolerance * best["l1"][0]
    if best_seeds is None:
        best_seeds = read_seeds(best.get("dirs") or [])
    mine = read_seeds(row.get("dirs") or [])
    gap = paired_gap(mine, best_seeds, "l1", threshold=margin) if mine and best_seeds else None
    if gap is None or gap.lo is None:
        return row["l1"][0] <= best["l1"][0] + margin, None
    return (not gap.near and gap.hi <= margin), gap


def pareto_pick_line(rows: list[dict], cost: str = PICK_COST, tolerance: float = PICK_L1_TOLERANCE) -> str:
    """The Pareto report's pick for one dataset: the cheapest row at evaluation within ``tolerance`` of the best L1,
    decided as ``pick_with_gap``, and its speed-up over the best. ``rows``: dicts with "label", "l1", ``cost`` (means)
    and "dirs" (the jobs, for the per-image results)."""
    entries = [{"kind": "train", "oracle": False, "label": r["label"], "dirs": [Path(d) for d in r["dirs"]],
                "l1": (_number(r["l1"]),), cost: (_number(r[cost]),)} for r in rows]
    best, pick, gap = pick_with_gap(entries, cost, tolerance)
    if best is None or pick is None:
        return "No pick: no row has both an L1 and an eval time."
    line = (f"**Pick**: {pick['label']}, the cheapest at evaluation within {100 * tolerance:g}% of the best L1 "
            f"({best['l1'][0]:.4f}, {best['label']})")
    if pick is best:
        return line + ": the best row itself; no cheaper row is shown to stay within that margin."
    return line + margin_clause(best, gap, tolerance) + \
        f": {best[cost][0] / pick[cost][0]:.2f}× faster at evaluation than the best row."


def margin_clause(best: dict, gap: Gap | None, tolerance: float = PICK_L1_TOLERANCE) -> str:
    """How a pick other than the best was put within the margin: its interval of ΔL1 against the best (``gap``), or
    the point estimate when there were no per-image results (``gap`` None)."""
    if gap is None:
        return ", by the point estimate (no per-image results to give an interval)"
    return (f", shown by the interval of ΔL1 against it, {gap_text(gap, 4)} (upper end at most "
            f"{tolerance * best['l1'][0]:.4f})")


def _number(v) -> float | None:
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return None if v != v else v
