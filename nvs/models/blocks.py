"""Convolution blocks shared by the encoder and decoders."""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

NORMS = {
    "instance": lambda c: nn.InstanceNorm2d(c, affine=False),
    "batch": lambda c: nn.BatchNorm2d(c),
    "none": lambda c: nn.Identity(),
}


def act() -> nn.Module:
    return nn.LeakyReLU(0.2, inplace=True)


def down(cin: int, cout: int, norm: str = "instance", activation: bool = True) -> nn.Sequential:
    """4x4 stride-2 convolution: (B,cin,H,W) -> (B,cout,H/2,W/2)."""
    layers = [nn.Conv2d(cin, cout, 4, stride=2, padding=1), NORMS[norm](cout)]
    if activation:
        layers.append(act())
    return nn.Sequential(*layers)


def conv3(cin: int, cout: int, norm: str = "instance", activation: bool = True) -> nn.Sequential:
    """3x3 convolution with reflection padding: (B,cin,H,W) -> (B,cout,H,W)."""
    layers = [nn.Conv2d(cin, cout, 3, padding=1, padding_mode="reflect"), NORMS[norm](cout)]
    if activation:
        layers.append(act())
    return nn.Sequential(*layers)


def up_transposed(cin: int, cout: int, norm: str) -> nn.Sequential:
    """4x4 stride-2 transposed convolution: (B,cin,h,w) -> (B,cout,2h,2w)."""
    return nn.Sequential(nn.ConvTranspose2d(cin, cout, 4, stride=2, padding=1), NORMS[norm](cout), act())


def upsample2(x: torch.Tensor) -> torch.Tensor:
    """Bilinear x2 (B,C,h,w) -> (B,C,2h,2w)."""
    return F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)


class Trunk(nn.Module):
    """Latent (B,n*3) -> fc -> 256 x 1 x 1 -> transposed-conv stages -> (B,256,S/16,S/16)."""

    def __init__(self, latent_dim: int, image_size: int, channels: int = 256, norm: str = "instance"):
        super().__init__()
        self.out_size = image_size // 16
        n_up = self.out_size.bit_length() - 1  # 1x1 -> the largest power of two <= S/16
        self.fc = nn.Linear(latent_dim, channels)
        # Normalising a 1x1 (or 2x2) map per instance would erase it; those stages use batch norm or none.
        stage_norm = lambda i: norm if (norm != "instance" or 2 ** (i + 1) >= 4) else "none"  # noqa: E731
        self.ups = nn.Sequential(*[up_transposed(channels, channels, stage_norm(i)) for i in range(n_up)])
        self.channels = channels

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = self.fc(z.flatten(1))[:, :, None, None]
        x = self.ups(F.leaky_relu(x, 0.2))
        if x.shape[-1] != self.out_size:  # sizes whose S/16 is not a power of two (80, 96, 144, ...)
            x = F.interpolate(x, size=(self.out_size, self.out_size), mode="bilinear", align_corners=False)
        return x
