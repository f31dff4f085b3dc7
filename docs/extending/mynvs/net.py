"""WarpRefine: predict the target depth, warp the source by it, refine the warped image. 7,604 parameters.

A network of nvs's forward contract (nvs/core/types.py): ``forward(batch, needs) -> outputs`` with
    rgb        (B,3,H,W) in [0,1]      the prediction
    rgb_scales [(B,3,H,W) in [-1,1]]   predictions coarse -> fine (one scale here: recon_final fits)
    depth      (B,1,H,W) > 0           the predicted target depth (depth metrics, the viewer, videos, point clouds)
It reads only the batch keys of the data contract (src, K, T_tgt_src); ``needs`` names extras that some nvs losses
request (nvs.core.types.Extras), which this network does not produce, so use losses that read rgb/rgb_scales/depth.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from nvs.core.geometry import inverse_warp


def _block(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=1), nn.GroupNorm(4, c_out), nn.ReLU(inplace=True))


class WarpRefine(nn.Module):
    """Args: image_size (the data's size; any), channels: width of the two small conv stacks,
    depth_range: (near, far) of the predicted depth in the data's pose units."""

    n_scales = 1  # len(rgb_scales): checked against the recon loss's scale weights when the module is built

    def __init__(self, image_size: int, channels: int = 16, depth_range: tuple[float, float] = (1.0, 3.0)):
        super().__init__()
        self.image_size = image_size
        self.near, self.far = float(depth_range[0]), float(depth_range[1])
        # Depth from the source image and the pose (12 numbers of T_tgt_src broadcast as planes).
        self.depth_net = nn.Sequential(_block(3 + 12, channels), _block(channels, channels), nn.Conv2d(channels, 1, 1))
        self.refine = nn.Sequential(_block(3 + 1, channels), _block(channels, channels), nn.Conv2d(channels, 3, 1))

    def forward(self, batch: dict, needs: frozenset[str] = frozenset()) -> dict:
        src, K, T = batch["src"], batch["K"], batch["T_tgt_src"]
        B, _, H, W = src.shape
        pose = T[:, :3, :].reshape(B, 12, 1, 1).expand(B, 12, H, W).to(src.dtype)
        depth = self.near + (self.far - self.near) * torch.sigmoid(self.depth_net(torch.cat([src, pose], 1)))
        warped, valid = inverse_warp(src, depth.to(src.dtype), K, T)
        x = torch.cat([warped * 2 - 1, valid.to(warped.dtype).view(B, 1, H, W)], 1)
        rgb_model = torch.tanh(self.refine(x) + (warped * 2 - 1))  # residual on the warped source, in [-1,1]
        return {"rgb": (rgb_model + 1) / 2, "rgb_scales": [rgb_model], "depth": depth}
