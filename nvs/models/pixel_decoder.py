"""Pixel decoder psi_p: transformed latent + skip features -> RGB at 1/8, 1/4, 1/2 and full resolution."""

from __future__ import annotations

import torch
import torch.nn as nn

from nvs.models.blocks import Trunk, conv3, upsample2
from nvs.models.encoder import SKIP_CHANNELS


class PixelDecoder(nn.Module):
    """(B,n,3), {level: features} -> list of RGB (B,3,S/8), (B,3,S/4), (B,3,S/2), (B,3,S) in [-1,1].

    Missing skip levels contribute no channels (chosen at build time from ``skip_levels``). Side predictions are
    upsampled and fed forward into the next stage.
    """

    def __init__(self, image_size: int, n_points: int, skip_levels=tuple(SKIP_CHANNELS), norm: str = "batch"):
        super().__init__()
        # Batch statistics, not per-image ones: instance norm would erase each image's colour levels before the
        # RGB heads.
        c = {lv: (SKIP_CHANNELS[lv] if lv in skip_levels else 0) for lv in SKIP_CHANNELS}
        self.skip_levels = tuple(lv for lv in SKIP_CHANNELS if lv in skip_levels)
        self.trunk = Trunk(n_points * 3, image_size, norm=norm)
        self.s16 = conv3(256 + c["conv4"], 128, norm=norm)
        self.s8 = conv3(128 + c["conv3"], 128, norm=norm)
        self.s4 = conv3(128 + c["conv2"] + 3, 64, norm=norm)
        self.s2 = conv3(64 + 3, 32, norm=norm)
        self.s1 = conv3(32 + c["conv0"] + 3, 32, norm=norm)
        self.rgb8 = nn.Conv2d(128, 3, 3, padding=1, padding_mode="reflect")
        self.rgb4 = nn.Conv2d(64, 3, 3, padding=1, padding_mode="reflect")
        self.rgb2 = nn.Conv2d(32, 3, 3, padding=1, padding_mode="reflect")
        self.rgb1 = nn.Conv2d(32, 3, 3, padding=1, padding_mode="reflect")

    @staticmethod
    def _cat(*xs):
        return torch.cat([x for x in xs if x is not None], dim=1)

    def forward(self, z: torch.Tensor, skips: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        g = skips.get
        x = self.s16(self._cat(self.trunk(z), g("conv4")))
        x = self.s8(self._cat(upsample2(x), g("conv3")))
        r8 = torch.tanh(self.rgb8(x))
        x = self.s4(self._cat(upsample2(x), g("conv2"), upsample2(r8)))
        r4 = torch.tanh(self.rgb4(x))
        x = self.s2(self._cat(upsample2(x), upsample2(r4)))
        r2 = torch.tanh(self.rgb2(x))
        x = self.s1(self._cat(upsample2(x), g("conv0"), upsample2(r2)))
        r1 = torch.tanh(self.rgb1(x))
        return [r8, r4, r2, r1]
