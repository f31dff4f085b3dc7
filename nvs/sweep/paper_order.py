"""Orderings of a table's rows against the paper's: each pair decided by the two-level bootstrap over seeds and test
groups (``nvs.sweep.bootstrap``), and traced per test group (``nvs.sweep.verdict_trace``). A variant row (``stands_for:
X``, no paper numbers of its own) is decided again in X's place in each of X's pairs, never against X itself."""

from __future__ import annotations

import collections
from dataclasses import dataclass, replace

import numpy as np

from nvs.core.metric_spec import SPECS
from nvs.sweep.bootstrap import LEVEL, Gap, bootstrap, interval_words, one_seed_note, pair_up, read_seeds
from nvs.sweep.bootstrap import verdict as decide_gap
from nvs.sweep.verdict_trace import Trace, oriented, trace, trace_text


@dataclass(frozen=True)
class Ordering:
    """One pair (A the paper's better row) on one metric: the gap, its verdict and, with per-image results, the
    per-group account and the per-group Δ turned so that > 0 favours A, with the seed spread's standard error."""

    a: str
    b: str
    metric: str
    gap: Gap
    verdict: str
    note: str = ""                        # ' (1 seed: ...)'
    trace: Trace | None = None
    groups: tuple[str, ...] = ()
    favour_a: np.ndarray | None = None    # (G,)
    se: np.ndarray | None = None          # (G,) or None with one seed in both rows
    a_for: str | None = None              # A is a variant of this row, decided in its place (None: A is the row)
    b_for: str | None = None

    @property
    def stands_for(self) -> str | None:
        """The paper's row that a variant takes the place of in this pair (None: the paper's two rows)."""
        return self.a_for or self.b_for

    @property
    def pair(self) -> str:
        """'A / B', a variant marked with the row it stands for: 'v (for x) / b'."""
        return " / ".join(n + (f" (for {x})" if x else "") for n, x in ((self.a, self.a_for), (self.b, self.b_for)))


def _ranked(rows: list[dict], m: str) -> list[dict]:
    return [r for r in rows if m in r["paper"] and r[m][0] is not None]


def decide(rows: list[dict], metrics: list[str]) -> dict[str, list[Ordering]]:
    """Per metric, every pair of rows the paper ranks (ties left out), A the paper's better one, in the paper's
    order. Only rows with both a paper number and a measured mean take part; rows carry their job dirs in ``dirs``.
    After them, each variant's (a row with ``stands_for``, in row order): the paper's pairs of the row it stands for,
    the variant in that row's place (``Ordering.a_for`` / ``b_for``), where it and the other row are measured."""
    seeds: dict[str, list[dict]] = {}

    def seeds_of(r: dict) -> list[dict]:
        if r["row"] not in seeds:
            seeds[r["row"]] = read_seeds(list(r.get("dirs") or []))
        return seeds[r["row"]]

    out: dict[str, list[Ordering]] = {}
    for m in metrics:
        higher = SPECS[m].higher_is_better
        decided = []
        ranked = _ranked(rows, m)
        if len(ranked) >= 2:
            for a, b in _paper_pairs(ranked, m):
                decided.append(_one(a, b, m, seeds_of(a), seeds_of(b), higher))
        by_name = {r["row"]: r for r in rows}
        for v in rows:
            x = v.get("stands_for")
            if x is None or x not in by_name or not _measured(v, m):
                continue
            for a, b in _paper_pairs([r for r in rows if m in r["paper"]], m):
                if x not in (a["row"], b["row"]) or not _measured(b if a["row"] == x else a, m):
                    continue
                a, b = (v, b) if a["row"] == x else (a, v)
                o = _one(a, b, m, seeds_of(a), seeds_of(b), higher)
                decided.append(replace(o, a_for=x if a is v else None, b_for=x if b is v else None))
        if len(ranked) >= 2 or decided:
            out[m] = decided
    return out


def _measured(r: dict, m: str) -> bool:
    return r.get(m, (None,))[0] is not None


def _paper_pairs(rows: list[dict], m: str) -> list[tuple[dict, dict]]:
    """Every pair of ``rows`` (all with a paper number on m) that the paper ranks, A its better one, in its order."""
    paper = sorted(rows, key=lambda r: (-1.0 if SPECS[m].higher_is_better else 1.0) * r["paper"][m])
    return [(a, b) for i, a in enumerate(paper) for b in paper[i + 1:] if a["paper"][m] != b["paper"][m]]


def _one(a: dict, b: dict, m: str, sa: list[dict], sb: list[dict], higher: bool) -> Ordering:
    names = [r["row"] if r.get("kind", "train") != "reference" else None for r in (a, b)]
    p = pair_up(sa, sb, m)
    if isinstance(p, str):
        gap = Gap(None, None, None, 0, 0, why=p, seeds=(len(sa), len(sb)))
        return Ordering(a["row"], b["row"], m, gap, "unresolved")
    gap = bootstrap(p)
    v = decide_gap(gap, higher)
    return Ordering(a["row"], b["row"], m, gap, v, one_seed_note(gap, *names), trace(p, gap, higher), p.names,
                    oriented(p, higher), p.group_se())


def ordering_lines(rows: list[dict], decided: dict[str, list[Ordering]]) -> list[str]:
    """Markdown: per metric both rankings (best first) and the counts, then one line per pair: the verdict, Δ and
    its interval, and the per-group trace; a variant's pairs last, marked 'v (for x)' and not in the counts."""
    lines: list[str] = []
    for m, pairs in decided.items():
        sign = -1.0 if SPECS[m].higher_is_better else 1.0
        ranked = _ranked(rows, m)
        paper = sorted(ranked, key=lambda r: sign * r["paper"][m])
        ours = sorted(ranked, key=lambda r: sign * r[m][0])
        own = [o for o in pairs if o.stands_for is None]
        counts = collections.Counter(o.verdict for o in own)
        lines.append(f"- **{SPECS[m].label}** (best first) paper: {' > '.join(r['row'] for r in paper)}; "
                     f"ours: {' > '.join(r['row'] for r in ours)}; of {len(own)} pairs {counts['agree']} agree, "
                     f"{counts['swap']} swap, {counts['unresolved']} unresolved")
        for o in pairs:
            text = f"  - {o.pair}: {o.verdict}{o.note}, {gap_text(o.gap, SPECS[m].decimals)}"
            lines.append(text + (f"; {trace_text(o.trace, o.a)}" if o.trace is not None else ""))
    if not lines:
        return []
    head = (f"Orderings against the paper. For each pair A / B (A the paper's better row), Δ = ours(A) − ours(B) "
            f"on the test pairs all their seeds were tested on, with its {100 * LEVEL:g}% interval from a two-level "
            f"bootstrap: each row's seeds, then the test models (objects) or sequences (scenes); {interval_words()}. "
            "**agree**: the interval is on the paper's side of zero; **swap**: on the other side; **unresolved**: "
            "it holds zero, or an end is within Monte-Carlo error of it. (1 seed: x): row x has one seed, so its "
            "seed spread is missing from the interval. Per pair: on how many test groups A is better (mean over "
            "seeds), the exact two-sided sign test over them (ties dropped), and for a resolved verdict the fewest "
            "groups whose removal undoes it (dropping first those that most favour the winner; ≥4: three are not "
            "enough).")
    variants = sorted({(o.a if o.a_for else o.b, o.stands_for) for ps in decided.values() for o in ps if o.stands_for})
    if variants:
        head += (" **v (for x)**: row v, a variant of the paper's row x with no paper numbers of its own, in x's place "
                 "in the paper's pairs of x (never against x; not in the counts): "
                 + ", ".join(f"{v} for {x}" for v, x in variants) + ".")
    return [head, "", *lines, ""]


def orderings(rows: list[dict], metrics: list[str]) -> list[str]:
    """Markdown lines comparing the paper's ranking of a table's rows with ours, per metric (``decide``)."""
    return ordering_lines(rows, decide(rows, metrics))


def signed(x: float, decimals: int) -> str:
    """'+0.01230'; a value that rounds to zero is '+0.00000' whatever its sign (float noise is not a direction)."""
    text = f"{x:+.{decimals}f}"
    return f"{0.0:+.{decimals}f}" if float(text) == 0 else text


def gap_text(gap: Gap, decimals: int) -> str:
    """'Δ +0.01 [-0.02, +0.04] over 15 test models (450 pairs)', or why there is no Δ."""
    if gap.diff is None:
        return gap.why
    d = decimals + 1
    text = f"Δ {signed(gap.diff, d)}"
    if gap.lo is not None:
        text += f" [{signed(gap.lo, d)}, {signed(gap.hi, d)}]"
    text += f" over {gap.n_groups} test {gap.unit} ({gap.n_pairs} pairs)"
    if gap.near:
        text += f", an end within Monte-Carlo error of the threshold at {gap.resamples} resamples"
    return text + (f"; {gap.why}" if gap.why else "")
