"""A cost table's columns and lines for evaluations: the share of test pairs per route, the forward time per image at
each timed size, and each evaluation row against the trained row it evaluates (``evaluates:``, nvs.sweep.eval_rows).

The columns appear only where some row has their values (``Columns.of``), so a table without routes or timed sizes
is the one it always was. An evaluation row's line: ΔL1 = evaluated − trained on the test pairs both were tested on,
with the interval of the two-level bootstrap (``nvs.sweep.bootstrap``: each row's seeds, then the test models or
sequences), its verdict against zero, whether it is shown within the pick's margin of the trained row's L1
(``nvs.sweep.pick.within_margin``) and the speed-up of its forward at the largest timed size.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from nvs.sweep.bootstrap import LEVEL, interval_words, one_seed_note, paired_gap, read_seeds, verdict
from nvs.sweep.collect import ROUTE_SHARES, size_columns
from nvs.sweep.goal_lines import md_cell
from nvs.sweep.paper_order import gap_text
from nvs.sweep.pick import PICK_L1_TOLERANCE, within_margin

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
                        f"ΔL1 = evaluated − trained on the same test pairs with its {100 * LEVEL:g}% interval (two-"
                        f"level bootstrap: each row's seeds, then the test models or sequences; {interval_words()}); "
                        "**better** / **worse**: the interval lies on one side of zero; within "
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


def evaluation_line(r: dict, src: dict, columns: Columns, tolerance: float = PICK_L1_TOLERANCE) -> str:
    """'- <row> (`route=fit`) against <trained row>: ΔL1 Δ +0.0012 [-0.0010, +0.0035] over ..., 3 seeds:
    **unresolved**; within 1% of its L1 (...); eval 256² 1.62× faster'."""
    settings = " ".join(r.get("overrides") or ())
    head = f"- {md_cell(r['label'])}" + (f" (`{settings}`)" if settings else "") + f" against {md_cell(src['label'])}"
    gap = paired_gap(read_seeds(list(r.get("dirs") or [])), read_seeds(list(src.get("dirs") or [])), "l1")
    pct, margin = f"{100 * tolerance:g}%", tolerance * src["l1"][0]
    if gap.diff is None:
        text = f"{head}: L1 {r['l1'][0]:.4f} against {src['l1'][0]:.4f}, no interval ({gap.why})"
    else:
        state = {"agree": "better", "swap": "worse", "unresolved": "unresolved"}[verdict(gap, False)]
        n = min(gap.seeds)
        text = (f"{head}: ΔL1 {gap_text(gap, 4).removeprefix('Δ ')}, {n} seed{'s' if n != 1 else ''}: "
                f"**{state}**{one_seed_note(gap, r['row'], src['row'])}")
    within, decided = within_margin(r, src, tolerance)
    how = "by the interval's upper end" if decided is not None else "by the point estimate"
    text += (f"; within {pct} of its L1 ({margin:.4f}) {how}" if within
             else f"; not shown within {pct} of its L1 ({margin:.4f})")
    for size in reversed(columns.sizes):
        speedup = r.get(size_columns(size)[1], (None,))[0]
        if speedup is not None:
            text += f"; eval {size}² {speedup:.2f}× " + ("faster" if speedup >= 1 else "slower") + \
                " than the network alone"
            break
    return text + "."
