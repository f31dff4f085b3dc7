"""The paper's network: encoder -> latent transform -> depth decoder -> depth-warped skips -> pixel decoder."""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn as nn

from nvs.core.choices import check_choice, check_count
from nvs.core.types import Batch, Extras, Outputs, to_image_range, to_model_range
from nvs.models.blocks import init_weights
from nvs.models.encoder import Encoder
from nvs.models.latent import ROTATIONS, transform_latent
from nvs.models.pixel_decoder import PixelDecoder
from nvs.models.warp import check_warp, warp

# An encoded source image: latent points z_s (B,n,3) and the encoder's skip features {level: (B,C,h,w)}.
Encoded = tuple[torch.Tensor, dict[str, torch.Tensor]]


def decode_depths(encoder: nn.Module, depth_source: nn.Module, z_s: torch.Tensor, z_t: torch.Tensor, batch: Batch,
                  needs: frozenset[str]) -> Outputs:
    """The target depth (psi_d(z~_t) for the paper's source) plus the depth extras the losses asked for.

    -> {"depth": (B,1,S,S), and Extras.DEPTH_FROM_TGT / Extras.DEPTH_SRC when in ``needs``}. The target image is
    encoded only if the depth source asks for its latent (depth consistency with a latent-based source).
    """
    return depth_source(z_t, z_s, lambda: encoder(to_model_range(batch["tgt"]))[0], batch, needs)


class NVSNet(nn.Module):
    """Depth-guided skip-connection network (Hou et al. 2021), at 256^2 the authors' network layer for layer.

    forward(batch, needs) -> outputs with ``rgb`` (B,3,S,S) in [0,1], ``rgb_scales`` (coarse -> fine, [-1,1]),
    ``depth`` (B,1,S,S) and whichever ``Extras`` were requested. ``forward = render(encode(src), batch, needs)``: a
    viewer encodes a source image once and renders it at many poses.

    The fidelity switches (``conf/fidelity``, docs/fidelity.md) default to the authors' code: ``decoder_norm``,
    ``conv0_norm``, ``conv0_padding``, ``latent_rotation`` (``nvs.models.latent``), ``side_upsample`` (pixel
    decoder), ``warp_align`` / ``warp_padding`` (the source warp the warp loss reads; ``nvs.models.warp``) and
    ``init`` (``nvs.models.blocks.init_weights``). The skips and the depth source carry their own.
    """

    n_scales = 4  # len(rgb_scales): the pixel decoder's S/8, S/4, S/2 and S predictions

    def __init__(self, image_size: int, skips: nn.Module, depth: Callable[..., nn.Module], n_points: int = 200,
                 decoder_norm: str = "instance", conv0_norm: str = "instance", conv0_padding: str = "zeros",
                 latent_rotation: str = "code", side_upsample: str = "nearest", warp_align: str = "code",
                 warp_padding: str = "border", init: str = "normal"):
        super().__init__()
        check_count(n_points, "n_points")
        check_warp(warp_align, warp_padding)
        check_choice(latent_rotation, ROTATIONS, "latent_rotation")
        self.image_size = image_size
        self.latent_rotation = latent_rotation
        self.warp_align, self.warp_padding = warp_align, warp_padding
        self.encoder = Encoder(image_size, n_points, conv0_norm=conv0_norm, conv0_padding=conv0_padding)
        self.depth = depth(image_size=image_size, n_points=n_points)
        self.skips = skips
        self.pixel_decoder = PixelDecoder(image_size, n_points, skips.levels, norm=decoder_norm,
                                          side_upsample=side_upsample)
        # The depth source's own decoder only: a plane's zero-initialised last layer keeps its start.
        for part in (self.encoder, self.pixel_decoder, getattr(self.depth, "decoder", None)):
            if part is not None:
                init_weights(part, init)

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        return self.render(self.encode(batch["src"]), batch, needs)

    def encode(self, src: torch.Tensor) -> Encoded:
        """The pose-independent part, run once per source image: src (B,3,S,S) in [0,1] -> (z_s, skip features)."""
        return self.encoder(to_model_range(src))

    def render(self, encoded: Encoded, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        """Everything that depends on the pose (``batch``'s K, T_tgt_src, pivot; src/tgt only for the extras)."""
        z_s, _ = encoded
        K, T = batch["K"], batch["T_tgt_src"]
        z_t = self._target_latent(z_s, batch)
        out: Outputs = decode_depths(self.encoder, self.depth, z_s, z_t, batch, needs)
        depth = out["depth"]
        rgb_scales = self.decode_pixels(encoded, z_t, depth, batch)
        out["rgb_scales"] = rgb_scales
        out["rgb"] = to_image_range(rgb_scales[-1])
        if Extras.WARPED_SRC in needs:
            src = batch["src"]
            out[Extras.WARPED_SRC], out["warp_valid"] = warp(src, depth.to(src.dtype), K, T, self.warp_align,
                                                             self.warp_padding)
        return out

    def _target_latent(self, z_s: torch.Tensor, batch: Batch) -> torch.Tensor:
        return transform_latent(z_s, batch["T_tgt_src"], batch["pivot"], self.latent_rotation)

    def predict_depth(self, encoded: Encoded, batch: Batch) -> tuple[torch.Tensor, torch.Tensor]:
        """The pose step up to the target depth, no pixel decoder: -> z~_t (B,n,3), depth (B,1,S,S)."""
        z_s, _ = encoded
        z_t = self._target_latent(z_s, batch)
        return z_t, decode_depths(self.encoder, self.depth, z_s, z_t, batch, frozenset())["depth"]

    def decode_pixels(self, encoded: Encoded, z_t: torch.Tensor, depth: torch.Tensor,
                      batch: Batch) -> list[torch.Tensor]:
        """The skips warped by ``depth`` and the pixel decoder: -> rgb_scales (coarse -> fine, [-1,1])."""
        return self.pixel_decoder(z_t, self.skips(encoded[1], depth, batch["K"], batch["T_tgt_src"]))
