"""A cost table's columns and lines for evaluations: the share of test pairs per route, the forward time per image at
each timed size, and each evaluation row against the trained row it evaluates (``evaluates:``, nvs.sweep.eval_rows).

The columns appear only where some row has their values (``Columns.of``), so a table without routes or timed sizes
is the one it always was. An evaluation row's line: ΔL1 = evaluated − trained on the test pairs both were tested on,
paired by seed as well (seed s of the evaluation is seed s's network evaluated again, so the seeds' spread of the
trained networks cancels): per seed, each pair's difference; then the two-level bootstrap of ``nvs.sweep.bootstrap``
over those differences (the seeds, then the test models or sequences, as levels) against zero. The line gives the
interval, its verdict against zero, whether it is shown within the pick's margin of the trained row's L1 (the
interval's upper end at most ``PICK_L1_TOLERANCE`` of it, as ``nvs.sweep.pick.within_margin`` decides a pick; the
point estimate without per-image results) and the speed-up of the forward at the largest timed size.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import math
from pathlib import Path

from nvs.sweep.bootstrap import LEVEL, PER_IMAGE, Gap, interval_words, paired_gap, read_per_image, verdict
from nvs.sweep.collect import ROUTE_SHARES, size_columns
from nvs.sweep.goal_lines import md_cell
from nvs.sweep.paper_order import gap_text
from nvs.sweep.pick import PICK_L1_TOLERANCE

_MS = re.compile(r"eval_(\d+)px_ms_per_image")


@dataclass(frozen=True)
class Columns:
    """Which evaluation columns a cost table has: the route shares, and the timed sizes (ascending)."""

    shares: bool = False
    sizes: tuple[int, ...] = ()

    @classmethod
    def of(cls, rows: list[dict]) -> Columns:
        """The columns some of ``rows`` (``summarize`` entries) have values for."""
        shares = any(r.get(k, (None,))[0] is not None for r in rows for k in ROUTE_SHARES)
        sizes = sorted({int(m[1]) for r in rows for k, v in r.items()
                        if (m := _MS.fullmatch(k)) and v[0] is not None})
        return cls(shares, tuple(sizes))

    def header(self) -> list[str]:
        head = ["Routes (copy/warp/full)"] if self.shares else []
        for s in self.sizes:
            head += [f"Eval {s}² (ms/img)", f"× {s}²"]
        return head

    def cells(self, r: dict) -> list[str]:
        out = []
        if self.shares:
            shares = [r.get(k, (None,))[0] for k in ROUTE_SHARES]
            out.append("—" if any(v is None for v in shares) else "/".join(f"{100 * v:.0f}" for v in shares))
        for s in self.sizes:
            (ms, ms_std), (speedup, _) = (r.get(k, (None, None)) for k in size_columns(s))
            out += ["—" if ms is None else f"{ms:.1f}" + (f" ± {ms_std:.1f}" if ms_std is not None else ""),
                    "—" if speedup is None else f"{speedup:.2f}×"]
        return out

    def explanation(self, evaluations: bool) -> str:
        """The sentences of the table's legend for these columns and the evaluation lines ('' when none)."""
        text = []
        if self.shares:
            text.append("Routes: the share of the test pairs each route took (copy the source / warp it by the "
                        "predicted depth / the full pixel decoder; `nvs.evaluate route=...`, docs/skipping.md), "
                        "in %.")
        if self.sizes:
            text.append("Eval S² is the forward time per image at S² (`nvs.evaluate time_sizes=...`: the routed "
                        "forward where the row has a route, else the network's); × S²: the network's time over the "
                        "routed one at that size.")
        if evaluations:
            pct = f"{100 * PICK_L1_TOLERANCE:g}%"
            text.append("An evaluation row evaluates a trained row's checkpoints again with its own `nvs.evaluate` "
                        "settings: it is never the best or the pick; under the table it is compared with that row, "
                        "ΔL1 = evaluated − trained on the same test pairs and seeds (each seed's network against "
                        f"itself evaluated again), with its {100 * LEVEL:g}% interval (two-level bootstrap of the "
                        "per-seed differences: the seeds, then the test models or sequences; "
                        f"{interval_words()}); **better** / **worse**: the interval lies on one side of zero; within "
                        f"{pct}: its upper end is at most {pct} of the trained row's L1, as for the pick.")
        return " ".join(text)


def evaluation_lines(rows: list[dict], columns: Columns) -> list[str]:
    """Markdown lines under one table: each evaluation row against the trained row of the table it evaluates."""
    by_name = {r["row"]: r for r in rows}
    lines = []
    for r in rows:
        src = by_name.get(r.get("evaluates") or "")
        if src is None or r["l1"][0] is None or src["l1"][0] is None:
            continue
        lines.append(evaluation_line(r, src, columns))
    return [*lines, ""] if lines else []


def seed_differences(r: dict, src: dict, metric: str = "l1") -> list[dict]:
    """Per seed both rows finished, each test pair's ``metric`` of ``r`` minus ``src``'s (a ``read_seeds``-like
    list, one dict per seed); pairs missing from either job or NaN left out."""
    mine = dict(zip(r.get("seeds") or [], r.get("dirs") or []))
    theirs = dict(zip(src.get("seeds") or [], src.get("dirs") or []))
    out = []
    for seed in sorted(set(mine) & set(theirs)):
        a, b = (read_per_image(Path(d) / PER_IMAGE) for d in (mine[seed], theirs[seed]))
        diff = {p: {metric: a[p][metric] - b[p][metric]} for p in a.keys() & b.keys()
                if not math.isnan(a[p].get(metric, math.nan) - b[p].get(metric, math.nan))}
        if diff:
            out.append(diff)
    return out


def paired_by_seed(diffs: list[dict], metric: str = "l1", threshold: float = 0.0) -> Gap:
    """The bootstrap of the per-seed differences (``seed_differences``) against zero: Δ, its interval, the seeds."""
    zero = [{p: {metric: 0.0} for d in diffs for p in d}] if diffs else []
    return paired_gap(diffs, zero, metric, threshold=threshold)


def evaluation_line(r: dict, src: dict, columns: Columns, tolerance: float = PICK_L1_TOLERANCE) -> str:
    """'- <row> (`route=fit`) against <trained row>: ΔL1 +0.0012 [-0.0010, +0.0035] over ..., 3 seeds:
    **unresolved**; within 1% of its L1 (...); eval 256² 1.62× faster'."""
    settings = " ".join(r.get("overrides") or ())
    head = f"- {md_cell(r['label'])}" + (f" (`{settings}`)" if settings else "") + f" against {md_cell(src['label'])}"
    diffs = seed_differences(r, src)
    pct, margin = f"{100 * tolerance:g}%", tolerance * src["l1"][0]
    pairs = sum(len(d) for d in diffs)
    if pairs and all(v["l1"] == 0.0 for d in diffs for v in d.values()):  # nothing to bootstrap: the same images
        seeds = f"{len(diffs)} seed" + ("s" if len(diffs) != 1 else "")
        same = f"the same L1 on every test pair ({pairs} pairs over {seeds}): **identical**"
        return f"{head}: {same}{_speed(r, columns)}."
    gap = paired_by_seed(diffs)
    if gap.diff is None:
        text = f"{head}: L1 {r['l1'][0]:.4f} against {src['l1'][0]:.4f}, no interval ({gap.why})"
    else:
        state = {"agree": "better", "swap": "worse", "unresolved": "unresolved"}[verdict(gap, False)]
        n = gap.seeds[0]
        seeds = f"{n} seeds" if n != 1 else "1 seed (no seed spread in the interval)"
        text = f"{head}: ΔL1 {gap_text(gap, 4).removeprefix('Δ ')}, {seeds}: **{state}**"
    decided = paired_by_seed(diffs, threshold=margin) if gap.lo is not None else None
    if decided is None:  # no interval: the point estimate (over the shared pairs where there are some)
        diff = gap.diff if gap.diff is not None else r["l1"][0] - src["l1"][0]
        within, how = diff <= margin, "by the point estimate"
    else:
        within, how = not decided.near and decided.hi <= margin, "by the interval's upper end"
    text += (f"; within {pct} of its L1 ({margin:.4f}) {how}" if within
             else f"; not shown within {pct} of its L1 ({margin:.4f})")
    return text + _speed(r, columns) + "."


def _speed(r: dict, columns: Columns) -> str:
    """'; eval 256² 1.62× faster than the network alone' at the largest timed size; '' where none was timed."""
    for size in reversed(columns.sizes):
        speedup = r.get(size_columns(size)[1], (None,))[0]
        if speedup is not None:
            how = "faster" if speedup >= 1 else "slower"
            return f"; eval {size}² {speedup:.2f}× {how} than the network alone"
    return ""
