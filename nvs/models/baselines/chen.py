"""Depth-based rendering baseline after Chen et al. (2019): TAE -> target depth -> warped source image."""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn as nn

from nvs.geometry import BORDER_TOLERANCE, project_to_source, sample_at
from nvs.models.baselines import BaselineOutputs, check_needs
from nvs.models.encoder import Encoder
from nvs.models.latent import transform_latent
from nvs.models.net import Extras, decode_depths, to_model_range
from nvs.types import Batch, Outputs


def warp_border(src: torch.Tensor, depth_tgt: torch.Tensor, K: torch.Tensor, T_tgt_src: torch.Tensor):
    """Inverse warp whose out-of-image samples take the nearest border pixel; points behind the source camera are 0.

    src (B,C,H,W), depth_tgt (B,1,H,W), K (B,3,3), T_tgt_src (B,4,4) -> warped (B,C,H,W),
    valid (B,1,H,W) float: in front of the source camera and inside the source image (as ``inverse_warp``).
    """
    H, W = src.shape[-2:]
    uv, _, in_front = project_to_source(depth_tgt, K, T_tgt_src)
    u, v = uv[..., 0], uv[..., 1]
    tol = BORDER_TOLERANCE
    inside = (u >= -tol) & (u <= W - 1 + tol) & (v >= -tol) & (v <= H - 1 + tol)
    # Clamping also stops the gradient there: depth is not pushed by pixels that see no source content.
    uv = torch.stack([u.clamp(0, W - 1), v.clamp(0, H - 1)], dim=-1)
    warped = sample_at(src, uv, in_front)
    return warped, (in_front & inside)[:, None].to(src.dtype)


class Chen(nn.Module):
    """Chen, Song, Hilliges, "Monocular Neural Image Based Rendering with Continuous View Control", ICCV 2019.

    As in the paper, a transforming auto-encoder maps the source image to latent points, moves them by the relative
    pose and decodes the target view's depth; the prediction is the source image warped by that depth, with no pixel
    decoder. What differs: the encoder, latent transform and depth decoder are the ones of our network (Hou et al.
    built theirs on Chen's TAE, so this is the same architecture minus the pixel decoder and skips), with the depth
    parameterised by the data config's head; image size is the data's (the shared encoder needs a power of two
    >= 64); pixels whose source point falls outside the source image take the nearest border pixel (white for the
    rendered objects, edge colours for scenes) and points behind the source camera are black, our choice. Losses:
    L1 of the warped image against the target (``recon`` at the final scale) and edge-aware depth smoothness
    (``edge_smooth``), the two terms the comparison uses; the depth is output so depth metrics are reported.

    forward(batch, needs) -> ``rgb`` (B,3,S,S) in [0,1], ``rgb_scales`` [(B,3,S,S) in [-1,1]], ``depth`` (B,1,S,S),
    and the requested ``Extras`` (``depth_from_tgt``, ``depth_src``, ``warped_src`` = ``rgb`` with ``warp_valid``).
    """

    provides = frozenset({Extras.DEPTH_FROM_TGT, Extras.DEPTH_SRC, Extras.WARPED_SRC})

    def __init__(self, image_size: int, depth: Callable[..., nn.Module], n_points: int = 200):
        super().__init__()
        self.image_size = image_size
        self.encoder = Encoder(image_size, n_points)
        self.depth = depth(image_size=image_size, n_points=n_points)

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        check_needs("chen", needs, self.provides)
        src, K, T = batch["src"], batch["K"], batch["T_tgt_src"]
        z_s, _ = self.encoder(to_model_range(src))  # skip features are unused
        depths = decode_depths(self.encoder, self.depth, z_s, transform_latent(z_s, T, batch["pivot"]), batch, needs)
        rgb, valid = warp_border(src, depths["depth"].to(src.dtype), K, T)
        out = BaselineOutputs("chen", rgb=rgb, rgb_scales=[to_model_range(rgb)], **depths)
        if Extras.WARPED_SRC in needs:
            out[Extras.WARPED_SRC], out["warp_valid"] = rgb, valid
        return out
