"""A synthesised view's predicted depth as a coloured point cloud (for nvs.export_ply and the viewer's button)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from nvs.core.errors import UserError
from nvs.report.pointcloud import depth_to_points
from nvs.viewer.controls import ObjectControls
from nvs.viewer.session import ViewSession


# an object render's background is white: a synthesised pixel this close to it in every channel is background
WHITE_BACKGROUND = 245


def view_points(session: ViewSession, key: str, values: dict[str, float], max_depth: float | None = None,
                keep_background: bool = False) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """-> xyz (N,3) float32, colours (N,3) uint8 and PLY header comments for source ``key`` at control ``values``.

    Points are in the synthesised view's camera (``nvs.report.pointcloud``'s convention), coloured by the view. For
    an object model the pixels it renders as the white background are left out unless ``keep_background``.
    """
    view = session.view(key, values)
    if view.depth_values is None:
        raise UserError("this model predicts no depth (a baseline without a depth decoder): no point cloud to export")
    objects = isinstance(session.controls, ObjectControls)
    background = WHITE_BACKGROUND if objects and not keep_background else None
    xyz, rgb = depth_to_points(view.depth_values, session.K[0].numpy(), view.rgb, max_depth, background)
    pose = ", ".join(f"{k}={v:g}" for k, v in values.items())
    comments = (f"nvs predicted depth of source {session.source(key).label} at {pose}",
                "points in the view's camera: OpenCV x right, y down, z forward; pose units")
    return xyz, rgb, comments


def file_stem(label: str, values: dict[str, float] | None = None) -> str:
    """A safe file name stem from a source label (and pose values)."""
    parts = [Path(label).stem] + [f"{v:g}" for v in (values or {}).values()]
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", "_".join(parts))
