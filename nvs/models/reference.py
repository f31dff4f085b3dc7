"""Reference rows that need no training: the floor (copy the source) and the ceiling of depth-based warping."""

from __future__ import annotations

import torch
import torch.nn as nn

from nvs.geometry import inverse_warp
from nvs.types import Batch, Outputs


class CopySource(nn.Module):
    """Predicts the source image unchanged: the floor any method must beat."""

    def __init__(self, image_size: int | None = None):
        super().__init__()

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        src = batch["src"]
        return {"rgb": src, "rgb_scales": [src * 2 - 1]}


class GroundTruthWarp(nn.Module):
    """Warps the source with the ground-truth target depth: the ceiling a pure depth-based warping method could reach
    on the rendered data (needs ``depth_tgt``).

    Pixels without ground-truth depth: for ``data_format='objects'`` they are background with no surface, so they
    and pixels with no correspondence are filled white. For ``'scenes'`` they are sky: warped as if ``sky_depth``
    away, and pixels with no correspondence keep the source pixel.
    """

    def __init__(self, image_size: int | None = None, fill: float = 1.0, data_format: str = "objects",
                 sky_depth: float = 100.0):
        super().__init__()
        if data_format not in ("objects", "scenes"):
            raise ValueError(f"data_format={data_format!r}: expected 'objects' or 'scenes'")
        self.fill = fill
        self.missing_depth = sky_depth if data_format == "scenes" else None

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        if "depth_tgt" not in batch:
            raise KeyError("GroundTruthWarp needs ground-truth target depth (data.loader.with_depth=true, depth/ files)")
        depth = batch["depth_tgt"]
        fill = self.fill
        if self.missing_depth is not None:
            depth = torch.where(depth > 0, depth, torch.full_like(depth, float(self.missing_depth)))
            fill = batch["src"]
        warped, valid = inverse_warp(batch["src"], depth, batch["K"], batch["T_tgt_src"])
        rgb = warped * valid + fill * (1 - valid)
        return {"rgb": rgb, "rgb_scales": [rgb * 2 - 1], "depth": depth}
