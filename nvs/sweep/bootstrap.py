"""Paired two-level bootstrap: whether one row beats another on a metric, with the 95% interval of the gap.

Both rows are compared on the test pairs every one of their jobs (seeds) was tested on (each job's
``test_per_image.csv``). The pairs are grouped by what they show -- objects: the model id of the view ids
(``<model>_<azimuth>_<elevation>``); scenes: the sequence (``<sequence>_<frame>``). Δ is the mean over the pairs of
(row A's mean over its seeds - row B's). Seeds and test groups are crossed (every seed is tested on every group), so
each resample draws both: first each row's seeds, independently, then the test groups with replacement. The seeds
are drawn as flat Dirichlet weights (Rubin's Bayesian bootstrap) rather than with replacement: 2-3 seeds drawn with
replacement have only 3 or 10 outcomes, whose lumps make the tail percentiles erratic; the weights give the same mean
and, scaled, the same variance. A row with one seed keeps it: it has no seed spread to draw, and its verdicts say
"1 seed". Two small-sample corrections, because 11-20 groups and 2-3 seeds make the plain percentile interval too
narrow: each level's deviations are scaled so that the bootstrap variance of its mean is the unbiased one (s^2 / n),
and the interval's ends are the percentiles at the t distribution's tail (G - 1 degrees of freedom, G groups)
instead of the normal's 2.5% (Hesterberg's expanded percentile interval; on symmetric groups, the t interval).

Monte-Carlo error: the draws come from a fixed seed (the same files give the same interval) and number ``RESAMPLES``;
while the threshold (zero, or a goal) lies inside either end's Monte-Carlo band (the order statistics ``MC_Z``
binomial standard errors either side of the end's rank), the draws are doubled, up to ``MAX_RESAMPLES``. An end
still that close is flagged ``near`` and its verdict is unresolved, so no verdict rests on where one seed's draws
happened to fall.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.special import ndtr, stdtrit

PER_IMAGE = "test_per_image.csv"
RESAMPLES = 20_000
MAX_RESAMPLES = 5_120_000
CHUNK = 160_000                # draws made at a time (memory: CHUNK x groups floats)
MC_Z = 4.0                     # the band's half-width in binomial standard errors of the end's rank
LEVEL = 0.95
SEED = 0


def group_of(view_id: str) -> tuple[str, str]:
    """('models', model id) of an object view '<model>_<az>_<el>'; ('sequences', sequence) of a frame '<seq>_<n>'."""
    parts = view_id.rsplit("_", 2)
    if len(parts) == 3 and all(p.lstrip("-").isdigit() for p in parts[1:]):
        return "models", parts[0]
    return "sequences", view_id.split("_", 1)[0]


def _float(text: str) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def read_per_image(path: Path) -> dict[tuple[str, str], dict[str, float]]:
    """{(id_src, id_tgt): {metric: value}} of one job's per-image CSV ({} when the file is absent)."""
    if not path.is_file():
        return {}
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    skip = {"index", "id_src", "id_tgt"}
    return {(r["id_src"], r["id_tgt"]): {k: _float(v) for k, v in r.items() if k not in skip} for r in rows
            if "id_src" in r and "id_tgt" in r}


def read_seeds(dirs: list[Path]) -> list[dict]:
    """One ``read_per_image`` dict per job (seed) of a row; jobs without per-image results left out."""
    return [x for x in (read_per_image(Path(d) / PER_IMAGE) for d in dirs) if x]


def seed_mean(dirs: list[Path]) -> dict[tuple[str, str], dict[str, float]]:
    """Each test pair's metrics averaged over the jobs (seeds) that have it; NaN entries left out."""
    sums: dict[tuple[str, str], dict[str, list[float]]] = {}
    for values_of in read_seeds(dirs):
        for pair, values in values_of.items():
            slot = sums.setdefault(pair, {})
            for k, v in values.items():
                if not math.isnan(v):
                    slot.setdefault(k, []).append(v)
    return {pair: {k: sum(v) / len(v) for k, v in values.items()} for pair, values in sums.items()}


@dataclass(frozen=True)
class Paired:
    """Two rows on one metric over their shared test pairs: per seed, the sum of each test group's values."""

    names: tuple[str, ...]         # (G,) test groups
    counts: np.ndarray             # (G,) pairs per group
    a: np.ndarray                  # (S_A, G) row A: per seed, the sum over each group's pairs
    b: np.ndarray                  # (S_B, G)
    unit: str = "models"

    def without(self, drop: set[int]) -> Paired:
        """The same rows with the groups at the indices ``drop`` left out."""
        keep = [i for i in range(len(self.names)) if i not in drop]
        return Paired(tuple(self.names[i] for i in keep), self.counts[keep], self.a[:, keep], self.b[:, keep],
                      self.unit)

    def group_deltas(self) -> np.ndarray:
        """(G,) each group's mean over its pairs of A - B, both rows averaged over their seeds."""
        return (self.a.mean(0) - self.b.mean(0)) / self.counts

    def group_se(self) -> np.ndarray | None:
        """(G,) the seed spread's standard error of ``group_deltas``; None when neither row has two seeds."""
        var = [x.var(0, ddof=1) / len(x) for x in (self.a / self.counts, self.b / self.counts) if len(x) > 1]
        return np.sqrt(sum(var)) if var else None


def pair_up(a: list[dict], b: list[dict], metric: str) -> Paired | str:
    """Rows A and B (``read_seeds`` lists) on ``metric`` over the pairs all their seeds have; else why not (a str)."""
    if not (a and b):
        return "no per-image results"
    shared = set.intersection(*({p for p, v in job.items() if not math.isnan(v.get(metric, math.nan))}
                                for job in (*a, *b)))
    if not shared:
        return "no shared test pairs with this metric"
    pairs = sorted(shared)
    of = [group_of(p[1]) for p in pairs]
    units = {u for u, _ in of}
    names = tuple(sorted({g for _, g in of}))
    index = {g: i for i, g in enumerate(names)}
    gi = np.array([index[g] for _, g in of])

    def sums(jobs: list[dict]) -> np.ndarray:
        return np.stack([np.bincount(gi, [job[p][metric] for p in pairs], len(names)) for job in jobs])

    unit = units.pop() if len(units) == 1 else "groups"
    return Paired(names, np.bincount(gi, minlength=len(names)).astype(float), sums(a), sums(b), unit)


@dataclass(frozen=True)
class Gap:
    """Row A - row B on one metric over their shared test pairs, with the bootstrap interval (None: not resolvable)."""

    diff: float | None
    lo: float | None
    hi: float | None
    n_pairs: int
    n_groups: int
    unit: str = "models"
    why: str = ""                  # why there is no interval
    seeds: tuple[int, int] = (0, 0)  # jobs of row A, row B
    resamples: int = 0
    near: bool = False             # an end within Monte-Carlo error of the threshold at MAX_RESAMPLES: unresolved


def _seed_draw(x: np.ndarray, r: int, rng: np.random.Generator) -> np.ndarray:
    """(S, G) per-seed sums -> (r, G): the seeds' mean under r draws of flat Dirichlet weights, deviations scaled."""
    s = len(x)
    if s == 1:
        return np.broadcast_to(x[0], (r, x.shape[1]))
    w = rng.dirichlet(np.ones(s), r)                                  # (r, S)
    # Var of a Dirichlet-weighted mean is (S - 1) / (S + 1) of the unbiased s^2 / S: scale the deviations back up
    return (1 / s + math.sqrt((s + 1) / (s - 1)) * (w - 1 / s)) @ x


def _draws(p: Paired, r: int, rng: np.random.Generator) -> np.ndarray:
    """(r,) resampled Δ: seeds within each row, then test groups (see the module doc)."""
    d = _seed_draw(p.a, r, rng) - _seed_draw(p.b, r, rng)           # (r, G) group sums of A - B
    g = len(p.counts)
    t_seed = d.sum(1) / p.counts.sum()
    idx = rng.integers(0, g, (r, g))
    t_group = np.take_along_axis(d, idx, 1).sum(1) / p.counts[idx].sum(1)
    return t_seed + math.sqrt(g / (g - 1)) * (t_group - t_seed)


def tail_probability(n_groups: int, level: float = LEVEL) -> float:
    """The lower end's percentile / 100: the normal tail at the t quantile with G - 1 degrees of freedom."""
    return float(ndtr(-stdtrit(n_groups - 1, 1 - (1 - level) / 2)))


def _ends(stats: np.ndarray, q: float, threshold: float) -> tuple[float, float, bool]:
    """(lo, hi) percentiles of the sorted draws, and whether ``threshold`` is inside either end's MC band."""
    r = len(stats)
    lo, hi = np.quantile(stats, [q, 1 - q])
    half = MC_Z * math.sqrt(r * q * (1 - q))
    near = False
    for rank in (q * (r - 1), (1 - q) * (r - 1)):
        band = stats[max(0, math.floor(rank - half))], stats[min(r - 1, math.ceil(rank + half))]
        near |= bool(band[0] <= threshold <= band[1])
    return float(lo), float(hi), near


def bootstrap(p: Paired, threshold: float = 0.0, level: float = LEVEL, seed: int = SEED,
              max_resamples: int = MAX_RESAMPLES) -> Gap:
    """The two-level bootstrap of Δ = A - B over ``p`` (see the module doc); ``threshold`` is what a verdict is
    decided against (zero for an ordering, the goal for a goal), where the Monte-Carlo check looks."""
    n = int(p.counts.sum())
    diff = float((p.a.mean(0) - p.b.mean(0)).sum() / n)
    seeds = (len(p.a), len(p.b))
    if len(p.names) < 2:
        return Gap(diff, None, None, n, len(p.names), p.unit, f"one test {p.unit[:-1]}: nothing to resample", seeds)
    rng = np.random.default_rng(seed)
    q = tail_probability(len(p.names), level)
    draws, r = [_draws(p, RESAMPLES, rng)], RESAMPLES
    while True:
        lo, hi, near = _ends(np.sort(np.concatenate(draws)), q, threshold)
        if not near or r >= max_resamples:
            break
        draws += [_draws(p, min(CHUNK, r - start), rng) for start in range(0, r, CHUNK)]
        r *= 2
    return Gap(diff, lo, hi, n, len(p.names), p.unit, seeds=seeds, resamples=r, near=near)


def paired_gap(a: list[dict], b: list[dict], metric: str, threshold: float = 0.0, seed: int = SEED) -> Gap:
    """``bootstrap`` of rows A and B (``read_seeds`` lists) on ``metric``; a Gap without interval when not possible."""
    p = pair_up(a, b, metric)
    if isinstance(p, str):
        return Gap(None, None, None, 0, 0, why=p, seeds=(len(a), len(b)))
    return bootstrap(p, threshold, seed=seed)


def verdict(gap: Gap, higher_is_better: bool) -> str:
    """'agree' when the interval says A is better than B (the paper's order), 'swap' when B is, else 'unresolved'."""
    if gap.lo is None or gap.hi is None or gap.near:
        return "unresolved"
    lo, hi = (-gap.hi, -gap.lo) if higher_is_better else (gap.lo, gap.hi)  # lower is better from here on
    if hi < 0:
        return "agree"
    if lo > 0:
        return "swap"
    return "unresolved"


def one_seed_note(gap: Gap, a: str | None, b: str | None) -> str:
    """' (1 seed: a)' when a named row was compared at one seed (no seed spread in its interval); else ''."""
    single = [name for name, s in zip((a, b), gap.seeds) if name is not None and s == 1]
    return f" (1 seed: {', '.join(single)})" if single else ""


def interval_words() -> str:
    """How the intervals are computed, for the tables' explanatory lines."""
    return (f"the small-sample corrected percentile interval (module doc of `nvs/sweep/bootstrap.py`), "
            f"{RESAMPLES} to {MAX_RESAMPLES} resamples (more where an end lies near the threshold), seeded")
