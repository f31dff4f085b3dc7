"""Depth statistics of a drive render (depth_stats.json): a log-spaced histogram of the ground-truth depths, and
the share of them a depth head's range can express."""

from __future__ import annotations

from pathlib import Path

import numpy as np

# Log-spaced bins in metres, 50 per decade from 1 cm to 100 km.
DEPTH_BINS = np.logspace(-2, 5, 7 * 50 + 1)


def depth_histogram(root: Path, ids: list[str]) -> np.ndarray:
    """Counts (len(DEPTH_BINS)+1,) of depth values over the frames: [0] = no data (<= 0), then per bin
    (values beyond the last edge land in the last bin)."""
    counts = np.zeros(len(DEPTH_BINS) + 1, dtype=np.int64)
    for fid in ids:
        d = np.load(root / "depth" / f"{fid}.npy").reshape(-1)
        counts[0] += int((d <= 0).sum())
        v = d[d > 0]
        idx = np.clip(np.searchsorted(DEPTH_BINS, v, side="right") - 1, 0, len(DEPTH_BINS) - 2)
        counts[1:len(DEPTH_BINS)] += np.bincount(idx, minlength=len(DEPTH_BINS) - 1)
    return counts


def representable_fraction(counts, min_depth_m: float, max_depth_m: float) -> float:
    """Fraction of valid depths (counts from depth_histogram) that are certainly inside (min, max) metres:
    only bins entirely inside count, so the answer errs low."""
    counts = np.asarray(counts)
    valid = counts[1:len(DEPTH_BINS)]
    lo, hi = DEPTH_BINS[:-1], DEPTH_BINS[1:]
    inside = (lo >= min_depth_m) & (hi <= max_depth_m)
    total = valid.sum()
    return float(valid[inside].sum() / total) if total else 0.0
