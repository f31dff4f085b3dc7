"""``nvs.evaluate skips_threshold=calibrate``: the adaptive skips' ``threshold_px`` (``model/skips=adaptive``) chosen
on the validation pairs instead of the trained 0.5 px: the largest threshold whose mean validation L1 stays within
``calibration.tolerance`` of threshold 0 (every warp done) (docs/skipping.md). A network trained with warped skips
(``model/skips=warped``) is given adaptive ones in their place first: threshold 0 is the trained network itself.

Exact over every threshold at the cost of L + 1 pixel-decoder runs per pair (L skip levels): as the threshold grows,
a pair's levels are skipped in the order of their displacement bounds, so a pair has at most L + 1 outcomes. Each one
is computed (the pair's own threshold just above its k-th smallest bound), and the mean L1 at a threshold t reads,
per pair, the outcome with the levels whose bound is below t skipped. The candidates are 0, every distinct finite
bound seen (each the largest threshold of the interval below it) and the one just above the largest bound.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from nvs.core.errors import UserError
from nvs.core.types import to_image_range
from nvs.data.datamodule import NVSDataModule
from nvs.metrics import per_image as M
from nvs.models.skips import AdaptiveWarpedSkips, WarpedSkips
from nvs.module.lightning_module import NVSModule
from nvs.run.validation_pass import Calibration, validation_columns

# Slack on the L1 budget for the round-off of summing the same values in another order.
_BUDGET_RTOL = 1e-12


def threshold_option(value) -> str | float | None:
    """``skips_threshold=``: None (the checkpoint's own), ``"calibrate"`` or a threshold in px (>= 0)."""
    if value is None or value == "calibrate":
        return value
    if not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value) and value >= 0:
        return float(value)
    raise UserError(f"skips_threshold={value!r}: expected null (the checkpoint's own threshold_px), calibrate or a "
                    "threshold in pixels >= 0")


def adaptive_skips(module: NVSModule) -> AdaptiveWarpedSkips:
    """The network's adaptive skips. A network trained with warped skips (``model/skips=warped``, the paper's) gets
    adaptive ones in their place, at threshold 0 (its own outputs) until one is set: skipping a warp needs no
    retraining. A network with neither (or several sets) is one UserError."""
    found = [m for m in module.net.modules() if isinstance(m, AdaptiveWarpedSkips)]
    if not found:
        found = _adaptive_in_place_of_warped(module.net)
    if len(found) != 1:
        raise UserError(f"skips_threshold: model '{module.model_name}' has no warped skips to skip "
                        "(model/skips=warped or adaptive); drop skips_threshold")
    return found[0]


def _adaptive_in_place_of_warped(net: torch.nn.Module) -> list[AdaptiveWarpedSkips]:
    """Put adaptive skips in place of the network's one set of warped skips -> [them] (nothing changed: [])."""
    slots = [(parent, name, child) for parent in net.modules() for name, child in parent.named_children()
             if type(child) is WarpedSkips]
    if len(slots) != 1:
        return []
    parent, name, warped = slots[0]
    adaptive = AdaptiveWarpedSkips.from_warped(warped)
    setattr(parent, name, adaptive)
    return [adaptive]


def _columns(skips: AdaptiveWarpedSkips):
    """Per pair: each level's bound (``bound_<level>``) and the L1 with its k smallest-bound levels skipped
    (``l1_<k>``, k = 0 .. L)."""
    def columns(net, batch) -> dict[str, torch.Tensor]:
        encoded = net.encode(batch["src"])
        z_t, depth = net.predict_depth(encoded, batch)

        def l1_at(threshold: torch.Tensor) -> torch.Tensor:
            with skips.per_sample_threshold(threshold):
                return M.l1(to_image_range(net.decode_pixels(encoded, z_t, depth, batch)[-1]), batch["tgt"])

        out = {"l1_0": l1_at(torch.zeros(depth.shape[0], dtype=torch.float64, device=depth.device))}
        bounds = torch.stack([skips.last_bounds[lv] for lv in skips.levels], 1)  # (B, L) float64
        ordered = bounds.sort(1).values
        for k in range(1, len(skips.levels) + 1):
            out[f"l1_{k}"] = l1_at(torch.nextafter(ordered[:, k - 1], torch.full_like(ordered[:, 0], math.inf)))
        return {**out, **{f"bound_{lv}": bounds[:, i] for i, lv in enumerate(skips.levels)}}

    return columns


def pick_threshold(bounds: np.ndarray, l1: np.ndarray, tolerance: float) -> tuple[float, dict]:
    """The largest threshold whose mean L1 is at most ``(1 + tolerance)`` x threshold 0's.

    bounds (n, L) each pair's bound per level; l1 (n, L + 1) its L1 with its k smallest-bound levels skipped ->
    (threshold_px, {n_pairs, tolerance, l1_at_zero, l1_at_threshold, skipped_at_threshold, candidates})."""
    n, L = bounds.shape
    finite = np.unique(bounds[np.isfinite(bounds)])
    top = [np.nextafter(finite[-1], np.inf)] if len(finite) else []
    candidates = np.concatenate([[0.0], finite[finite > 0], top])
    skipped = (bounds[None] < candidates[:, None, None]).sum(-1)  # (t, n): levels skipped per pair
    mean_l1 = l1[np.arange(n)[None], skipped].mean(1)
    feasible = mean_l1 <= (1 + tolerance) * mean_l1[0] * (1 + _BUDGET_RTOL)
    i = int(np.nonzero(feasible)[0].max())  # threshold 0 is always feasible
    return float(candidates[i]), {"n_pairs": n, "tolerance": float(tolerance), "l1_at_zero": float(mean_l1[0]),
                                  "l1_at_threshold": float(mean_l1[i]),
                                  "skipped_at_threshold": float(skipped[i].sum() / (n * L)),
                                  "candidates": len(candidates)}


def calibrate(module: NVSModule, datamodule: NVSDataModule, settings: Calibration, placement: dict,
              precision) -> dict:
    """Pick the threshold on the validation pairs and set it on the network -> the calibration's record."""
    skips = adaptive_skips(module)
    if settings.tolerance < 0:
        raise UserError(f"calibration.tolerance={settings.tolerance}: skips_threshold=calibrate needs a tolerance "
                        ">= 0 (its reference, threshold 0, is one of the thresholds it picks from)")
    table = validation_columns(module.net, datamodule, _columns(skips), settings, placement, precision)
    bounds = np.stack([table[f"bound_{lv}"] for lv in skips.levels], 1)
    l1 = np.stack([table[f"l1_{k}"] for k in range(len(skips.levels) + 1)], 1)
    threshold, stats = pick_threshold(bounds, l1, settings.tolerance)
    trained = skips.threshold_px
    skips.threshold_px = threshold
    return {"threshold_px": threshold, "trained_threshold_px": trained, "trained_skips": skips.trained_as,
            "source": "calibrate", "validation": stats}


def set_threshold(module: NVSModule, threshold: float) -> dict:
    """``skips_threshold=<px>``: that threshold on the network -> its record."""
    skips = adaptive_skips(module)
    trained, skips.threshold_px = skips.threshold_px, float(threshold)
    return {"threshold_px": float(threshold), "trained_threshold_px": trained, "trained_skips": skips.trained_as,
            "source": "given"}
