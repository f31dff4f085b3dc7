"""Depth decoder psi_d: latent (B,n,3) -> depth (B,1,S,S); the pixel decoder's trunk without skips, with BatchNorm."""

from __future__ import annotations

import torch
import torch.nn as nn

from nvs.models.blocks import Trunk, conv3, upsample2


class DepthDecoder(nn.Module):
    """(B,n,3) -> raw (B,1,S,S) -> head -> depth. Several latents are decoded in one call so BatchNorm sees one batch."""

    def __init__(self, image_size: int, n_points: int, head: nn.Module):
        super().__init__()
        self.trunk = Trunk(n_points * 3, image_size, norm="batch")
        chans = [256, 64, 64, 32, 32, 16]  # 1/16, 1/8, 1/4, 1/2, 1 (then the output conv)
        self.convs = nn.ModuleList([conv3(chans[i], chans[i + 1], norm="batch") for i in range(5)])
        self.out = nn.Conv2d(16, 1, 3, padding=1, padding_mode="reflect")
        self.head = head

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = self.convs[0](self.trunk(z))
        for conv in self.convs[1:]:
            x = conv(upsample2(x))
        return self.head(self.out(x))
