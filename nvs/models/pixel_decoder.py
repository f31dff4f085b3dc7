"""Pixel decoder psi_p: transformed latent + warped skip features -> RGB at 1/8, 1/4, 1/2 and full resolution."""

from __future__ import annotations

import torch
import torch.nn as nn

from nvs.core.choices import check_choice
from nvs.core.scales import UPSAMPLES, upsample_side
from nvs.models.blocks import NORMS, Trunk, UpStage, act
from nvs.models.encoder import SKIP_CHANNELS


def _pred(cin: int, cout: int = 3, k: int = 3) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, k, padding=k // 2)


class PixelDecoder(nn.Module):
    """The authors' ``Decoder``: (B,n,3), {level: features} -> RGB (B,3,S/8), (B,3,S/4), (B,3,S/2), (B,3,S) in [-1,1].

    Stages (widths at 256^2 as the authors'): the trunk to S/16 (256), then x2 stages to S/8 (256), S/4 (128),
    S/2 (64), S (32), each with ``norm`` and LeakyReLU(0.2). Skips are concatenated before a stage: conv4 before the
    S/8 stage, conv3 before the S/4 stage, conv2 after it (with the upsampled S/8 prediction, feeding both the S/4
    prediction and the next stage), conv0 before the final 3x3 fusion at S. Side predictions (raw, before tanh)
    are upsampled (``side_upsample``: nearest as the code, or bilinear) and concatenated into the next stage. The
    final prediction is a 3x3 conv of the fused features plus a 1x1 residual path from the S features that
    bypasses conv0 (``finalup`` in the code). Missing skip levels contribute no channels (chosen at build time).
    """

    def __init__(self, image_size: int, n_points: int, skip_levels=tuple(SKIP_CHANNELS), norm: str = "instance",
                 side_upsample: str = "nearest"):
        super().__init__()
        check_choice(norm, NORMS, "decoder_norm")
        self.side_upsample = check_choice(side_upsample, UPSAMPLES, "side_upsample")
        self.skip_levels = tuple(lv for lv in SKIP_CHANNELS if lv in skip_levels)
        c = {lv: (SKIP_CHANNELS[lv] if lv in self.skip_levels else 0) for lv in SKIP_CHANNELS}
        self.trunk = Trunk(n_points * 3, image_size, norm=norm)
        self.up8 = UpStage(256 + c["conv4"], 256, False, norm)
        self.up4 = UpStage(256 + c["conv3"], 128, False, norm)
        self.up2 = UpStage(128 + 3 + c["conv2"], 64, False, norm)
        self.up1 = UpStage(64 + 3, 32, False, norm)
        self.fuse1 = nn.Sequential(_pred(32 + 3 + c["conv0"], 16), NORMS[norm](16), act())
        self.res1 = _pred(32 + 3, 16, k=1)
        self.rgb8 = _pred(256)
        self.rgb4 = _pred(128 + 3 + c["conv2"])
        self.rgb2 = _pred(64 + 3)
        self.rgb1 = _pred(16)

    def _up(self, pred: torch.Tensor) -> torch.Tensor:
        h, w = pred.shape[-2:]
        return upsample_side(pred, (2 * h, 2 * w), self.side_upsample)

    @staticmethod
    def _cat(*xs):
        xs = [x for x in xs if x is not None]
        return torch.cat(xs, dim=1) if len(xs) > 1 else xs[0]

    def forward(self, z: torch.Tensor, skips: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        g = skips.get
        x8 = self.up8(self._cat(self.trunk(z), g("conv4")))
        r8 = self.rgb8(x8)
        i4 = self._cat(self.up4(self._cat(x8, g("conv3"))), self._up(r8), g("conv2"))
        r4 = self.rgb4(i4)
        i2 = self._cat(self.up2(i4), self._up(r4))
        r2 = self.rgb2(i2)
        i1 = self._cat(self.up1(i2), self._up(r2))
        r1 = self.rgb1(self.fuse1(self._cat(i1, g("conv0"))) + self.res1(i1))
        return [torch.tanh(r) for r in (r8, r4, r2, r1)]
