"""Scenes in the KITTI-odometry format the paper's code reads.

Root::

    images/{id}.png          frames (square; resized to the configured size)
    poses.txt                'id rx ry rz tx ty tz' per frame: camera-to-world of the OpenCV camera,
                             R = Rotation.from_euler('xyz', [rx, ry, rz]) (radians), t in metres;
                             or 'id r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz': the same pose as KITTI
                             odometry's 3x4 [R|t] row (poses/XX.txt) with the frame id put first;
                             a trailing separator is allowed. Implausible poses are refused: |angle| > 2 pi
                             (degrees given as radians), R not a rotation, or |t| * translation_scale beyond
                             MAX_SCENE_UNITS
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

from nvs.core.errors import DataError
from nvs.data.files import parse_float, read_depth, read_image, read_lines, read_pair_lines

_SPLIT_FILES = {"train": "pairs_train.txt", "val": "pairs_val.txt", "test": "eval_kitti.txt"}


# Beyond this many scene units (metres x translation_scale) a camera position is a unit or parsing mistake:
# KITTI's longest sequence spans ~1 km, 20 units at the paper's 1/50.
MAX_SCENE_UNITS = 1e4
_FIELDS = ("rx", "ry", "rz", "tx", "ty", "tz")
_MATRIX = ("r11", "r12", "r13", "tx", "r21", "r22", "r23", "ty", "r31", "r32", "r33", "tz")


def _pose_of(parts: list[str], path: Path, lineno: int, s: str) -> tuple[np.ndarray, np.ndarray]:
    """The fields of one line (id first) -> (R (3,3), t (3,)) camera-to-world."""
    if len(parts) == 13:  # id + KITTI's 3x4 [R|t] row
        M = np.asarray([parse_float(tok, path, lineno, name) for tok, name in zip(parts[1:], _MATRIX)]).reshape(3, 4)
        R, t = M[:, :3], M[:, 3].copy()
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
            raise DataError(path, "the 3x4 pose's left 3x3 block is not a rotation (orthonormal, det +1)", lineno)
        return R, t
    if len(parts) == 12:
        raise DataError(path, "12 numbers: a KITTI odometry 3x4 [R|t] row without its frame id; put the id first "
                        "('id r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz' is read as that matrix), e.g. awk "
                        "-v SEQ=0 '{printf \"%02d_%06d %s\\n\", SEQ, NR-1, $0}' poses/00.txt", lineno)
    if len(parts) != 7:
        raise DataError(path, f"expected 'id rx ry rz tx ty tz' (7 fields) or 'id' + a 3x4 [R|t] row (13), "
                        f"got {len(parts)}: {s!r}", lineno)
    vals = [parse_float(tok, path, lineno, name) for tok, name in zip(parts[1:], _FIELDS)]
    for name, v in zip(_FIELDS[:3], vals[:3]):
        if abs(v) > 2 * np.pi:
            raise DataError(path, f"{name} = {v:g} is beyond a full turn (2 pi); angles are radians", lineno)
    return Rotation.from_euler("xyz", vals[:3]).as_matrix(), np.asarray(vals[3:], dtype=np.float64)


def read_poses(path: str | Path, translation_scale: float = 1.0) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """poses.txt -> {id: (R (3,3), t (3,))} camera-to-world, float64."""
    path = Path(path)
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    lines: dict[str, int] = {}
    for lineno, s in read_lines(path):
        parts = [p for p in re.split(r"[\s,;]+", s) if p]
        fid = parts[0]
        R, t = _pose_of(parts, path, lineno, s)
        if fid in poses:
            raise DataError(path, f"duplicated frame id {fid!r} (first on line {lines[fid]})", lineno)
        units = float(np.linalg.norm(t)) * abs(translation_scale)
        if units > MAX_SCENE_UNITS:
            raise DataError(path, f"translation {t.tolist()} is implausible: {units:.3g} scene units at "
                            f"translation_scale {translation_scale:g} (more than {MAX_SCENE_UNITS:g}); "
                            "translations are metres", lineno)
        poses[fid] = (R, t)
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
        self.poses = read_poses(self.root / "poses.txt", self.translation_scale)

    @property
    def has_depth(self) -> bool:
        return (self.root / "depth").is_dir()

    def pairs(self, split: str, val_fraction: float, seed: int) -> list[tuple[str, str]]:
        """(src, tgt) pairs of 'train' | 'val' | 'test'; without pairs_val.txt, val is a seeded slice of train."""
        return [pair for _, _, pair in self._pair_lines(split, val_fraction, seed)]

    def _pair_lines(self, split: str, val_fraction: float, seed: int) -> list[tuple[Path, int, tuple[str, str]]]:
        known = set(self.poses)
        if split == "test" or (self.root / _SPLIT_FILES["val"]).is_file():
            path = self.root / _SPLIT_FILES[split]
            return [(path, ln, pair) for pair, ln in read_pair_lines(path, known).items()]
        path = self.root / _SPLIT_FILES["train"]
        train = list(read_pair_lines(path, known).items())
        order = list(range(len(train)))
        random.Random(seed).shuffle(order)
        n_val = max(1, round(len(train) * val_fraction)) if len(train) > 1 else 0
        val_idx = set(order[:n_val])
        chosen = [(path, ln, p) for i, (p, ln) in enumerate(train) if (i in val_idx) == (split == "val")]
        if not chosen:
            raise DataError(path, f"the {split} split has no pairs")
        return chosen

    def references(self, split: str, val_fraction: float, seed: int) -> list[tuple[Path, int, str, list[str]]]:
        """What a split reads, by the line of the list that names it: (list file, line, what, frame ids)."""
        return [(path, ln, f"pair '{a} {b}'", [a, b]) for path, ln, (a, b) in self._pair_lines(split, val_fraction,
                                                                                                 seed)]

    def image_path(self, fid: str) -> Path:
        return self.root / "images" / f"{fid}.png"

    def depth_path(self, fid: str) -> Path:
        return self.root / "depth" / f"{fid}.npy"

    def pose(self, tgt: str, src: str) -> torch.Tensor:
        """T_tgt_src (4,4) float32."""
        return torch.from_numpy(relative_pose(self.poses[tgt], self.poses[src], self.translation_scale)).float()

    def read(self, fid: str, size: int, with_depth: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        img = read_image(self.image_path(fid), size)
        depth = None
        if with_depth:
            depth = read_depth(self.depth_path(fid), size) * self.translation_scale
        return img, depth
