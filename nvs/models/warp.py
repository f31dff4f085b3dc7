"""The feature/image warp as the network uses it: exact (``nvs.core.geometry.inverse_warp``) or as the authors' code does.

Two independent switches, both defaulting to the authors' code:
    align:   ``code``  - pixel coordinates normalised by (W-1) (align_corners=True's convention) but sampled with
                         ``grid_sample``'s align_corners=False, so every sample lands at u*W/(W-1) - 0.5: even the
                         identity pose moves the features (by up to half a pixel at the borders);
             ``exact`` - normalised and sampled with the same convention (an identity warp is the identity).
    padding: ``border`` - the code's: source depth clamped at 1e-3 (points behind the camera project far away),
                         samples outside the image take the nearest border value, nothing is masked;
             ``zeros``  - exact: points behind the source camera or outside the image are 0 (masked).
Both return the geometric validity mask (B,1,H,W) (in front and inside, exact) for the losses that use it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from nvs.core.choices import check_choice
from nvs.core.geometry import BORDER_TOLERANCE, MIN_DEPTH, inverse_warp, invert_pose
from nvs.models.blocks import is_channels_last

ALIGNS = ("code", "exact")
WARP_PADDINGS = ("border", "zeros")
# The authors' projection clamps the source depth at this value instead of masking points behind the camera.
CODE_MIN_DEPTH = 1e-3


def check_warp(align: str, padding: str) -> None:
    check_choice(align, ALIGNS, "warp_align")
    check_choice(padding, WARP_PADDINGS, "warp_padding")


def _project(depth_tgt: torch.Tensor, K: torch.Tensor, T_tgt_src: torch.Tensor):
    """Source-camera x, y, z of every target pixel, in the order the authors' projection computes them:
    K^-1 [u v 1]^T * D, then (K R) p + K t with [R|t] = T_src_tgt. -> three (B,H,W) float32-at-least tensors."""
    B, _, H, W = depth_tgt.shape
    dtype = torch.promote_types(torch.promote_types(depth_tgt.dtype, K.dtype), torch.float32)
    d = depth_tgt[:, 0].to(dtype)
    d = torch.where(torch.isfinite(d), d, torch.zeros_like(d))
    K = K.to(dtype)
    v, u = torch.meshgrid(torch.arange(H, dtype=dtype, device=d.device), torch.arange(W, dtype=dtype,
                                                                                       device=d.device), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)]).reshape(1, 3, -1).expand(B, 3, H * W)
    cam = torch.linalg.inv(K).bmm(pix).reshape(B, 3, H, W) * d[:, None]
    proj = K.bmm(invert_pose(T_tgt_src.to(dtype))[:, :3, :])  # (B,3,4): source pixels from target-camera points
    p = proj[:, :, :3].bmm(cam.reshape(B, 3, -1)) + proj[:, :, 3:]
    return p[:, 0].reshape(B, H, W), p[:, 1].reshape(B, H, W), p[:, 2].reshape(B, H, W), d


def warp(src: torch.Tensor, depth_tgt: torch.Tensor, K: torch.Tensor, T_tgt_src: torch.Tensor,
         align: str = "code", padding: str = "border") -> tuple[torch.Tensor, torch.Tensor]:
    """src (B,C,H,W), depth_tgt (B,1,H,W), K (B,3,3), T_tgt_src (B,4,4) -> warped (B,C,H,W), valid (B,1,H,W)."""
    if align == "exact" and padding == "zeros":
        return inverse_warp(src, depth_tgt, K, T_tgt_src)
    H, W = src.shape[-2:]
    with torch.autocast(device_type=src.device.type, enabled=False):
        X, Y, z, d = _project(depth_tgt, K, T_tgt_src)  # X = z * u, Y = z * v (pixels)
        in_front = (d > 0) & (z > MIN_DEPTH) & torch.isfinite(z)
        z_div = z.clamp(min=CODE_MIN_DEPTH) if padding == "border" else torch.where(in_front, z, torch.ones_like(z))
        u, v = X / z_div, Y / z_div
        tol = BORDER_TOLERANCE
        valid = in_front & (u >= -tol) & (u <= W - 1 + tol) & (v >= -tol) & (v <= H - 1 + tol)
        grid = torch.stack([2 * u / (W - 1) - 1, 2 * v / (H - 1) - 1], dim=-1)
        if padding == "zeros":
            grid = torch.where(valid[..., None], grid, torch.full_like(grid, -2.0))
        dtype = torch.promote_types(src.dtype, torch.float32)
        out = F.grid_sample(src.to(dtype), grid.to(dtype), mode="bilinear", padding_mode=padding,
                            align_corners=align == "exact")
    # grid_sample answers in NCHW: back to the source's layout (one copy, with the cast where there is one), so a
    # channels_last network's skip concatenations and convolutions do not convert whole tensors.
    layout = torch.channels_last if is_channels_last(src) else torch.contiguous_format
    return out.to(src.dtype, memory_format=layout), valid[:, None].to(src.dtype)
