"""A synthesised view's predicted depth as a coloured point cloud (for nvs.export_ply and the viewer's button)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from nvs.core.errors import UserError
from nvs.report.pointcloud import depth_to_points
from nvs.viewer.session import ViewSession


def view_points(session: ViewSession, key: str, values: dict[str, float],
                max_depth: float | None = None) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """-> xyz (N,3) float32, colours (N,3) uint8 and PLY header comments for source ``key`` at control ``values``.

    Points are in the synthesised view's camera (``nvs.report.pointcloud``'s convention), coloured by the view.
    """
    view = session.view(key, values)
    if view.depth_values is None:
        raise UserError("this model predicts no depth (a baseline without a depth decoder): no point cloud to export")
    xyz, rgb = depth_to_points(view.depth_values, session.K[0].numpy(), view.rgb, max_depth)
    pose = ", ".join(f"{k}={v:g}" for k, v in values.items())
    comments = (f"nvs predicted depth of source {session.source(key).label} at {pose}",
                "points in the view's camera: OpenCV x right, y down, z forward; pose units")
    return xyz, rgb, comments


def file_stem(label: str, values: dict[str, float] | None = None) -> str:
    """A safe file name stem from a source label (and pose values)."""
    parts = [Path(label).stem] + [f"{v:g}" for v in (values or {}).values()]
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", "_".join(parts))
