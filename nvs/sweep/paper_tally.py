"""How many of the paper's orderings the committed tables reproduce.

Every pair of rows the paper ranks on a metric, with a gap of at least ``MIN_GAP`` of the paper's worse row, is
counted once across the tables (Table 3 repeats Table 1's full model against Chen et al.). Its verdict is read from
the ordering lines of the table's Markdown (``paper_order``): agree, swap or unresolved; a pair with a row that has
no finished job is "not run". Each pair run also says whether its interval lies short of the paper's margin: the
paper's relative gap applied to our value of the worse row (``Entry.short_of_paper``), one criterion for all pairs.
The paper's numbers and the finished seeds come from the table's CSV.

Each ordering is measured with the code's network (the paper's rows, ``CODE``) and, where the study file gives a
variant of one of its two rows (``stands_for:``, the norms-fixed network for the full model), with that variant in
the row's place too: an ``Entry`` of the same pair whose ``network`` is the variant, read from the variant's
ordering line (``v (for x) / b``); "not run" while the variant or the other row has no finished job. ``summary``
counts the code's network; ``networks_summary`` the orderings reproduced by at least one of the two.
"""

from __future__ import annotations

import collections
import csv
import dataclasses
import itertools
import math
import re
from dataclasses import dataclass
from pathlib import Path

from nvs.core.errors import UserError
from nvs.core.metric_spec import SPECS
from nvs.sweep.study import load_study

# Tables 1-4 and the metrics of their orderings counted: L1 (Tables 1-3) and the depth errors (Table 4)
TABLES: dict[str, tuple[str, ...]] = {
    "comparison_objects": ("l1",),
    "comparison_drive": ("l1",),
    "ablation": ("l1",),
    "depth": ("depth_l1", "depth_l1_rel", "depth_l1_inv", "depth_sc_inv"),
}
MIN_GAP = 0.10
NOT_RUN = "not run"
CODE = "code"  # the network of the paper's rows (the authors' code's); a variant's entries name the variant row

_LABEL = {s.label: k for k, s in SPECS.items()}
_NUM = r"([+-]?\d+\.\d+)"
_FOR = r"(?: \(for (\S+)\))?"   # a variant in the place of the paper's row (``paper_order.Ordering.pair``)
_PAIR = re.compile(rf"^  - (\S+){_FOR} / (\S+){_FOR}: (agree|swap|unresolved)(?: \(1 seed: ([^)]*)\))?, "
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
    network: str = CODE              # measured with the paper's rows, or with this variant row in a's or b's place
    stands_for: str | None = None    # the variant's place: a or b (None for the code's network)

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


def read_orderings(path: Path) -> dict[tuple[str, str, str, str, str], Line]:
    """{(data, metric, A, B, network): (verdict, lo, hi, rows at one seed)} of a table's ordering lines
    (``paper_order.ordering_lines``); A and B are the paper's rows, network ``CODE`` or the variant in one's place."""
    if not path.is_file():
        raise UserError(f"{path}: no such table (`python -m nvs.sweep sweeps/<study>.yaml --collect-only`)")
    out: dict[tuple[str, str, str, str, str], Line] = {}
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
            a, a_for, b, b_for, verdict = m.group(1, 2, 3, 4, 5)
            lo, hi = (float(m.group(i)) if m.group(i) else None for i in (8, 9))
            single = tuple(x.strip() for x in m.group(6).split(",")) if m.group(6) else ()
            network = a if a_for else b if b_for else CODE
            out[(data, metric, a_for or a, b_for or b, network)] = (verdict, lo, hi, single)
    return out


def _mean(records: list[dict], metric: str) -> float | None:
    values = [float(r[metric]) for r in records if r["status"] == "done" and r.get(metric)]
    return sum(values) / len(values) if values else None


def _variants(path: Path) -> dict[str, list[str]]:
    """{paper's row: [its variants]} of a study file (``stands_for:``)."""
    out: dict[str, list[str]] = {}
    for row in load_study(path).rows:
        if row.stands_for is not None:
            out.setdefault(row.stands_for, []).append(row.name)
    return out


def tally(results: Path, tables: dict[str, tuple[str, ...]] = TABLES, min_gap: float = MIN_GAP,
          sweeps: Path | None = None) -> list[Entry]:
    """Every ordering of the paper with a gap ≥ ``min_gap`` in ``tables`` (study -> metrics), once each: the code's
    network's entries, then the variants' (the study files in ``sweeps``, default ``results/../sweeps``, name them)."""
    sweeps = results.parent / "sweeps" if sweeps is None else sweeps
    seen: dict[tuple[str, str, str, str, str], Entry] = {}
    for study, metrics in tables.items():
        md = results / f"{study}.md"
        rows = _read_csv(results / f"{study}.csv")
        lines = read_orderings(md)
        variants = _variants(sweeps / f"{study}.yaml")
        for metric, data in itertools.product(metrics, sorted({d for d, _ in rows})):
            col = f"paper_{metric}"
            ranked = [(name, float(recs[0][col]), recs) for (d, name), recs in rows.items()
                      if d == data and recs[0].get(col)]
            ranked.sort(key=lambda x: -x[1] if SPECS[metric].higher_is_better else x[1])
            for (a, pa, ra), (b, pb, rb) in itertools.combinations(ranked, 2):
                gap = abs(pa - pb) / abs(pb) if pb else math.inf
                if pa == pb or gap < min_gap:
                    continue
                measured = [(CODE, None, ra, rb)]
                measured += [(v, a, rows.get((data, v), []), rb) for v in variants.get(a, ())]
                measured += [(v, b, ra, rows.get((data, v), [])) for v in variants.get(b, ())]
                for network, x, rec_a, rec_b in measured:
                    entry = _entry(md, Entry(study, data, metric, a, b, gap, NOT_RUN, network=network, stands_for=x),
                                   _mean(rec_a, metric), _mean(rec_b, metric), lines)
                    key = (data, metric, a, b, network)
                    old = seen.get(key)
                    if old is not None and old.verdict != entry.verdict:
                        raise UserError(f"{md}: {_pair(entry)} on {metric} ({data}) is {entry.verdict} here but "
                                        f"{old.verdict} in {old.study}.md")
                    seen.setdefault(key, entry)
    entries = list(seen.values())
    return [e for e in entries if e.network == CODE] + [e for e in entries if e.network != CODE]


def _pair(e: Entry) -> str:
    """'a / b', or with the variant in its row's place 'v (for a) / b' (as the table writes it)."""
    return " / ".join(f"{e.network} (for {x})" if x == e.stands_for else x for x in (e.a, e.b))


def _entry(md: Path, entry: Entry, mean_a: float | None, mean_b: float | None,
           lines: dict[tuple[str, str, str, str, str], Line]) -> Entry:
    """``entry`` (not run) with the verdict of its table line once both rows it compares have finished jobs."""
    if mean_a is None or mean_b is None:
        return entry
    line = lines.get((entry.data, entry.metric, entry.a, entry.b, entry.network))
    if line is None:
        raise UserError(f"{md}: no ordering line for {_pair(entry)} on {entry.metric} ({entry.data}), though both "
                        f"rows finished: rebuild it with --collect-only")
    verdict, lo, hi, single = line
    return dataclasses.replace(entry, verdict=verdict, lo=lo, hi=hi, b_mean=mean_b, one_seed=single)


def _counts(entries: list[Entry]) -> str:
    """'2 reproduced (0 short of the paper's margin, 2 with a row at one seed), 2 swapped, 1 unresolved (...), 4 not
    run'."""
    n = collections.Counter(e.verdict for e in entries)

    def of(verdict: str) -> str:
        group = [e for e in entries if e.verdict == verdict]
        short = sum(1 for e in group if e.short_of_paper)
        single = sum(1 for e in group if e.one_seed)
        name = "reproduced" if verdict == "agree" else verdict
        return f"{len(group)} {name} ({short} short of the paper's margin, {single} with a row at one seed)"

    return f"{of('agree')}, {n['swap']} swapped, {of('unresolved')}, {n[NOT_RUN]} not run"


def summary(entries: list[Entry], min_gap: float = MIN_GAP) -> str:
    """One line for the code's network: how many orderings are reproduced, swapped, unresolved and not run; of the
    reproduced and the unresolved, how many have an interval short of the paper's margin, and how many rest on a row
    at one seed."""
    code = [e for e in entries if e.network == CODE]
    return f"{len(code)} orderings with a paper gap ≥ {100 * min_gap:g}%: {_counts(code)}"


def networks_summary(entries: list[Entry], min_gap: float = MIN_GAP) -> str:
    """One line: how many of the orderings the code's network or a variant in its row's place reproduces, and the
    variants' own counts over the orderings they take part in."""
    code = [e for e in entries if e.network == CODE]
    variant = [e for e in entries if e.network != CODE]
    agree = {(e.data, e.metric, e.a, e.b) for e in entries if e.verdict == "agree"}
    alone = agree - {(e.data, e.metric, e.a, e.b) for e in code if e.verdict == "agree"}
    names = sorted({(e.network, e.stands_for) for e in variant})
    which = ", ".join(f"{v} for {x}" for v, x in names) or "none"
    return (f"reproduced by at least one of the two networks: {len(agree)} of {len(code)} orderings with a paper gap "
            f"≥ {100 * min_gap:g}% ({len(alone)} by the variant alone); the variant ({which}) on its {len(variant)} "
            f"orderings: {_counts(variant)}")
