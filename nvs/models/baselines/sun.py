"""Flow + pixel aggregation baseline after Sun et al. (2018), single-input setting."""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from nvs.models.baselines import POSE_DIM, RGB_BRANCHES, BaselineOutputs, check_needs, halvings, pose_code
from nvs.models.blocks import act, conv3, down, up_transposed
from nvs.models.net import to_image_range, to_model_range
from nvs.types import Batch, Outputs


class PoseUNet(nn.Module):
    """Encoder-decoder with skip connections and the pose joined at a fully connected bottleneck.

    image (B,3,S,S) in [-1,1], pose code (B,12) -> (B,out_channels,S,S) (raw; the head is linear).
    """

    def __init__(self, image_size: int, out_channels: int, fc_dim: int = 256, pose_fc_dim: int = 64,
                 max_channels: int = 192):
        super().__init__()
        k = halvings(image_size)
        self.bottleneck = image_size // 2 ** k
        chans = [32] + [min(max_channels, 64 * 2 ** i) for i in range(k)]  # at S, S/2, ..., S/2^k
        self.stem = conv3(3, chans[0], norm="none")
        self.downs = nn.ModuleList([down(chans[i], chans[i + 1]) for i in range(k)])
        self.channels = chans[-1]
        self.image_fc = nn.Sequential(nn.Linear(chans[-1] * 16, fc_dim), act())
        self.pose_fc = nn.Sequential(nn.Linear(POSE_DIM, pose_fc_dim), act(),
                                     nn.Linear(pose_fc_dim, pose_fc_dim), act())
        self.joint_fc = nn.Sequential(nn.Linear(fc_dim + pose_fc_dim, chans[-1] * 16), act())
        # Decoder stage i goes from S/2^(i+1) to S/2^i and fuses the encoder features of that resolution.
        self.ups = nn.ModuleList([up_transposed(chans[i + 1], chans[i], "instance") for i in range(k)])
        self.fuse = nn.ModuleList([conv3(2 * chans[i], chans[i]) for i in range(k)])
        self.head = nn.Conv2d(chans[0], out_channels, 3, padding=1, padding_mode="reflect")

    def forward(self, x: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
        feats = [self.stem(x)]
        for stage in self.downs:
            feats.append(stage(feats[-1]))
        h = feats[-1] if self.bottleneck == 4 else F.adaptive_avg_pool2d(feats[-1], 4)
        h = self.image_fc(h.flatten(1))
        y = self.joint_fc(torch.cat([h, self.pose_fc(pose.to(h.dtype))], dim=1)).view(-1, self.channels, 4, 4)
        if self.bottleneck != 4:
            y = F.interpolate(y, size=(self.bottleneck,) * 2, mode="bilinear", align_corners=False)
        for i in reversed(range(len(self.downs))):
            y = self.fuse[i](torch.cat([self.ups[i](y), feats[i]], dim=1))
        return self.head(y)


def identity_grid(B: int, H: int, W: int, like: torch.Tensor) -> torch.Tensor:
    """Normalised sampling grid of the pixel centres for ``grid_sample(align_corners=True)``: (B,H,W,2), (x, y)."""
    ys = torch.linspace(-1.0, 1.0, H, device=like.device, dtype=like.dtype)
    xs = torch.linspace(-1.0, 1.0, W, device=like.device, dtype=like.dtype)
    return torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1).expand(B, H, W, 2)


class Sun(nn.Module):
    """Sun, Huh, Liao, Zhang, Lim, "Multi-view to Novel View: Synthesizing Novel Views with Self-Learned Confidence",
    ECCV 2018, in its single-input setting.

    As in the paper, a flow module predicts an appearance flow (a 2-channel sampling field applied to the source
    with bilinear sampling) and a confidence map, a pixel-generation module predicts RGB and a confidence map, and
    the two predictions are blended per pixel by a softmax over the two confidences. What differs: with one input
    view there is nothing to aggregate over, so the pixel module's recurrent (ConvLSTM) aggregation is dropped; both
    modules are our encoder-decoders with skip connections and the pose joined at a fully connected bottleneck
    (``PoseUNet``), any image size divisible by 16; the pose is the relative [R|t] about the pivot, 12 numbers, as
    for the Tatarchenko baseline; the flow is an offset from the identity in normalised coordinates (zero at
    initialisation, i.e. copying the source) with border replication outside the image. Losses: L1 on the blended
    output (``recon`` at the final scale) plus L1 on each module's own prediction (``branches``). The paper's
    adversarial loss on the pixel module is not implemented (a results table should footnote this row).

    forward(batch, needs) -> ``rgb`` (B,3,S,S) in [0,1], ``rgb_scales`` [(B,3,S,S) in [-1,1]], ``rgb_branches``
    {"flow", "pixel": (B,3,S,S) in [0,1]}, ``confidence`` (B,2,S,S) softmax weights (flow, pixel).
    """

    provides = frozenset({RGB_BRANCHES})

    def __init__(self, image_size: int, fc_dim: int = 256, pose_fc_dim: int = 64, max_channels: int = 192):
        super().__init__()
        # max_channels 192 puts the two modules together at about the full model's size (10M at 64^2, 18M at 256^2).
        self.flow_net = PoseUNet(image_size, 3, fc_dim, pose_fc_dim, max_channels)  # flow (x, y) + confidence
        self.pixel_net = PoseUNet(image_size, 4, fc_dim, pose_fc_dim, max_channels)  # RGB + confidence
        # Zero flow and equal confidence at the start: the flow branch begins as a copy of the source.
        nn.init.zeros_(self.flow_net.head.weight)
        nn.init.zeros_(self.flow_net.head.bias)

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        check_needs("sun", needs, self.provides)
        src = batch["src"]
        B, _, H, W = src.shape
        x = to_model_range(src)
        pose = pose_code(batch["T_tgt_src"], batch["pivot"])
        f = self.flow_net(x, pose)
        # In bf16 the identity grid is off by up to 1/256 of the image: build it and add the flow in float32.
        grid = identity_grid(B, H, W, src.float()) + f[:, :2].float().permute(0, 2, 3, 1)
        rgb_flow = F.grid_sample(src, grid.to(src.dtype), mode="bilinear", padding_mode="border", align_corners=True)
        g = self.pixel_net(x, pose)
        rgb_pixel = to_image_range(torch.tanh(g[:, :3]))
        w = torch.softmax(torch.cat([f[:, 2:], g[:, 3:]], dim=1).float(), dim=1).to(rgb_pixel.dtype)
        rgb = w[:, :1] * rgb_flow + w[:, 1:] * rgb_pixel
        return BaselineOutputs("sun", rgb=rgb, rgb_scales=[to_model_range(rgb)], confidence=w,
                               **{RGB_BRANCHES: {"flow": rgb_flow, "pixel": rgb_pixel}})
