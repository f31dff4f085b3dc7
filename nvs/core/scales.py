"""The multi-scale predictions (``Outputs["rgb_scales"]``): how a coarse one is brought to full size.

Read by the pixel decoder (its side outputs) and the reconstruction loss alike, so both resize the same way.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

# nearest: the authors' code; bilinear: align_corners=False, the resize used everywhere else in nvs.
UPSAMPLES = ("nearest", "bilinear")


def upsample_side(x: torch.Tensor, size: tuple[int, int], mode: str) -> torch.Tensor:
    """A side prediction (B,3,h,w) brought to ``size`` (H,W) by ``mode`` (one of UPSAMPLES) -> (B,3,H,W)."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    if mode == "nearest":
        return F.interpolate(x, size=size, mode="nearest")
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False)
