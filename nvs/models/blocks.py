"""Convolution blocks shared by the encoder, the decoders and the baselines, and the weight initialisation."""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from nvs.core.choices import check_choice


def is_channels_last(x: torch.Tensor) -> bool:
    """A 4-D tensor stored channels_last (and not also contiguous, as tensors with C == 1 or H*W == 1 are)."""
    return x.dim() == 4 and x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous()


class _InstanceNormKeepingLayout(torch.autograd.Function):
    """Instance normalisation over (H, W) that keeps its input's memory format: ``torch.var_mean`` (Welford: as
    accurate as ``F.instance_norm``'s, where a sum of squares cancels), then ``(x - mean) * rstd``; the backward in
    closed form, ``rstd * (g - mean(g) - y * mean(g * y))``."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, eps: float) -> torch.Tensor:
        var, mean = torch.var_mean(x, dim=(2, 3), keepdim=True, correction=0)
        rstd = torch.rsqrt(var + eps)
        shift = -mean * rstd
        ctx.save_for_backward(x, rstd, shift)  # not y: an in-place activation overwrites it
        return torch.addcmul(shift, x, rstd)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        x, rstd, shift = ctx.saved_tensors
        y = torch.addcmul(shift, x, rstd)
        mean_g = g.mean(dim=(2, 3), keepdim=True)
        mean_gy = (g * y).mean(dim=(2, 3), keepdim=True)
        return (g - mean_g - y * mean_gy) * rstd, None


class InstanceNorm(nn.InstanceNorm2d):
    """``nn.InstanceNorm2d`` without affine or running statistics that keeps a channels_last fp32 input channels_last.

    ``F.instance_norm`` normalises a (1, B*C, H, W) view of a contiguous copy, so a channels_last network paid a copy
    into NCHW here and one back at the next convolution, forward and backward (~10% of a 64² channels_last step, 25%
    of the novel view at 256²). fp32/fp64 channels_last inputs take ``_InstanceNormKeepingLayout``; NCHW inputs and
    reduced precisions (whose statistics must stay fp32) take torch's own path, unchanged.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if (not self.affine and not self.track_running_stats and x.dtype in (torch.float32, torch.float64)
                and is_channels_last(x)):
            return _InstanceNormKeepingLayout.apply(x, self.eps)
        return super().forward(x)


def pad_values(x: torch.Tensor, pad: tuple[int, ...], mode: str) -> torch.Tensor:
    """``F.pad`` in the input's dtype. CPU autocast runs reflection and replication pads in fp32, so a bf16 network
    cast every padded tensor to fp32 and back at the next convolution, forward and backward (at 64², a third of a
    bf16 step's copied bytes). A pad only copies values: in bf16 it gives the same numbers."""
    if torch.is_autocast_enabled(x.device.type):
        with torch.autocast(x.device.type, enabled=False):
            return F.pad(x, pad, mode=mode)
    return F.pad(x, pad, mode=mode)


class Conv2d(nn.Conv2d):
    """``nn.Conv2d`` whose non-zero padding (reflect, replicate, circular) runs in the input's dtype (``pad_values``);
    the same parameters and state_dict keys."""

    def _conv_forward(self, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        if self.padding_mode == "zeros":
            return super()._conv_forward(x, weight, bias)
        return F.conv2d(pad_values(x, self._reversed_padding_repeated_twice, self.padding_mode), weight, bias,
                        self.stride, 0, self.dilation, self.groups)


class ReflectionPad2d(nn.ReflectionPad2d):
    """``nn.ReflectionPad2d`` in the input's dtype (``pad_values``)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return pad_values(x, self.padding, "reflect")


NORMS = {
    "instance": lambda c: InstanceNorm(c, affine=False),
    "batch": lambda c: nn.BatchNorm2d(c),
    "none": lambda c: nn.Identity(),
}
PADDINGS = ("zeros", "reflect")
INITS = ("normal", "default")


def act() -> nn.Module:
    return nn.LeakyReLU(0.2, inplace=True)


def down(cin: int, cout: int, norm: str = "instance", activation: bool = True) -> nn.Sequential:
    """4x4 stride-2 convolution: (B,cin,H,W) -> (B,cout,H/2,W/2)."""
    layers = [nn.Conv2d(cin, cout, 4, stride=2, padding=1), NORMS[norm](cout)]
    if activation:
        layers.append(act())
    return nn.Sequential(*layers)


def conv3(cin: int, cout: int, norm: str = "instance", activation: bool = True,
          padding: str = "reflect") -> nn.Sequential:
    """3x3 convolution, reflection (or zero) padding: (B,cin,H,W) -> (B,cout,H,W)."""
    check_choice(padding, PADDINGS, "padding")
    layers = [Conv2d(cin, cout, 3, padding=1, padding_mode=padding), NORMS[norm](cout)]
    if activation:
        layers.append(act())
    return nn.Sequential(*layers)


def up_transposed(cin: int, cout: int, norm: str) -> nn.Sequential:
    """4x4 stride-2 transposed convolution: (B,cin,h,w) -> (B,cout,2h,2w)."""
    return nn.Sequential(nn.ConvTranspose2d(cin, cout, 4, stride=2, padding=1), NORMS[norm](cout), act())


def upsample2(x: torch.Tensor) -> torch.Tensor:
    """Bilinear x2 (B,C,h,w) -> (B,C,2h,2w)."""
    return F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)


class UpStage(nn.Module):
    """One x2 decoder stage + norm + LeakyReLU(0.2): (B,cin,h,w) -> (B,cout,2h,2w).

    ``transposed``: 4x4 stride-2 transposed convolution; otherwise bilinear x2, reflection pad 1, 3x3 convolution
    (the two kinds of the authors' decoders: transposed near 1x1, bilinear from 4x4 on).
    """

    def __init__(self, cin: int, cout: int, transposed: bool, norm: str):
        super().__init__()
        self.transposed = transposed
        self.conv = (nn.ConvTranspose2d(cin, cout, 4, stride=2, padding=1) if transposed
                     else nn.Conv2d(cin, cout, 3))
        self.norm = NORMS[norm](cout)
        self.act = act()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.transposed:
            x = pad_values(upsample2(x), (1, 1, 1, 1), "reflect")
        return self.act(self.norm(self.conv(x)))


# Stages of a decoder trunk that are transposed convolutions (the rest, towards S/16, are bilinear).
N_TRANSPOSED = 2


class Trunk(nn.Module):
    """Latent (B,n*3) -> fc + LeakyReLU -> 256 x 1 x 1 -> x2 stages -> (B,256,S/16,S/16).

    The authors' decoders at 256^2: two transposed stages (1 -> 4) then two bilinear ones (4 -> 16), 256 channels,
    a norm after every stage. Smaller images drop the bilinear stages (64^2: none, 128^2: one). Sizes whose S/16 is
    not a power of two end at the largest power of two below it and are resized bilinearly.
    """

    def __init__(self, latent_dim: int, image_size: int, channels: int = 256, norm: str = "instance"):
        super().__init__()
        self.out_size = image_size // 16
        n_up = self.out_size.bit_length() - 1  # 1x1 -> the largest power of two <= S/16
        self.fc = nn.Linear(latent_dim, channels)
        self.stages = nn.ModuleList([UpStage(channels, channels, i < N_TRANSPOSED, norm) for i in range(n_up)])
        self.channels = channels

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = F.leaky_relu(self.fc(z.flatten(1)), 0.2)[:, :, None, None]
        for stage in self.stages:
            x = stage(x)
        if x.shape[-1] != self.out_size:
            x = F.interpolate(x, size=(self.out_size, self.out_size), mode="bilinear", align_corners=False)
        return x


@torch.no_grad()
def init_weights(module: nn.Module, scheme: str) -> None:
    """``normal``: conv/linear weights N(0, 0.02), biases 0, BatchNorm scale N(1, 0.02) (the authors' code);
    ``default``: leave PyTorch's initialisation."""
    check_choice(scheme, INITS, "init")
    if scheme == "default":
        return
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d, nn.Linear)):
            nn.init.normal_(m.weight, 0.0, 0.02)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.normal_(m.weight, 1.0, 0.02)
            nn.init.zeros_(m.bias)
