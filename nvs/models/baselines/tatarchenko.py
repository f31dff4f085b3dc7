"""Pixel-generation baseline after Tatarchenko et al. (2016): image and pose branches merged, up-convolutions to RGB."""

from __future__ import annotations

import torch
import torch.nn as nn

from nvs.core.types import Batch, Outputs, to_image_range, to_model_range
from nvs.models.baselines.common import POSE_DIM, BaselineOutputs, halvings, pose_code
from nvs.models.blocks import Conv2d, act, down, up_transposed


class Tatarchenko(nn.Module):
    """Tatarchenko, Dosovitskiy, Brox, "Multi-view 3D Models from Single Images with a Convolutional Network",
    ECCV 2016.

    As in the paper, a convolutional encoder plus fully connected layers embed the image, a separate fully connected
    branch embeds the viewpoint, the two codes are concatenated and further fully connected layers and
    up-convolutions regress the target RGB. What differs: any image size divisible by 16 (the paper used 128^2;
    here stride-2 4x4 convolutions run down to a 4x4-7x7 map, pooled to 4x4 for the fully connected layers, so layer
    sizes are ours); the viewpoint is the relative pose [R|t] of ``T_tgt_src`` about the pivot, 12 numbers, for
    objects and scenes alike (Hou et al. fed cos/sin of the view angles; for objects [R|0] holds exactly those
    cos/sin products, and it also covers scene camera motion); RGB only, no depth map, so losses that read depth
    cannot be used; the loss is L1 (``recon`` at the final scale, optionally with ``vgg``) instead of the paper's
    squared error. LeakyReLU(0.2), no normalisation, He initialisation.

    forward(batch, needs) -> ``rgb`` (B,3,S,S) in [0,1], ``rgb_scales`` [(B,3,S,S) in [-1,1]].
    """

    provides: frozenset[str] = frozenset()
    n_scales = 1  # len(rgb_scales)

    def __init__(self, image_size: int, fc_dim: int = 1024, pose_fc_dim: int = 64):
        super().__init__()
        k = halvings(image_size)
        self.bottleneck = image_size // 2 ** k
        enc = [min(256, 32 * 2 ** i) for i in range(k)]  # S/2 ... S/2^k
        self.encoder = nn.Sequential(*[down(cin, cout, norm="none") for cin, cout in zip([3] + enc[:-1], enc)])
        self.image_fc = nn.Sequential(nn.Linear(enc[-1] * 16, fc_dim), act(), nn.Linear(fc_dim, fc_dim), act())
        self.pose_fc = nn.Sequential(nn.Linear(POSE_DIM, pose_fc_dim), act(), nn.Linear(pose_fc_dim, pose_fc_dim),
                                     act(), nn.Linear(pose_fc_dim, pose_fc_dim), act())
        self.joint_fc = nn.Sequential(nn.Linear(fc_dim + pose_fc_dim, fc_dim), act(), nn.Linear(fc_dim, fc_dim), act(),
                                      nn.Linear(fc_dim, enc[-1] * 16), act())
        dec = enc[-2::-1] + [32]  # S/2^(k-1) ... S
        self.decoder = nn.Sequential(*[up_transposed(cin, cout, norm="none")
                                       for cin, cout in zip([enc[-1]] + dec[:-1], dec)])
        self.out = Conv2d(dec[-1], 3, 3, padding=1, padding_mode="reflect")
        self.channels = enc[-1]
        # Bottlenecks other than 4x4 (sizes that are no power of two) are pooled to 4x4 and resized back.
        same = self.bottleneck == 4
        self.to_4x4 = nn.Identity() if same else nn.AdaptiveAvgPool2d(4)
        self.from_4x4 = nn.Identity() if same else nn.Upsample(size=(self.bottleneck,) * 2, mode="bilinear",
                                                                align_corners=False)
        # Without normalisation, PyTorch's default init shrinks the signal layer by layer until the output no longer
        # depends on the input; He init for LeakyReLU(0.2) keeps it alive.
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d, nn.Linear)):
                nn.init.kaiming_normal_(m.weight, a=0.2, nonlinearity="leaky_relu")
                nn.init.zeros_(m.bias)

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        x = self.to_4x4(self.encoder(to_model_range(batch["src"])))
        h = self.image_fc(x.flatten(1))
        p = self.pose_fc(pose_code(batch["T_tgt_src"], batch["pivot"]).to(h.dtype))
        x = self.from_4x4(self.joint_fc(torch.cat([h, p], dim=1)).view(-1, self.channels, 4, 4))
        rgb = torch.tanh(self.out(self.decoder(x)))
        return BaselineOutputs("tatarchenko", rgb=to_image_range(rgb), rgb_scales=[rgb])
