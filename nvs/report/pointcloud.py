"""Point clouds of predicted depth: every pixel lifted into 3-D and coloured by the synthesised view; PLY in and out.

Convention: points are in the camera of the view whose depth it is (OpenCV: x right, y down, z forward; pixel
centres at integer coordinates, as in ``nvs.core.geometry``), in the data's pose units (ShapeNet: the object at z = 2;
scenes: metres times ``translation_scale``). The PLY is binary little-endian with float32 ``x y z`` and uint8
``red green blue`` per vertex, which MeshLab, CloudCompare, Open3D and Blender read. Figure-6-style plots can be
drawn from ``depth_to_points`` directly.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.depth import depth_to_3d_v2
from plyfile import PlyData, PlyElement


def depth_to_points(depth: np.ndarray | torch.Tensor, K: np.ndarray | torch.Tensor, rgb: np.ndarray,
                    max_depth: float | None = None, background: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """depth (H,W) > 0, K (3,3) at that resolution, rgb (H,W,3) uint8 -> xyz (N,3) float32, colours (N,3) uint8.

    Pixels with non-finite or non-positive depth (no data), farther than ``max_depth`` (e.g. the sky of a drive
    scene), or with every channel at least ``background`` (an object render's white background, e.g. 245) are left
    out; N is the number of pixels kept, in row-major pixel order.
    """
    d = torch.as_tensor(np.asarray(depth, dtype=np.float32))
    if d.ndim != 2 or tuple(np.shape(rgb)) != (*d.shape, 3):
        raise ValueError(f"depth (H,W) and rgb (H,W,3) expected, got {tuple(d.shape)} and {tuple(np.shape(rgb))}")
    Kt = torch.as_tensor(np.asarray(K, dtype=np.float32)).reshape(3, 3)
    keep = torch.isfinite(d) & (d > 0)
    if max_depth is not None:
        keep &= d <= max_depth
    if background is not None:
        keep &= torch.from_numpy(np.asarray(rgb).min(axis=-1) < background)
    xyz = depth_to_3d_v2(torch.where(keep, d, torch.zeros_like(d))[None], Kt[None])[0]  # (H,W,3)
    mask = keep.numpy()
    return xyz.numpy()[mask].astype(np.float32), np.asarray(rgb, dtype=np.uint8)[mask]


def _ply(xyz: np.ndarray, rgb: np.ndarray, comments: tuple[str, ...]) -> PlyData:
    vertex = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, axis in enumerate("xyz"):
        vertex[axis] = xyz[:, i]
    for i, channel in enumerate(("red", "green", "blue")):
        vertex[channel] = rgb[:, i]
    return PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<", comments=list(comments))


def write_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray, comments: tuple[str, ...] = ()) -> Path:
    """Binary PLY of coloured points; ``comments`` go into the header (what the points are)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _ply(xyz, rgb, comments).write(str(path))
    return path


def ply_bytes(xyz: np.ndarray, rgb: np.ndarray, comments: tuple[str, ...] = ()) -> bytes:
    buf = io.BytesIO()
    _ply(xyz, rgb, comments).write(buf)
    return buf.getvalue()


def read_ply(path: str | Path | io.BytesIO) -> tuple[np.ndarray, np.ndarray]:
    """-> xyz (N,3) float32, colours (N,3) uint8."""
    v = PlyData.read(path if isinstance(path, io.BytesIO) else str(path))["vertex"]
    return (np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32),
            np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.uint8))
