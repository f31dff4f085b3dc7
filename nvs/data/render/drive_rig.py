"""The drive camera rig: intrinsics per camera option, the centre line resampled every metre, camera poses
riding 1.65 m above the right lane, and every pixel's viewing ray."""

from __future__ import annotations

import numpy as np

# fx = fy at 256^2 (principal point at the centre), per camera option.
CAMERAS = {"kitti": 718.9, "wide": 160.0}
CAMERA_HEIGHT = 1.65
STEP = 1.0
SMOOTH = 4  # m: half-window of the moving average applied to the centre line
UP = np.array([0.0, 1.0, 0.0])  # every scene is returned y up, in metres


def camera_K(camera: str) -> np.ndarray:
    """K (3,3) at 256^2 of a camera option."""
    if camera not in CAMERAS:
        raise ValueError(f"unknown camera {camera!r}; known: {', '.join(CAMERAS)}")
    f = CAMERAS[camera]
    return np.array([[f, 0.0, 128.0], [0.0, f, 128.0], [0.0, 0.0, 1.0]])


def resample(pts: np.ndarray, wid: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every `step` metres of arc length, then a moving average over +-SMOOTH metres."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    t = np.arange(0.0, s[-1], step)
    p = np.stack([np.interp(t, s, pts[:, i]) for i in range(3)], axis=1)
    w = np.interp(t, s, wid)
    k = int(round(SMOOTH / step))
    kernel = np.ones(2 * k + 1) / (2 * k + 1)
    padded = np.pad(p, ((k, k), (0, 0)), mode="edge")
    p = np.stack([np.convolve(padded[:, i], kernel, mode="valid") for i in range(3)], axis=1)
    return p, w


def camera_poses(path: np.ndarray, widths: np.ndarray, start: int, frames: int) -> np.ndarray:
    """OpenCV camera-to-world (frames,4,4) along a resampled path from index `start` (1 m apart)."""
    poses = []
    for i in range(start, start + frames):
        fwd = path[min(i + 2, len(path) - 1)] - path[max(i - 2, 0)]
        z = fwd / np.linalg.norm(fwd)
        x = np.cross(z, UP)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        # Right-lane centre: a quarter of the road width right of the centre line (horizontal offset).
        right = x - np.dot(x, UP) * UP
        right /= np.linalg.norm(right)
        c = path[i] + widths[i] / 4 * right + CAMERA_HEIGHT * UP
        T = np.eye(4)
        T[:3, :3] = np.stack([x, y, z], axis=1)
        T[:3, 3] = c
        poses.append(T)
    return np.stack(poses)


def view_dirs(T_world_cam: np.ndarray, K: np.ndarray, size: int) -> np.ndarray:
    """World direction (size,size,3) of every pixel's viewing ray (unit length)."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    d = rays @ T_world_cam[:3, :3].T
    return d / np.linalg.norm(d, axis=-1, keepdims=True)
