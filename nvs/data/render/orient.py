"""Turning a y-up model so that its front faces +z (the canonical model frame of nvs.data.render.assets)."""

from __future__ import annotations

import numpy as np

from nvs.data.render.scene import Part, bounds

# Rotations about y taking the named front direction to +z (y kept, det +1).
_TO_FRONT = {
    "+z": np.eye(3),
    "-z": np.diag([-1.0, 1.0, -1.0]),
    "+x": np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
    "-x": np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
}
FRONT_AXES = tuple(_TO_FRONT)


def length_axis(parts: list[Part]) -> str:
    """'x' or 'z': the longer horizontal side of the parts' bounding box (y up)."""
    lo, hi = bounds(parts)
    d = hi - lo
    return "x" if d[0] > d[2] else "z"


def facing(parts: list[Part], front: str) -> list[Part]:
    """Rotate y-up parts about y so that `front` ('+x', '-x', '+z', '-z') points along +z."""
    if front not in _TO_FRONT:
        raise ValueError(f"front must be one of {FRONT_AXES}, got {front!r}")
    R = _TO_FRONT[front]
    return [Part(p.positions @ R.T, p.faces, p.uvs, p.image, p.color) for p in parts]


def face_front(parts: list[Part], where: str, front: str | dict[str, str]) -> list[Part]:
    """Turn y-up parts so that their front faces +z. `front` is a direction ('+x', '-x', '+z', '-z') or one per
    length axis ({'x': ..., 'z': ...}, a source's default, chosen by length_axis); `where` names the model."""
    if isinstance(front, dict):
        front = front[length_axis(parts)]
    if front not in FRONT_AXES:
        raise ValueError(f"{where}: front {front!r} is not one of {FRONT_AXES}")
    return facing(parts, front)
