"""Encoder phi: image -> latent points z (B,n,3) and skip features conv0 (1), conv2 (1/4), conv3 (1/8), conv4 (1/16)."""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from nvs.core.choices import check_choice
from nvs.models.blocks import NORMS, PADDINGS, conv3, down

SKIP_CHANNELS = {"conv0": 64, "conv2": 128, "conv3": 256, "conv4": 256}
SKIP_STRIDES = {"conv0": 1, "conv2": 4, "conv3": 8, "conv4": 16}


class Encoder(nn.Module):
    """The paper's encoder (LeakyReLU 0.2, InstanceNorm without affine); stages after conv4 follow the image size.

    (B,3,S,S) in [-1,1] -> z (B,n_points,3), {level: (B,C,S/stride,S/stride)}. ``conv0_norm`` is the norm of the
    two full-resolution convs (the authors' code: instance; ``none`` keeps each image's colour levels in the conv0
    skip) and ``conv0_padding`` their padding (the code: zeros). At 256^2 this is the authors' ``Encoder`` layer for
    layer (conv5, conv6 are ``extra``).
    """

    def __init__(self, image_size: int, n_points: int = 200, conv0_norm: str = "instance",
                 conv0_padding: str = "zeros"):
        super().__init__()
        if image_size % 16 or image_size < 64:
            raise ValueError(f"image_size={image_size} must be a multiple of 16 and at least 64")
        if conv0_norm not in NORMS:
            raise ValueError(f"model.conv0_norm={conv0_norm!r}: choose one of {sorted(NORMS)}")
        check_choice(conv0_padding, PADDINGS, "conv0_padding")
        self.n_points = n_points
        self.conv0 = nn.Sequential(conv3(3, 64, norm=conv0_norm, padding=conv0_padding),
                                   conv3(64, 64, norm=conv0_norm, padding=conv0_padding))
        self.conv1 = down(64, 64, norm="none")
        self.conv2 = down(64, 128)
        self.conv3 = down(128, 256)
        self.conv4 = down(256, 256)
        # Extra stride-2 stages towards 4x4 (conv5, conv6 at 256^2); the last has no norm/activation. Sizes whose
        # S/16 is not a power of two end between 4 and 8 and are average-pooled to 4x4 before the fc.
        n_extra = (image_size // 64).bit_length() - 1
        self.extra = nn.Sequential(*[down(256, 256, norm="none" if i == n_extra - 1 else "instance",
                                          activation=i != n_extra - 1) for i in range(n_extra)])
        self.fc = nn.Linear(256 * 4 * 4, n_points * 3)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        c0 = self.conv0(x)
        c2 = self.conv2(self.conv1(c0))
        c3 = self.conv3(c2)
        c4 = self.conv4(c3)
        top = self.extra(c4)
        if top.shape[-1] != 4:
            top = F.adaptive_avg_pool2d(top, 4)
        z = self.fc(top.flatten(1)).view(-1, self.n_points, 3)
        return z, {"conv0": c0, "conv2": c2, "conv3": c3, "conv4": c4}
