"""Reference rows that need no training: the floor (copy the source) and the ceiling of depth-based warping."""

from __future__ import annotations

import torch
import torch.nn as nn

from nvs.core.geometry import inverse_warp
from nvs.core.types import Batch, Outputs

# Models evaluated without training (``nvs.evaluate model=...``, ``conf/model/<name>.yaml``), the floors and ceilings of every table: copying the
# source, the ground-truth warp, the constant depth at the training views' mean, each test image's ground-truth plane.
REFERENCE_MODELS = ("copy_source", "gt_warp", "mean_depth", "gt_plane")


class CopySource(nn.Module):
    """Predicts the source image unchanged: the floor any method must beat.

    No ``n_scales``: a reference trains nothing, so no loss is checked against it (training one stops at the start
    with the message that it has no trainable parameters).
    """

    def __init__(self, image_size: int | None = None):
        super().__init__()

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        src = batch["src"]
        return {"rgb": src, "rgb_scales": [src * 2 - 1]}


class GroundTruthWarp(nn.Module):
    """Warps the source with the ground-truth target depth: the ceiling a pure depth-based warping method could reach
    on the rendered data (needs ``depth_tgt``).

    Pixels without ground-truth depth: with ``sky_disparity=None`` they are background with no surface, so they and
    pixels with no correspondence are filled with ``fill`` (white). With a disparity they are sky, warped as if
    ``1 / sky_disparity`` away, and pixels with no correspondence keep the source pixel (``conf/model/gt_warp.yaml``
    reads it from the data config's depth head: its far limit).
    """

    def __init__(self, image_size: int | None = None, fill: float = 1.0, sky_disparity: float | None = None):
        super().__init__()
        if sky_disparity is not None and not sky_disparity > 0:
            raise ValueError(f"sky_disparity={sky_disparity!r}: a positive disparity, or null for no sky")
        self.fill = fill
        self.sky_depth = None if sky_disparity is None else 1.0 / float(sky_disparity)
        # What stands where the ground truth has no depth, chosen once: (depth, fill) from (depth, src).
        self.missing = self._background if sky_disparity is None else self._sky

    def _background(self, depth: torch.Tensor, src: torch.Tensor) -> tuple[torch.Tensor, float]:
        return depth, self.fill

    def _sky(self, depth: torch.Tensor, src: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.where(depth > 0, depth, torch.full_like(depth, self.sky_depth)), src

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        if "depth_tgt" not in batch:
            raise KeyError("GroundTruthWarp needs ground-truth target depth (data.loader.with_depth=true, depth/ files)")
        depth, fill = self.missing(batch["depth_tgt"], batch["src"])
        warped, valid = inverse_warp(batch["src"], depth, batch["K"], batch["T_tgt_src"])
        rgb = warped * valid + fill * (1 - valid)
        return {"rgb": rgb, "rgb_scales": [rgb * 2 - 1], "depth": depth}
