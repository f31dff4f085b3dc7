"""Skip connections from the encoder to the pixel decoder: warped by the target depth (the paper), plain, or none.

Each option is chosen once at build time (Hydra group ``model/skips``); ``levels`` lists the encoder levels used.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from nvs.geometry import downsample_depth, inverse_warp, scale_intrinsics
from nvs.models.encoder import SKIP_CHANNELS, SKIP_STRIDES


def _check_levels(levels) -> tuple[str, ...]:
    levels = tuple(levels)
    unknown = [lv for lv in levels if lv not in SKIP_CHANNELS]
    if unknown:
        raise ValueError(f"unknown skip level(s) {unknown}; choose from {list(SKIP_CHANNELS)}")
    return levels


class _LevelSkips(nn.Module):
    """Skips that pass a chosen list of encoder levels."""

    def __init__(self, levels=("conv0", "conv2", "conv3", "conv4")):
        super().__init__()
        self.levels = _check_levels(levels)


class WarpedSkips(_LevelSkips):
    """Warp each level's features into the target view with the depth downsampled to it and K scaled to it."""

    needs_depth = True

    def forward(self, feats: dict[str, torch.Tensor], depth: torch.Tensor, K: torch.Tensor,
                T_tgt_src: torch.Tensor) -> dict[str, torch.Tensor]:
        out = {}
        for lv in self.levels:
            f = feats[lv]
            s = SKIP_STRIDES[lv]
            d = downsample_depth(depth, tuple(f.shape[-2:]))
            Ks = scale_intrinsics(K, 1.0 / s) if s != 1 else K
            out[lv], _ = inverse_warp(f, d, Ks, T_tgt_src)
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
