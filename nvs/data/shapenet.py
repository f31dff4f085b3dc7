"""Objects in the ShapeNet-renders format the paper's code reads (Chen et al. / Sun et al. layout).

Root (one per category)::

    images/{model}_{azimuth}_{elevation}.png   RGB, white background; 18 azimuths 0..340 step 20 x elevations 0,10,20
    id_train.txt                               training model ids, one per line
    id_val.txt, id_test.txt                    optional (our renders write them); val is carved from train if absent
    eval_{category}_40.txt                     test pairs 'idA idB' (A = source, B = target), ids are image stems
    depth/{stem}.npy                           optional ground-truth z-depth in metres, 0 = background

Pose convention: view (az, el) has R_v = Rotation.from_euler('xyz', [-el, az, 0], degrees=True); an object point
appears in that camera at R_v^T X + c, c = (0,0,2). The paper's relative pose [[R, c - R c], [0, 1]] with
R = R_A^T R_B maps camera-B points into camera A; with A = target and B = source it is T_tgt_src.
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from nvs.core.errors import DataError
from nvs.data.files import read_depth, read_id_lines, read_ids, read_image, read_pair_lines, read_pairs

AZIMUTHS = tuple(range(0, 360, 20))
ELEVATIONS = (0, 10, 20)


def parse_stem(stem: str) -> tuple[str, int, int]:
    """'{model}_{az}_{el}' -> (model, az, el)."""
    parts = stem.rsplit("_", 2)
    if len(parts) != 3 or not parts[1].lstrip("-").isdigit() or not parts[2].lstrip("-").isdigit():
        raise ValueError(f"view id {stem!r} is not of the form model_azimuth_elevation")
    return parts[0], int(parts[1]), int(parts[2])


def view_rotation(azimuth: float, elevation: float) -> np.ndarray:
    """R_v (3,3) float64 of a view, as the paper's code builds it."""
    return Rotation.from_euler("xyz", [-elevation, azimuth, 0.0], degrees=True).as_matrix()


def relative_pose(view_a: tuple[float, float], view_b: tuple[float, float], centre: np.ndarray) -> np.ndarray:
    """The paper's T (4,4) = [[R_A^T R_B, c - R c], [0, 1]]: maps camera-B points into camera A."""
    Ra, Rb = view_rotation(*view_a), view_rotation(*view_b)
    R = Ra.T @ Rb
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre
    return T


def azimuth_gap(a: int, b: int) -> int:
    """Smallest absolute azimuth difference in degrees, with wrap-around."""
    d = abs(a - b) % 360
    return min(d, 360 - d)


@dataclass
class ObjectsFormat:
    """One category root on disk; reads splits, views and poses."""

    root: Path
    category: str
    centre: tuple[float, float, float] = (0.0, 0.0, 2.0)

    def __post_init__(self):
        self.root = Path(self.root)
        if not self.root.is_dir():
            raise DataError(self.root, "dataset root does not exist (render it with `python -m nvs.data.render` "
                            "or point data.root at the real data)")
        self._c = np.asarray(self.centre, dtype=np.float64)

    def image_path(self, stem: str) -> Path:
        return self.root / "images" / f"{stem}.png"

    def depth_path(self, stem: str) -> Path:
        return self.root / "depth" / f"{stem}.npy"

    @property
    def has_depth(self) -> bool:
        return (self.root / "depth").is_dir()

    def split_models(self, split: str, val_fraction: float, seed: int) -> list[str]:
        """Model ids of 'train' | 'val' | 'test'. Without id_val.txt, val is a seeded slice of the train models."""
        if split == "test":
            p = self.root / "id_test.txt"
            if p.is_file():
                return read_ids(p)
            return sorted({parse_stem(a)[0] for pair in self.test_pairs() for a in pair})
        train = read_ids(self.root / "id_train.txt")
        val_file = self.root / "id_val.txt"
        if val_file.is_file():
            val = read_ids(val_file)
            overlap = set(val) & set(train)
            if overlap:
                raise DataError(val_file, f"models also in id_train.txt: {sorted(overlap)[:3]}")
        else:
            shuffled = sorted(train)
            random.Random(seed).shuffle(shuffled)
            n_val = max(1, round(len(shuffled) * val_fraction)) if len(shuffled) > 1 else 0
            val = sorted(shuffled[:n_val])
            train = [m for m in train if m not in set(val)]
        models = train if split == "train" else val
        if not models:
            raise DataError(self.root / "id_train.txt", f"the {split} split has no models")
        return models

    def test_pairs(self) -> list[tuple[str, str]]:
        return list(self._test_pair_lines())

    def _test_pair_lines(self) -> dict[tuple[str, str], int]:
        path = self.root / f"eval_{self.category}_40.txt"
        pairs = read_pair_lines(path)
        for (a, b), lineno in pairs.items():
            for stem in (a, b):
                try:
                    parse_stem(stem)
                except ValueError as err:
                    raise DataError(path, str(err), lineno) from None
        return pairs

    def references(self, split: str, val_fraction: float, seed: int) -> list[tuple[Path, int, str, list[str]]]:
        """What a split reads, by the line of the list that names it: (list file, line, what, view stems)."""
        if split == "test":
            path = self.root / f"eval_{self.category}_40.txt"
            return [(path, ln, f"pair '{a} {b}'", [a, b]) for (a, b), ln in self._test_pair_lines().items()]
        models = self.split_models(split, val_fraction, seed)
        val_file = self.root / "id_val.txt"
        path = val_file if split == "val" and val_file.is_file() else self.root / "id_train.txt"
        lines = read_id_lines(path)
        return [(path, lines[m], f"model {m!r}", self.views(m)) for m in models]

    def views(self, model: str) -> list[str]:
        return [f"{model}_{a}_{e}" for a in AZIMUTHS for e in ELEVATIONS]

    def pose(self, tgt: str, src: str) -> torch.Tensor:
        """T_tgt_src (4,4) float32 between two view stems."""
        _, az_t, el_t = parse_stem(tgt)
        _, az_s, el_s = parse_stem(src)
        return torch.from_numpy(relative_pose((az_t, el_t), (az_s, el_s), self._c)).float()

    def read(self, stem: str, size: int, with_depth: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        img = read_image(self.image_path(stem), size)
        depth = read_depth(self.depth_path(stem), size) if with_depth else None
        return img, depth


def random_partner(stem: str, max_delta: int, rng: random.Random) -> str:
    """A different view of the same model with |delta azimuth| <= max_delta (any elevation)."""
    model, az, el = parse_stem(stem)
    choices = [(a, e) for a in AZIMUTHS for e in ELEVATIONS
               if azimuth_gap(a, az) <= max_delta and (a, e) != (az, el)]
    a, e = rng.choice(choices)
    return f"{model}_{a}_{e}"


def object_pairs(models: list[str], fmt: ObjectsFormat, per_model: int, max_delta: int, seed: int):
    """A fixed, seeded list of (src, tgt) pairs, ``per_model`` for each model (validation)."""
    rng = random.Random(seed)
    pairs = []
    for m in models:
        views = fmt.views(m)
        for _ in range(per_model):
            src = rng.choice(views)
            pairs.append((src, random_partner(src, max_delta, rng)))
    return pairs
