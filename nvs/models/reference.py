"""Reference rows that need no training: the floor (copy the source) and the ceiling of depth-based warping."""

from __future__ import annotations

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
    """Warps the source with the ground-truth target depth; pixels with no correspondence stay white (background).

    The ceiling a pure depth-based warping method could reach on the rendered data (needs ``depth_tgt``).
    """

    def __init__(self, image_size: int | None = None, fill: float = 1.0):
        super().__init__()
        self.fill = fill

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        if "depth_tgt" not in batch:
            raise KeyError("GroundTruthWarp needs ground-truth target depth (data.loader.with_depth=true, depth/ files)")
        depth = batch["depth_tgt"]
        warped, valid = inverse_warp(batch["src"], depth, batch["K"], batch["T_tgt_src"])
        rgb = warped * valid + self.fill * (1 - valid)
        return {"rgb": rgb, "rgb_scales": [rgb * 2 - 1], "depth": depth}
