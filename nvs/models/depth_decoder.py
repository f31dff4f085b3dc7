"""Depth decoder psi_d: latent (B,n,3) -> depth (B,1,S,S); the authors' ``depthDecoder`` (BatchNorm, no skips)."""

from __future__ import annotations

import torch
import torch.nn as nn

from nvs.models.blocks import Trunk, UpStage

# Widths of the stages after the trunk: S/8, S/4, S/2, S (the authors' at 256^2).
WIDTHS = (256, 128, 64, 32)


class DepthDecoder(nn.Module):
    """(B,n,3) -> raw (B,1,S,S) -> head -> depth.

    The trunk to S/16 (256 channels), then bilinear x2 stages of 256, 128, 64, 32 channels, each with BatchNorm and
    LeakyReLU(0.2), and a 3x3 conv (zero padding) to one channel; the head maps it to depth.
    """

    def __init__(self, image_size: int, n_points: int, head: nn.Module):
        super().__init__()
        self.trunk = Trunk(n_points * 3, image_size, norm="batch")
        widths = (256,) + WIDTHS
        self.stages = nn.ModuleList([UpStage(widths[i], widths[i + 1], False, "batch") for i in range(len(WIDTHS))])
        self.out = nn.Conv2d(WIDTHS[-1], 1, 3, padding=1)
        self.head = head

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = self.trunk(z)
        for stage in self.stages:
            x = stage(x)
        return self.head(self.out(x))
