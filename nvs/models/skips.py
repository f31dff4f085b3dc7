"""Skip connections from the encoder to the pixel decoder: warped by the target depth (the paper), warped only where
the warp moves something (adaptive), plain, or none.

Each option is chosen once at build time (Hydra group ``model/skips``); ``levels`` lists the encoder levels used.
Levels that are off cost nothing here, and nothing in the encoder either: every level lies on the encoder's path
to the latent, so there is no skip-only computation to drop (pinned by tests/test_skip.py).
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence

import torch
import torch.nn as nn

import torch.nn.functional as F

from nvs.core.choices import check_choice
from nvs.core.geometry import downsample_depth, max_warp_displacement, scale_intrinsics
from nvs.models.encoder import SKIP_CHANNELS, SKIP_STRIDES
from nvs.models.warp import check_warp, warp

DEPTH_DOWNSAMPLES = ("nearest", "area")
INTRINSICS_SCALINGS = ("code", "exact")


def _check_levels(levels) -> tuple[str, ...]:
    levels = tuple(levels)
    unknown = [lv for lv in levels if lv not in SKIP_CHANNELS]
    if unknown:
        raise ValueError(f"unknown skip level(s) {unknown}; choose from {list(SKIP_CHANNELS)}")
    return levels


class _LevelSkips(nn.Module):
    """Skips that pass a chosen list of encoder levels."""

    def __init__(self, levels: Sequence[str] = ("conv0", "conv2", "conv3", "conv4")):
        super().__init__()
        self.levels = _check_levels(levels)


def _nearest_depth(depth: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """The authors' depth at a level: nearest-neighbour resampling of (B,1,H,W) to ``size``."""
    return F.interpolate(depth, size=size, mode="nearest")


def code_scaled_intrinsics(K: torch.Tensor, s: float) -> torch.Tensor:
    """K (B,3,3) with fx, fy, cx, cy all multiplied by s: the authors' code (exact is ``scale_intrinsics``)."""
    K = K.clone()
    K[:, :2, :] = K[:, :2, :] * s
    return K


class _WarpingSkips(_LevelSkips):
    """Skips warped into the target view; how each level gets its depth, K and warp is chosen at build time.

    ``depth_downsample``: ``nearest`` (the code: every stride-th pixel, F.interpolate's default) or ``area``
    (the mean over each block, matching ``intrinsics_scaling=exact``); ``intrinsics_scaling``: ``code`` (fx, fy,
    cx, cy times 1/stride) or ``exact`` (pixel centres preserved, ``nvs.core.geometry.scale_intrinsics``);
    ``align`` / ``padding``: see ``nvs.models.warp``.
    """

    needs_depth = True

    def __init__(self, levels: Sequence[str] = ("conv0", "conv2", "conv3", "conv4"), align: str = "code", padding: str = "border",
                 depth_downsample: str = "nearest", intrinsics_scaling: str = "code"):
        super().__init__(levels)
        check_warp(align, padding)
        self.align, self.padding = align, padding
        self.depth_downsample = check_choice(depth_downsample, DEPTH_DOWNSAMPLES, "skip_depth")
        self.intrinsics_scaling = check_choice(intrinsics_scaling, INTRINSICS_SCALINGS, "skip_intrinsics")
        # The two fidelity switches as the functions they choose, once.
        self.downsample = _nearest_depth if depth_downsample == "nearest" else downsample_depth
        self.scale_K = code_scaled_intrinsics if intrinsics_scaling == "code" else scale_intrinsics

    def at_level(self, lv: str, f: torch.Tensor, depth: torch.Tensor, K: torch.Tensor):
        """The depth brought to a level's features f (B,C,h,w) and K scaled to it: (B,1,h,w), (B,3,3)."""
        s = SKIP_STRIDES[lv]
        if s == 1:
            return depth, K
        return self.downsample(depth, tuple(f.shape[-2:])), self.scale_K(K, 1.0 / s)

    def warp(self, f, d, K, T):
        return warp(f, d, K, T, self.align, self.padding)[0]


class WarpedSkips(_WarpingSkips):
    """Warp each level's features into the target view with the depth and K brought to that level."""

    def forward(self, feats: dict[str, torch.Tensor], depth: torch.Tensor, K: torch.Tensor,
                T_tgt_src: torch.Tensor) -> dict[str, torch.Tensor]:
        out = {}
        for lv in self.levels:
            d, Ks = self.at_level(lv, feats[lv], depth, K)
            out[lv] = self.warp(feats[lv], d, Ks, T_tgt_src)
        return out


def level_displacement(d: torch.Tensor, K: torch.Tensor, T_tgt_src: torch.Tensor) -> torch.Tensor:
    """Bound on the pixel displacement of warping with depth d (B,1,h,w) at K (B,3,3) -> (B,) float64, per sample.

    Uses the depth map's own per-sample range, so it holds for the depth actually used; any depth that is not
    finite and positive (no data: the warp zeroes those pixels) makes the bound ``inf``.
    """
    flat = d.detach().flatten(1)
    usable = (torch.isfinite(flat) & (flat > 0)).all(1)
    lo = torch.where(usable, flat.amin(1), torch.nan)
    hi = torch.where(usable, flat.amax(1), torch.nan)
    return max_warp_displacement(K, T_tgt_src, lo, hi, tuple(d.shape[-2:]))


class AdaptiveWarpedSkips(_WarpingSkips):
    """Warped skips that skip the warp of a (sample, level) whose bound on the displacement is below threshold_px.

    For each level, ``level_displacement`` bounds how far the warp could move any pixel of that sample at that
    level's resolution (from the pose, K and the depth's range); samples below ``threshold_px`` pass their features
    unwarped, the others are warped as a subset and scattered back. With the identity pose the bound is exactly 0,
    so the output equals the unwarped features (which the exact warp, ``align=exact``, reproduces up to round-off;
    the code's alignment shifts even an identity warp, so there skipping is not output-preserving);
    ``threshold_px=0`` warps everything, as ``WarpedSkips``. Counts of skipped warps per level accumulate until
    ``reset_counts``; ``last_bounds`` holds the last forward's bounds per level. ``nvs.evaluate
    skips_threshold=calibrate`` picks threshold_px on the validation pairs (``nvs.run.skips_calibration``).
    """

    def __init__(self, levels: Sequence[str] = ("conv0", "conv2", "conv3", "conv4"), threshold_px: float = 0.5, align: str = "code",
                 padding: str = "border", depth_downsample: str = "nearest", intrinsics_scaling: str = "code"):
        super().__init__(levels, align, padding, depth_downsample, intrinsics_scaling)
        if not threshold_px >= 0:
            raise ValueError(f"threshold_px must be >= 0, got {threshold_px}")
        self.threshold_px = float(threshold_px)
        self.trained_as = "adaptive"  # "warped": standing in for a trained network's warped skips (from_warped)
        self._forced: frozenset[str] | None = None  # levels_forced: the levels skipped whatever the bounds
        self.reset_counts()

    @classmethod
    def from_warped(cls, skips: WarpedSkips) -> AdaptiveWarpedSkips:
        """The adaptive skips standing in for a trained network's warped ones: the same levels and the same warp, at
        ``threshold_px=0`` (every warp done, so the outputs are those of ``skips``) until a threshold is set."""
        adaptive = cls(skips.levels, 0.0, skips.align, skips.padding, skips.depth_downsample, skips.intrinsics_scaling)
        adaptive.trained_as = "warped"
        return adaptive

    @contextlib.contextmanager
    def per_sample_threshold(self, threshold_px: torch.Tensor):
        """Within the block sample b's threshold is ``threshold_px[b]`` ((B,) float64 on the features' device): the
        threshold calibration's table (``nvs.run.skips_calibration``) evaluates each pair at its own thresholds."""
        kept = self.threshold_px
        self.threshold_px = threshold_px
        try:
            yield
        finally:
            self.threshold_px = kept

    @contextlib.contextmanager
    def levels_forced(self, skipped: Sequence[str]):
        """Within the block the levels in ``skipped`` pass every sample's features unwarped and the other levels warp
        every sample, whatever the bounds: the timing of a study measures each level skipped alone
        (``nvs.sweep.timing``)."""
        unknown = sorted(set(skipped) - set(self.levels))
        if unknown:
            raise ValueError(f"levels_forced: {unknown} are not levels of these skips {list(self.levels)}")
        kept, self._forced = self._forced, frozenset(skipped)
        try:
            yield
        finally:
            self._forced = kept

    def reset_counts(self) -> None:
        # Plain integers, not buffers: counts are per process and never belong in a checkpoint.
        self.skipped = dict.fromkeys(self.levels, 0)
        self.seen = dict.fromkeys(self.levels, 0)
        self.last_bounds: dict[str, torch.Tensor] = {}  # {level: (B,) float64} of the last forward

    def skip_fractions(self) -> dict[str, float]:
        """Fraction of (sample, level) warps skipped since the last reset: per level and over all levels ('all')."""
        seen = sum(self.seen.values())
        if not seen:
            return {}
        out = {lv: self.skipped[lv] / self.seen[lv] for lv in self.levels}
        out["all"] = sum(self.skipped.values()) / seen
        return out

    def forward(self, feats: dict[str, torch.Tensor], depth: torch.Tensor, K: torch.Tensor,
                T_tgt_src: torch.Tensor) -> dict[str, torch.Tensor]:
        out = {}
        for lv in self.levels:
            f = feats[lv]
            d, Ks = self.at_level(lv, f, depth, K)
            bound = self.last_bounds[lv] = level_displacement(d, Ks, T_tgt_src)
            warp = bound >= self.threshold_px if self._forced is None else torch.full_like(
                bound, lv not in self._forced, dtype=torch.bool)
            idx = warp.nonzero()[:, 0]
            n = idx.numel()
            self.seen[lv] += f.shape[0]
            self.skipped[lv] += f.shape[0] - n
            if n == 0:
                out[lv] = f
            elif n == f.shape[0]:
                out[lv] = self.warp(f, d, Ks, T_tgt_src)
            else:
                warped = self.warp(f[idx], d[idx], Ks[idx], T_tgt_src[idx])
                out[lv] = f.index_copy(0, idx, warped)
        return out


class PlainSkips(_LevelSkips):
    """Unwarped source features, as a U-Net would pass them."""

    needs_depth = False

    def forward(self, feats, depth, K, T_tgt_src):
        return {lv: feats[lv] for lv in self.levels}


class NoSkips(nn.Module):
    """No skip connections: the pixel decoder sees only the transformed latent."""

    needs_depth = False
    levels: tuple[str, ...] = ()

    def forward(self, feats, depth, K, T_tgt_src):
        return {}
