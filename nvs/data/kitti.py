"""Scenes in the KITTI-odometry format the paper's code reads.

Root::

    images/{id}.png          frames (square; resized to the configured size)
    poses.txt                'id rx ry rz tx ty tz' per frame: camera-to-world of the OpenCV camera,
                             R = Rotation.from_euler('xyz', [rx, ry, rz]) (radians), t in metres;
                             a trailing separator is allowed
    pairs_train.txt          'idA idB' per line (A = source, B = target)
    pairs_val.txt            optional; carved from the training pairs (seeded) when absent
    eval_kitti.txt           test pairs, frames at most 7 apart
    depth/{id}.npy           optional ground-truth z-depth in metres, 0 = no data (sky)

Relative pose (the paper's code): R = R_A^T R_B, t = R_A^T (t_B - t_A) * translation_scale maps camera-B points
into camera A; with A = target, B = source it is T_tgt_src. Depth is returned in the same scaled units.
"""

from __future__ import annotations

import random
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from nvs.data.files import parse_float, read_depth, read_image, read_lines, read_pairs
from nvs.errors import DataError

_SPLIT_FILES = {"train": "pairs_train.txt", "val": "pairs_val.txt", "test": "eval_kitti.txt"}


def read_poses(path: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """poses.txt -> {id: (R (3,3), t (3,))} camera-to-world, float64."""
    path = Path(path)
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    lines: dict[str, int] = {}
    for lineno, s in read_lines(path):
        parts = [p for p in re.split(r"[\s,;]+", s) if p]
        if len(parts) != 7:
            raise DataError(path, f"expected 'id rx ry rz tx ty tz' (7 fields), got {len(parts)}: {s!r}", lineno)
        fid = parts[0]
        if fid in poses:
            raise DataError(path, f"duplicated frame id {fid!r} (first on line {lines[fid]})", lineno)
        vals = [parse_float(tok, path, lineno, name)
                for tok, name in zip(parts[1:], ("rx", "ry", "rz", "tx", "ty", "tz"))]
        R = Rotation.from_euler("xyz", vals[:3]).as_matrix()
        poses[fid] = (R, np.asarray(vals[3:], dtype=np.float64))
        lines[fid] = lineno
    if not poses:
        raise DataError(path, "no poses")
    return poses


def relative_pose(pose_a, pose_b, translation_scale: float) -> np.ndarray:
    """The paper's T (4,4): maps camera-B points into camera A, translation scaled."""
    (Ra, ta), (Rb, tb) = pose_a, pose_b
    T = np.eye(4)
    T[:3, :3] = Ra.T @ Rb
    T[:3, 3] = Ra.T @ (tb - ta) * translation_scale
    return T


@dataclass
class ScenesFormat:
    """One scenes root on disk; reads poses, pairs and frames."""

    root: Path
    translation_scale: float = 1.0 / 50.0

    def __post_init__(self):
        self.root = Path(self.root)
        if not self.root.is_dir():
            raise DataError(self.root, "dataset root does not exist (render it with `python -m nvs.data.render drive` "
                            "or point data.root at the real data)")
        self.poses = read_poses(self.root / "poses.txt")

    @property
    def has_depth(self) -> bool:
        return (self.root / "depth").is_dir()

    def pairs(self, split: str, val_fraction: float, seed: int) -> list[tuple[str, str]]:
        """(src, tgt) pairs of 'train' | 'val' | 'test'; without pairs_val.txt, val is a seeded slice of train."""
        known = set(self.poses)
        if split == "test" or (self.root / _SPLIT_FILES["val"]).is_file():
            return read_pairs(self.root / _SPLIT_FILES[split], known)
        train = read_pairs(self.root / _SPLIT_FILES["train"], known)
        order = list(range(len(train)))
        random.Random(seed).shuffle(order)
        n_val = max(1, round(len(train) * val_fraction)) if len(train) > 1 else 0
        val_idx = set(order[:n_val])
        chosen = [p for i, p in enumerate(train) if (i in val_idx) == (split == "val")]
        if not chosen:
            raise DataError(self.root / _SPLIT_FILES["train"], f"the {split} split has no pairs")
        return chosen

    def pose(self, tgt: str, src: str) -> torch.Tensor:
        """T_tgt_src (4,4) float32."""
        return torch.from_numpy(relative_pose(self.poses[tgt], self.poses[src], self.translation_scale)).float()

    def read(self, fid: str, size: int, with_depth: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        img = read_image(self.root / "images" / f"{fid}.png", size)
        depth = None
        if with_depth:
            depth = read_depth(self.root / "depth" / f"{fid}.npy", size) * self.translation_scale
        return img, depth
