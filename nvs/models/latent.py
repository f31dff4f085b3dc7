"""Latent transform: z~_t = [R|t] . z_s (homogeneous points), expressed about the dataset's pivot."""

from __future__ import annotations

import torch

from nvs.core.choices import check_choice
from nvs.core.geometry import about_pivot

ROTATIONS = ("code", "exact")


def transform_latent(z: torch.Tensor, T_tgt_src: torch.Tensor, pivot: torch.Tensor,
                     rotation: str = "exact") -> torch.Tensor:
    """z (B,n,3), T_tgt_src (B,4,4), pivot (B,3) -> (B,n,3).

    The latent lives in coordinates centred on the pivot: the object centre for objects (so only the rotation
    acts, as in the paper's code) and the camera centre (pivot 0) for scenes (rotation and translation act).
    ``rotation``: ``exact`` applies R to each point (z R^T for row vectors); ``code`` multiplies the row vectors by
    R, as the authors' ``transform_code`` does (``z.bmm(R)``), which rotates each point by R^T instead of R.
    """
    check_choice(rotation, ROTATIONS, "latent_rotation")
    T = about_pivot(T_tgt_src.to(z.dtype), pivot.to(z.dtype))
    R = T[:, :3, :3]
    return z @ (R if rotation == "code" else R.transpose(1, 2)) + T[:, None, :3, 3]
