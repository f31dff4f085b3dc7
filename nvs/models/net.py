"""The paper's network: encoder -> latent transform -> depth decoder -> depth-warped skips -> pixel decoder."""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn as nn

from nvs.geometry import inverse_warp
from nvs.models.encoder import Encoder
from nvs.models.latent import transform_latent
from nvs.models.pixel_decoder import PixelDecoder
from nvs.types import Batch, Outputs

# An encoded source image: latent points z_s (B,n,3) and the encoder's skip features {level: (B,C,h,w)}.
Encoded = tuple[torch.Tensor, dict[str, torch.Tensor]]


class Extras:
    """Names of outputs that only some losses read; a forward computes only those requested."""

    DEPTH_FROM_TGT = "depth_from_tgt"  # psi_d(z_t), z_t encoded from the target image (depth consistency)
    DEPTH_SRC = "depth_src"  # psi_d(z_s), the source view's own depth (edge smoothness on the source)
    WARPED_SRC = "warped_src"  # source image warped by the predicted target depth (warp loss)


def to_model_range(img: torch.Tensor) -> torch.Tensor:
    return img * 2.0 - 1.0


def to_image_range(x: torch.Tensor) -> torch.Tensor:
    return (x + 1.0) * 0.5


def decode_depths(encoder: nn.Module, depth_source: nn.Module, z_s: torch.Tensor, z_t: torch.Tensor, batch: Batch,
                  needs: frozenset[str]) -> Outputs:
    """The target depth (psi_d(z~_t) for the paper's source) plus the depth extras the losses asked for.

    -> {"depth": (B,1,S,S), and Extras.DEPTH_FROM_TGT / Extras.DEPTH_SRC when in ``needs``}. The target image is
    encoded only if the depth source asks for its latent (depth consistency with a latent-based source).
    """
    return depth_source(z_t, z_s, lambda: encoder(to_model_range(batch["tgt"]))[0], batch, needs)


class NVSNet(nn.Module):
    """Depth-guided skip-connection network (Hou et al. 2021).

    forward(batch, needs) -> outputs with ``rgb`` (B,3,S,S) in [0,1], ``rgb_scales`` (coarse -> fine, [-1,1]),
    ``depth`` (B,1,S,S) and whichever ``Extras`` were requested. ``forward = render(encode(src), batch, needs)``: a
    viewer encodes a source image once and renders it at many poses.
    """

    def __init__(self, image_size: int, skips: nn.Module, depth: Callable[..., nn.Module], n_points: int = 200,
                 decoder_norm: str = "batch", conv0_norm: str = "instance"):
        super().__init__()
        self.image_size = image_size
        self.encoder = Encoder(image_size, n_points, conv0_norm=conv0_norm)
        self.depth = depth(image_size=image_size, n_points=n_points)
        self.skips = skips
        self.pixel_decoder = PixelDecoder(image_size, n_points, skips.levels, norm=decoder_norm)

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        return self.render(self.encode(batch["src"]), batch, needs)

    def encode(self, src: torch.Tensor) -> Encoded:
        """The pose-independent part, run once per source image: src (B,3,S,S) in [0,1] -> (z_s, skip features)."""
        return self.encoder(to_model_range(src))

    def render(self, encoded: Encoded, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        """Everything that depends on the pose (``batch``'s K, T_tgt_src, pivot; src/tgt only for the extras)."""
        z_s, feats = encoded
        K, T = batch["K"], batch["T_tgt_src"]
        z_t = transform_latent(z_s, T, batch["pivot"])
        out: Outputs = decode_depths(self.encoder, self.depth, z_s, z_t, batch, needs)
        depth = out["depth"]
        rgb_scales = self.pixel_decoder(z_t, self.skips(feats, depth, K, T))
        out["rgb_scales"] = rgb_scales
        out["rgb"] = to_image_range(rgb_scales[-1])
        if Extras.WARPED_SRC in needs:
            src = batch["src"]
            out[Extras.WARPED_SRC], out["warp_valid"] = inverse_warp(src, depth.to(src.dtype), K, T)
        return out
