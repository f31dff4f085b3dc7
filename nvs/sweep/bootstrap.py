"""Paired bootstrap over test models: whether one row beats another on a metric, with the 95% interval of the gap.

Both rows are compared on the test pairs they share (each job's ``test_per_image.csv``; a row with several seeds
contributes each pair's mean over its seeds). The pairs are grouped by what they show -- objects: the model id of
the view ids (``<model>_<azimuth>_<elevation>``); scenes: the sequence (``<sequence>_<frame>``) -- and the groups are
resampled with replacement (``RESAMPLES`` times, a fixed seed: the same files give the same interval). Each resample's
statistic is the mean over its pairs of (row A - row B); the interval is the 2.5th and 97.5th percentile.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

PER_IMAGE = "test_per_image.csv"
RESAMPLES = 2000
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


def seed_mean(dirs: list[Path]) -> dict[tuple[str, str], dict[str, float]]:
    """Each test pair's metrics averaged over the jobs (seeds) that have it; NaN entries left out."""
    sums: dict[tuple[str, str], dict[str, list[float]]] = {}
    for d in dirs:
        for pair, values in read_per_image(Path(d) / PER_IMAGE).items():
            slot = sums.setdefault(pair, {})
            for k, v in values.items():
                if not math.isnan(v):
                    slot.setdefault(k, []).append(v)
    return {pair: {k: sum(v) / len(v) for k, v in values.items()} for pair, values in sums.items()}


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


def paired_gap(a: dict, b: dict, metric: str, resamples: int = RESAMPLES, level: float = LEVEL,
               seed: int = SEED) -> Gap:
    """The paired bootstrap of ``a[pair][metric] - b[pair][metric]`` over test groups (see the module doc)."""
    pairs = sorted(p for p in set(a) & set(b) if not (math.isnan(a[p].get(metric, math.nan))
                                                       or math.isnan(b[p].get(metric, math.nan))))
    if not pairs:
        why = "no per-image results" if not (a and b) else "no shared test pairs with this metric"
        return Gap(None, None, None, 0, 0, why=why)
    groups: dict[str, list[float]] = {}
    units = set()
    for p in pairs:
        unit, g = group_of(p[1])
        units.add(unit)
        groups.setdefault(g, []).append(a[p][metric] - b[p][metric])
    unit = units.pop() if len(units) == 1 else "groups"
    sums = np.array([sum(v) for v in groups.values()])
    counts = np.array([len(v) for v in groups.values()], dtype=float)
    diff = float(sums.sum() / counts.sum())
    if len(groups) < 2:
        return Gap(diff, None, None, len(pairs), len(groups), unit, why=f"one test {unit[:-1]}: nothing to resample")
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(groups), size=(resamples, len(groups)))
    stats = sums[idx].sum(axis=1) / counts[idx].sum(axis=1)
    tail = 100 * (1 - level) / 2
    lo, hi = np.percentile(stats, [tail, 100 - tail])
    return Gap(diff, float(lo), float(hi), len(pairs), len(groups), unit)


def verdict(gap: Gap, higher_is_better: bool) -> str:
    """'agree' when the interval says A is better than B (the paper's order), 'swap' when B is, else 'unresolved'."""
    if gap.lo is None or gap.hi is None:
        return "unresolved"
    lo, hi = (-gap.hi, -gap.lo) if higher_is_better else (gap.lo, gap.hi)  # lower is better from here on
    if hi < 0:
        return "agree"
    if lo > 0:
        return "swap"
    return "unresolved"
