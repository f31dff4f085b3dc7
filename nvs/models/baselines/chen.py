"""Depth-based rendering baseline after Chen et al. (2019): TAE -> target depth -> warped source image, as their code."""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn as nn

from nvs.core.choices import check_count
from nvs.core.geometry import BORDER_TOLERANCE, about_pivot, project_to_source, sample_at
from nvs.core.types import Batch, Extras, Outputs, to_model_range
from nvs.models.baselines.common import BaselineOutputs
from nvs.models.blocks import ReflectionPad2d

LATENT_ROTATIONS = ("code", "exact")


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


def transform_points(z: torch.Tensor, T_tgt_src: torch.Tensor, pivot: torch.Tensor, rotation: str) -> torch.Tensor:
    """Move latent points by the relative pose about the pivot: z (B,n,3) -> (B,n,3).

    ``code``: z R + t, Chen et al.'s ``transform_code`` (the row vectors times R, i.e. R^T applied to each point;
    for objects only R acts, as about the object centre t = 0); ``exact``: R z + t, the points moved by the pose.
    """
    T = about_pivot(T_tgt_src.to(z.dtype), pivot.to(z.dtype))
    R, t = T[:, :3, :3], T[:, None, :3, 3]
    return (z @ R if rotation == "code" else z @ R.transpose(1, 2)) + t


def n_halvings(image_size: int) -> int:
    n = image_size.bit_length() - 1
    if image_size != 2 ** n or n < 4:
        raise ValueError(f"image_size={image_size}: Chen et al.'s auto-encoder runs to 1x1 and needs a power of two "
                         ">= 16")
    return n


class ChenEncoder(nn.Module):
    """Chen et al.'s encoder: log2(S) stride-2 4x4 convs (64, 128, then 256 channels) down to 1x1, the first followed
    by LeakyReLU(0.2), the middle ones by BatchNorm + LeakyReLU(0.2), the last by nothing; then a linear layer to
    the latent points. (B,3,S,S) in [-1,1] -> (B,n_points,3).
    """

    def __init__(self, image_size: int, n_points: int = 200):
        super().__init__()
        n = n_halvings(image_size)
        chans = [64 * min(2 ** i, 4) for i in range(n)]
        layers = [nn.Conv2d(3, chans[0], 4, stride=2, padding=1), nn.LeakyReLU(0.2)]
        for i in range(1, n):
            layers.append(nn.Conv2d(chans[i - 1], chans[i], 4, stride=2, padding=1))
            if i < n - 1:
                layers += [nn.BatchNorm2d(chans[i]), nn.LeakyReLU(0.2)]
        self.convs = nn.Sequential(*layers)
        self.fc = nn.Linear(chans[-1], n_points * 3)
        self.n_points = n_points

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.convs(x).flatten(1)).view(-1, self.n_points, 3)


class ChenDecoder(nn.Module):
    """Chen et al.'s depth decoder: linear to 256 x 1 x 1 + LeakyReLU, then log2(S) x2 stages, each followed by
    BatchNorm + LeakyReLU(0.2): transposed 4x4 convs up to 4x4, bilinear x2 + reflection pad + 3x3 conv after that;
    widths 256 down to 128, 64, 32 over the last three stages; a 3x3 conv (zero padding) to one channel.
    (B,n,3) -> raw (B,1,S,S).
    """

    N_TRANSPOSED = 2  # their 8 stages at 256^2: 2 transposed, 6 bilinear

    def __init__(self, image_size: int, n_points: int = 200):
        super().__init__()
        n = n_halvings(image_size)
        widths = [int(64 * min(2.0 ** (n - k - 1), 4)) for k in range(1, n + 1)]
        self.fc = nn.Sequential(nn.Linear(n_points * 3, 256), nn.LeakyReLU(0.2))
        layers, cin = [], 256
        for k, cout in enumerate(widths):
            if k < self.N_TRANSPOSED:
                layers.append(nn.ConvTranspose2d(cin, cout, 4, stride=2, padding=1))
            else:
                layers += [nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False), ReflectionPad2d(1),
                           nn.Conv2d(cin, cout, 3)]
            layers += [nn.BatchNorm2d(cout), nn.LeakyReLU(0.2)]
            cin = cout
        self.ups = nn.Sequential(*layers, nn.Conv2d(cin, 1, 3, padding=1))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.ups(self.fc(z.flatten(1))[:, :, None, None])


def init_normal(module: nn.Module, std: float = 0.02) -> None:
    """Their ``init_weights('normal')``: conv/linear weights N(0, std), biases 0; BatchNorm weights N(1, std), biases 0."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d, nn.Linear)):
            nn.init.normal_(m.weight, 0.0, std)
            nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.normal_(m.weight, 1.0, std)
            nn.init.zeros_(m.bias)


class Chen(nn.Module):
    """Chen, Song, Hilliges, "Monocular Neural Image Based Rendering with Continuous View Control", ICCV 2019, as
    their code (``continuous_view_synthesis/models``) builds it.

    A transforming auto-encoder maps the source image to latent points, moves them by the relative pose and decodes
    the target view's depth; the prediction is the source image warped by that depth, with no pixel decoder. Their
    encoder and decoder (BatchNorm, LeakyReLU(0.2), to and from 1x1), their N(0, 0.02) initialisation, their latent
    rotation z R (``latent_rotation: code``; ``exact`` moves the points by R), the depth head of the data config
    (objects tanh + 2, scenes 1 / (10 sigmoid + 0.01): theirs). What differs (docs/fidelity_baselines.md): image size
    a power of two (theirs 256), fewer stages below it; the warp is exact at pixel centres with border replication
    (theirs on the PyTorch 1.1 they used), points behind the source camera black (theirs clamp the depth to 1e-3).

    forward(batch, needs) -> ``rgb`` (B,3,S,S) in [0,1], ``rgb_scales`` [(B,3,S,S) in [-1,1]], ``depth`` (B,1,S,S),
    and the requested ``Extras`` (``depth_from_tgt``, ``depth_src``, ``warped_src`` = ``rgb`` with ``warp_valid``).
    """

    provides = frozenset({Extras.DEPTH_FROM_TGT, Extras.DEPTH_SRC, Extras.WARPED_SRC})
    n_scales = 1  # len(rgb_scales)

    def __init__(self, image_size: int, head: nn.Module, n_points: int = 200, latent_rotation: str = "code",
                 depth: Callable[..., nn.Module] | None = None):
        super().__init__()
        check_count(n_points, "n_points")
        if latent_rotation not in LATENT_ROTATIONS:
            raise ValueError(f"latent_rotation={latent_rotation!r}: expected one of {', '.join(LATENT_ROTATIONS)}")
        self.image_size = image_size
        self.latent_rotation = latent_rotation
        self.encoder = ChenEncoder(image_size, n_points)
        # Their depth decoder, unless a ``model/depth`` source (plane, oracle, ...) replaces it.
        self.decoder = ChenDecoder(image_size, n_points) if depth is None else None
        self.head = head
        init_normal(self)
        self.depth = depth(image_size=image_size, n_points=n_points) if depth is not None else None
        self._depths = self._own_depths if depth is None else self._source_depths  # chosen once

    def _source_depths(self, z_s: torch.Tensor, z_t: torch.Tensor, batch: Batch, needs: frozenset[str]) -> Outputs:
        return self.depth(z_t, z_s, lambda: self.encoder(to_model_range(batch["tgt"])), batch, needs)

    def _own_depths(self, z_s: torch.Tensor, z_t: torch.Tensor, batch: Batch, needs: frozenset[str]) -> Outputs:
        encode_target = lambda: self.encoder(to_model_range(batch["tgt"]))  # noqa: E731
        # One decoder call per latent (each normalised by its own batch statistics), as a loss asks for it.
        out = {"depth": self.head(self.decoder(z_t))}
        if Extras.DEPTH_SRC in needs:
            out[Extras.DEPTH_SRC] = self.head(self.decoder(z_s))
        if Extras.DEPTH_FROM_TGT in needs:
            out[Extras.DEPTH_FROM_TGT] = self.head(self.decoder(encode_target()))
        return out

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        src, K, T = batch["src"], batch["K"], batch["T_tgt_src"]
        z_s = self.encoder(to_model_range(src))
        z_t = transform_points(z_s, T, batch["pivot"], self.latent_rotation)
        depths = self._depths(z_s, z_t, batch, needs)
        rgb, valid = warp_border(src, depths["depth"].to(src.dtype), K, T)
        out = BaselineOutputs("chen", rgb=rgb, rgb_scales=[to_model_range(rgb)], **depths)
        if Extras.WARPED_SRC in needs:
            out[Extras.WARPED_SRC], out["warp_valid"] = rgb, valid
        return out
