"""Pictures of predictions for logs and videos: depth as grey (near = bright) and grids of image columns."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def depth_to_grey(depth: torch.Tensor, span: tuple[float, float] | None = None) -> torch.Tensor:
    """(B,1,H,W) depth -> (B,3,H,W) in [0,1], near = bright.

    Stretched over each image's own range, or over ``span`` = (near, far) for all (a video keeps one scale).
    """
    d = depth.float()
    if span is None:
        lo = d.amin(dim=(1, 2, 3), keepdim=True)
        hi = d.amax(dim=(1, 2, 3), keepdim=True)
    else:
        lo, hi = (torch.tensor(v, dtype=d.dtype, device=d.device) for v in span)
    width = hi - lo
    grey = torch.where(width > 0, (hi - d) / width.clamp_min(1e-12), torch.full_like(d, 0.5))
    return grey.clamp(0, 1).expand(-1, 3, -1, -1)


def image_grid(columns: list[torch.Tensor], scale: int = 1, pad: int = 2) -> torch.Tensor:
    """Columns of (B,C,H,W) images (C=3 in [0,1], or C=1 depth, drawn grey) -> (3, B*(H+pad)+pad, N*(W+pad)+pad).

    Row b holds sample b of every column; dark grey padding between tiles (the renders are on white); tiles upscaled ``scale``x (nearest).
    """
    tiles = [depth_to_grey(c) if c.shape[1] == 1 else c.float().clamp(0, 1) for c in columns]
    if scale > 1:
        tiles = [F.interpolate(t, scale_factor=scale, mode="nearest") for t in tiles]
    B, _, H, W = tiles[0].shape
    grid = torch.full((3, B * (H + pad) + pad, len(tiles) * (W + pad) + pad), 0.25)
    for j, t in enumerate(tiles):
        for b in range(B):
            y, x = pad + b * (H + pad), pad + j * (W + pad)
            grid[:, y:y + H, x:x + W] = t[b].cpu()
    return grid


def to_uint8_hwc(img: torch.Tensor) -> np.ndarray:
    """(3,H,W) float in [0,1] -> (H,W,3) uint8."""
    return (img.float().clamp(0, 1) * 255.0).round().to(torch.uint8).permute(1, 2, 0).contiguous().cpu().numpy()
