"""The routing rule of ``nvs.models.route``: thresholds on a pair's cheap features that send it to ``copy``, ``warp``
or ``full``, and its fit on validation pairs (docs/skipping.md).

The rule, for one pair with features ``pose_px`` (the pose's bound on the displacement), ``disocclusion`` and
``disp_mean_px`` (of the warp by the predicted depth):
    copy  if pose_px <= copy_pose_px
    warp  elif disocclusion <= warp_disocclusion and disp_mean_px <= warp_displacement_px
    full  otherwise
A threshold of None never fires (a NaN or an infinite feature never passes one either).

The fit (:func:`fit_rule`) tries every combination of up to ``candidates`` thresholds per feature (observed values,
spread over their sorted distinct values, plus "never") and keeps the one of least mean cost whose mean validation L1
is at most ``(1 + tolerance)`` times the full decoder's. Ties go to the lower L1, then to the smaller thresholds
(enumeration order), so the fit is deterministic. All-``full`` qualifies at any tolerance >= 0. A negative tolerance
is a margin for the test pairs: a rule that routes anything must beat the full decoder on validation by that
fraction; where none does, the fit is all-``full`` (the network itself, every pair through the full decoder) and its
statistics say so (``margin_met: false``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from nvs.core.types import ROUTES

# The features a routed network computes per pair (``Outputs["route_features"]``), in the per-image CSV's order.
FEATURES = ("pose_px", "disp_mean_px", "disp_max_px", "disocclusion")
THRESHOLDS = ("copy_pose_px", "warp_disocclusion", "warp_displacement_px")
# Slack on the L1 budget for the round-off of summing the same values in another order.
_BUDGET_RTOL = 1e-12


def _never(value: float | None) -> float:
    return float("-inf") if value is None else float(value)


@dataclass(frozen=True)
class RouteRule:
    """Thresholds of the three routes (None: the route is never taken)."""

    copy_pose_px: float | None = None
    warp_disocclusion: float | None = None
    warp_displacement_px: float | None = None

    def copies(self, pose_px):
        """Bool mask (tensor or array, like ``pose_px`` (B,)): the pairs routed ``copy``."""
        return pose_px <= _never(self.copy_pose_px)

    def warps(self, disocclusion, disp_mean_px):
        """Bool mask: the pairs routed ``warp`` among those not copied."""
        return (disocclusion <= _never(self.warp_disocclusion)) & (disp_mean_px <= _never(self.warp_displacement_px))

    def routes(self, pose_px: np.ndarray, disocclusion: np.ndarray, disp_mean_px: np.ndarray) -> np.ndarray:
        """(n,) int: each pair's index into ``ROUTES``."""
        copy = self.copies(np.asarray(pose_px))
        warp = ~copy & self.warps(np.asarray(disocclusion), np.asarray(disp_mean_px))
        return np.where(copy, ROUTES.index("copy"), np.where(warp, ROUTES.index("warp"), ROUTES.index("full")))

    def as_dict(self) -> dict[str, float | None]:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict, where: str) -> RouteRule:
        """The rule of ``values`` (keys THRESHOLDS, each a finite number or null); ``where`` names the mapping in the
        error (``<file>: rule``): a missing, unknown or non-numeric key is one ValueError naming it."""
        if not isinstance(values, dict):
            raise ValueError(f"{where}: expected a mapping of {', '.join(THRESHOLDS)}, got {type(values).__name__}")
        expected = f"(expected {', '.join(THRESHOLDS)})"
        missing = [k for k in THRESHOLDS if k not in values]
        if missing:
            raise ValueError(f"{where}: missing key '{missing[0]}' {expected}")
        unknown = sorted(set(values) - set(THRESHOLDS))
        if unknown:
            raise ValueError(f"{where}: unknown key '{unknown[0]}' {expected}")
        for key in THRESHOLDS:
            v = values[key]
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v)):
                raise ValueError(f"{where}.{key}: {v!r} is not a finite number or null")
        return cls(**{k: None if values[k] is None else float(values[k]) for k in THRESHOLDS})


def _candidates(x: np.ndarray, k: int) -> np.ndarray:
    """-inf ("never"), then up to ``k`` observed finite values of ``x`` spread evenly over its sorted distinct ones."""
    v = np.unique(x[np.isfinite(x)])
    if len(v) > k:
        v = v[np.unique(np.round(np.linspace(0, len(v) - 1, k)).astype(int))]
    return np.concatenate([[-np.inf], v])


def fit_rule(features: dict[str, np.ndarray], l1: dict[str, np.ndarray], costs: dict[str, float], tolerance: float,
             candidates: int = 32) -> tuple[RouteRule, dict]:
    """The rule of least mean cost whose mean L1 is within ``tolerance`` of the full decoder's, and its statistics.

    features: {pose_px, disocclusion, disp_mean_px: (n,)} per validation pair; l1: {route: (n,)} each route's L1 on
    every pair; costs: {route: cost of one pair} (any unit); tolerance > -1 (0.01: 1 % more L1 allowed; a negative
    one asks a rule that routes anything to be that much better than the full decoder; where none is, the rule is
    all-full); candidates: thresholds tried per feature. -> (rule, {n_pairs, tolerance, margin_met, l1_<route>,
    l1_routed, l1_budget, share_<route>, cost, cost_full}) with costs as means per pair; margin_met is False only
    where a negative tolerance found no rule and the all-full one was kept.
    """
    if not tolerance > -1:
        raise ValueError(f"tolerance={tolerance!r}: expected a number > -1")
    if isinstance(candidates, bool) or not isinstance(candidates, int) or candidates < 1:
        raise ValueError(f"candidates={candidates!r}: expected a positive integer")
    pose, disocc, disp = (np.asarray(features[k], dtype=np.float64) for k in ("pose_px", "disocclusion",
                                                                              "disp_mean_px"))
    table = np.stack([np.asarray(l1[r], dtype=np.float64) for r in ROUTES])  # (3, n)
    n = table.shape[1]
    if n == 0 or any(len(a) != n for a in (pose, disocc, disp)):
        raise ValueError(f"need the same positive number of pairs in every column, got features {len(pose)}, "
                         f"{len(disocc)}, {len(disp)} and L1 {n}")
    if not np.isfinite(table).all():
        raise ValueError("the L1 table holds non-finite values")
    cost = np.asarray([float(costs[r]) for r in ROUTES])
    budget = (1 + tolerance) * table[2].sum()
    A, Bd, C = _candidates(pose, candidates), _candidates(disocc, candidates), _candidates(disp, candidates)
    warp_ok = (disocc[None, :] <= Bd[:, None])[:, None, :] & (disp[None, :] <= C[:, None])[None, :, :]  # (b,c,n)
    best = None
    for ia, a in enumerate(A):
        copy = pose <= a
        warp = warp_ok & ~copy
        full = ~warp & ~copy
        n_copy, n_warp, n_full = int(copy.sum()), warp.sum(-1), full.sum(-1)
        total_cost = n_copy * cost[0] + n_warp * cost[1] + n_full * cost[2]
        total_l1 = table[0][copy].sum() + (warp * table[1]).sum(-1) + (full * table[2]).sum(-1)
        feasible = total_l1 <= budget * (1 + _BUDGET_RTOL)
        for ib, ic in zip(*np.nonzero(feasible)):  # enumeration order: b, then c ascending
            key = (total_cost[ib, ic], total_l1[ib, ic])
            if best is None or key < best[0]:
                best = (key, ia, ib, ic)
    margin_met = best is not None  # None only with a negative tolerance: all-full (a = b = -inf) is feasible at >= 0
    _, ia, ib, ic = best if margin_met else (None, 0, 0, 0)  # index 0 of every candidate list: -inf, "never"
    rule = _rule(A[ia], Bd[ib], C[ic])
    routes = rule.routes(pose, disocc, disp)
    routed = table[routes, np.arange(n)]
    stats = {"n_pairs": n, "tolerance": float(tolerance), "margin_met": margin_met, "l1_routed": float(routed.mean()),
             "l1_budget": float(budget / n), "cost": float(cost[routes].mean()), "cost_full": float(cost[2]),
             **{f"l1_{r}": float(table[i].mean()) for i, r in enumerate(ROUTES)},
             **{f"share_{r}": float((routes == i).mean()) for i, r in enumerate(ROUTES)}}
    return rule, stats


def _rule(a: float, b: float, c: float) -> RouteRule:
    finite = lambda x: None if np.isneginf(x) else float(x)  # noqa: E731
    warp = np.isneginf(b) or np.isneginf(c)  # either one "never": no pair is warped
    return RouteRule(finite(a), None if warp else finite(b), None if warp else finite(c))
