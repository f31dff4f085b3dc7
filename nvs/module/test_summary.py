"""What the test loop writes per pair beyond the metrics, and the means ``metrics.json`` reports over the pairs."""

from __future__ import annotations

import math

from nvs.core.metric_spec import METRICS
from nvs.core.types import ROUTES, Outputs


def _mean(values: list[float]) -> float:
    """The mean of the values that are not NaN (NaN when none is)."""
    vals = [v for v in values if not math.isnan(v)]
    return sum(vals) / len(vals) if vals else float("nan")


def metric_means(rows: list[dict]) -> dict[str, float]:
    """Each metric's mean over the rows (its NaN entries, e.g. no valid depth, ignored), in metric_spec's order."""
    return {k: _mean([r[k] for r in rows]) for k in METRICS if rows and k in rows[0]}


def route_columns(out: Outputs, i: int) -> dict:
    """A routed network's (``nvs.models.route``) per-pair columns of pair ``i``: the route it took and the features
    the rule read (NaN: not computed for it); nothing for any other network."""
    if "route" not in out:
        return {}
    return {"route": ROUTES[int(out["route"][i])], **{k: float(v[i]) for k, v in out["route_features"].items()}}


def route_summary(rows: list[dict]) -> dict[str, float | None]:
    """``route_share_<route>`` (fraction of the pairs) and ``route_l1_<route>`` (their mean L1, None without pairs)
    for each route, when the rows carry one; else nothing."""
    if not rows or "route" not in rows[0]:
        return {}
    out: dict[str, float | None] = {}
    for route in ROUTES:
        mine = [r for r in rows if r["route"] == route]
        out[f"route_share_{route}"] = len(mine) / len(rows)
        out[f"route_l1_{route}"] = _mean([r["l1"] for r in mine]) if mine else None
    return out
