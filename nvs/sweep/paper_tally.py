"""How many of the paper's orderings the committed tables reproduce.

Every pair of rows the paper ranks on a metric, with a gap of at least ``MIN_GAP`` of the paper's worse row, is
counted once across the tables (Table 3 repeats Table 1's full model against Chen et al.). Its verdict is read from
the ordering lines of the table's Markdown (``paper_order``): agree, swap or unresolved; a pair with a row that has
no finished job is "not run". Each pair run also says whether its interval lies short of the paper's margin: the
paper's relative gap applied to our value of the worse row (``Entry.short_of_paper``), one criterion for all pairs.
The paper's numbers and the finished seeds come from the table's CSV.
"""

from __future__ import annotations

import collections
import csv
import itertools
import math
import re
from dataclasses import dataclass
from pathlib import Path

from nvs.core.errors import UserError
from nvs.core.metric_spec import SPECS

# Tables 1-4 and the metrics of their orderings counted: L1 (Tables 1-3) and the depth errors (Table 4)
TABLES: dict[str, tuple[str, ...]] = {
    "comparison_objects": ("l1",),
    "comparison_drive": ("l1",),
    "ablation": ("l1",),
    "depth": ("depth_l1", "depth_l1_rel", "depth_l1_inv", "depth_sc_inv"),
}
MIN_GAP = 0.10
NOT_RUN = "not run"

_LABEL = {s.label: k for k, s in SPECS.items()}
_NUM = r"([+-]?\d+\.\d+)"
_PAIR = re.compile(rf"^  - (\S+) / (\S+): (agree|swap|unresolved)(?: \(1 seed: ([^)]*)\))?, "
                   rf"(?:Δ {_NUM} \[{_NUM}, {_NUM}\])?")
_METRIC = re.compile(r"^- \*\*(.+?)\*\* \(best first\) paper:")


@dataclass(frozen=True)
class Entry:
    """One ordering of the paper (A its better row) and what the committed table says of it."""

    study: str
    data: str
    metric: str
    a: str
    b: str
    paper_gap: float                 # |paper A - paper B| / |paper B|
    verdict: str                     # agree / swap / unresolved / not run
    lo: float | None = None          # the table's 95% interval of Δ = A - B (None: not run, or no interval)
    hi: float | None = None
    b_mean: float | None = None      # our mean of row B over its finished seeds
    one_seed: tuple[str, ...] = ()   # the rows the table compared at one seed (no seed spread in the interval)

    @property
    def short_of_paper(self) -> bool | None:
        """Whether the interval rules out A beating B by the paper's relative gap (None: no interval)."""
        if self.lo is None or self.hi is None or self.b_mean is None:
            return None
        favour_a_hi = self.hi if SPECS[self.metric].higher_is_better else -self.lo
        return favour_a_hi < self.paper_gap * abs(self.b_mean)


def _read_csv(path: Path) -> dict[tuple[str, str], list[dict]]:
    if not path.is_file():
        raise UserError(f"{path}: no such table CSV (`python -m nvs.sweep sweeps/<study>.yaml --collect-only`)")
    with open(path, newline="") as f:
        rows: dict[tuple[str, str], list[dict]] = {}
        for r in csv.DictReader(f):
            rows.setdefault((r["data"], r["row"]), []).append(r)
    return rows


Line = tuple[str, float | None, float | None, tuple[str, ...]]


def read_orderings(path: Path) -> dict[tuple[str, str, str, str], Line]:
    """{(data, metric, A, B): (verdict, lo, hi, rows at one seed)} of a table's ordering lines
    (``paper_order.ordering_lines``)."""
    if not path.is_file():
        raise UserError(f"{path}: no such table (`python -m nvs.sweep sweeps/<study>.yaml --collect-only`)")
    out: dict[tuple[str, str, str, str], Line] = {}
    data = metric = None
    for line in path.read_text().splitlines():
        if line.startswith("## "):
            data, metric = line[3:].strip(), None
        elif m := _METRIC.match(line):
            metric = _LABEL.get(m.group(1))
        elif not line.startswith("  - "):
            if line.strip():
                metric = None   # a pair line belongs to the metric line right above its block
        elif metric is not None and (m := _PAIR.match(line)):
            lo, hi = (float(m.group(i)) if m.group(i) else None for i in (6, 7))
            single = tuple(x.strip() for x in m.group(4).split(",")) if m.group(4) else ()
            out[(data, metric, m.group(1), m.group(2))] = (m.group(3), lo, hi, single)
    return out


def _mean(records: list[dict], metric: str) -> float | None:
    values = [float(r[metric]) for r in records if r["status"] == "done" and r.get(metric)]
    return sum(values) / len(values) if values else None


def tally(results: Path, tables: dict[str, tuple[str, ...]] = TABLES, min_gap: float = MIN_GAP) -> list[Entry]:
    """Every ordering of the paper with a gap ≥ ``min_gap`` in ``tables`` (study -> metrics), once each."""
    seen: dict[tuple[str, str, str, str], Entry] = {}
    for study, metrics in tables.items():
        rows = _read_csv(results / f"{study}.csv")
        lines = read_orderings(results / f"{study}.md")
        for metric, data in itertools.product(metrics, sorted({d for d, _ in rows})):
            col = f"paper_{metric}"
            ranked = [(name, float(recs[0][col]), recs) for (d, name), recs in rows.items()
                      if d == data and recs[0].get(col)]
            ranked.sort(key=lambda x: -x[1] if SPECS[metric].higher_is_better else x[1])
            for (a, pa, ra), (b, pb, rb) in itertools.combinations(ranked, 2):
                gap = abs(pa - pb) / abs(pb) if pb else math.inf
                if pa == pb or gap < min_gap:
                    continue
                key = (data, metric, a, b)
                means = _mean(ra, metric), _mean(rb, metric)
                if None in means:
                    entry = Entry(study, data, metric, a, b, gap, NOT_RUN)
                elif key in lines:
                    verdict, lo, hi, single = lines[key]
                    entry = Entry(study, data, metric, a, b, gap, verdict, lo, hi, means[1], single)
                else:
                    raise UserError(f"{results / f'{study}.md'}: no ordering line for {a} / {b} on {metric} ({data}), "
                                    f"though both rows finished: rebuild it with --collect-only")
                old = seen.get(key)
                if old is not None and old.verdict != entry.verdict:
                    raise UserError(f"{results / f'{study}.md'}: {a} / {b} on {metric} ({data}) is {entry.verdict} "
                                    f"here but {old.verdict} in {old.study}.md")
                seen.setdefault(key, entry)
    return list(seen.values())


def summary(entries: list[Entry], min_gap: float = MIN_GAP) -> str:
    """One line: how many orderings are reproduced, swapped, unresolved and not run; of the reproduced and the
    unresolved, how many have an interval short of the paper's margin, and how many rest on a row at one seed."""
    n = collections.Counter(e.verdict for e in entries)

    def of(verdict: str) -> str:
        group = [e for e in entries if e.verdict == verdict]
        short = sum(1 for e in group if e.short_of_paper)
        single = sum(1 for e in group if e.one_seed)
        name = "reproduced" if verdict == "agree" else verdict
        return f"{len(group)} {name} ({short} short of the paper's margin, {single} with a row at one seed)"

    return (f"{len(entries)} orderings with a paper gap ≥ {100 * min_gap:g}%: {of('agree')}, {n['swap']} swapped, "
            f"{of('unresolved')}, {n[NOT_RUN]} not run")
