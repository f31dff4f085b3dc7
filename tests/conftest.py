"""Shared fixtures: tiny datasets in both on-disk formats, and the real Hydra config composed and shrunk."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from PIL import Image

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")
AZIMUTHS = range(0, 360, 20)
ELEVATIONS = (0, 10, 20)


def _blob_image(rng: np.random.Generator, size: int) -> np.ndarray:
    """A white image with a few coloured rectangles (something to learn, white background like the renders)."""
    img = np.full((size, size, 3), 255, np.uint8)
    for _ in range(3):
        x0, y0 = rng.integers(0, size // 2, 2)
        w, h = rng.integers(size // 8, size // 2, 2)
        img[y0:y0 + h, x0:x0 + w] = rng.integers(0, 200, 3)
    return img


def make_objects_root(root: Path, models=("m0", "m1", "m2", "m3"), size: int = 64, category: str = "chair",
                      depth: bool = True, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True, exist_ok=True)
    if depth:
        (root / "depth").mkdir(exist_ok=True)
    for m in models:
        for a in AZIMUTHS:
            for e in ELEVATIONS:
                stem = f"{m}_{a}_{e}"
                Image.fromarray(_blob_image(rng, size)).save(root / "images" / f"{stem}.png")
                if depth:
                    np.save(root / "depth" / f"{stem}.npy", np.full((size, size), 2.0, np.float32))
    train, test = list(models[:-1]), [models[-1]]
    (root / "id_train.txt").write_text("\n".join(train) + "\n")
    pairs = [f"{test[0]}_{a}_0 {test[0]}_{(a + 20) % 360}_10" for a in (0, 40, 80, 120)]
    (root / f"eval_{category}_40.txt").write_text("\n".join(pairs) + "\n")
    return root


def make_scenes_root(root: Path, n_seq: int = 2, n_frames: int = 12, size: int = 64, depth: bool = True,
                     seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True, exist_ok=True)
    if depth:
        (root / "depth").mkdir(exist_ok=True)
    lines, train, test = [], [], []
    for s in range(n_seq):
        for f in range(n_frames):
            fid = f"{s:02d}_{f:06d}"
            Image.fromarray(_blob_image(rng, size)).save(root / "images" / f"{fid}.png")
            if depth:
                np.save(root / "depth" / f"{fid}.npy", np.full((size, size), 20.0, np.float32))
            lines.append(f"{fid} 0 {0.01 * f:.6f} 0 0 0 {1.0 * f:.6f}")
            if f >= 1:
                (test if s == n_seq - 1 else train).append(f"{s:02d}_{f - 1:06d} {fid}")
    (root / "poses.txt").write_text("\n".join(lines) + "\n")
    (root / "pairs_train.txt").write_text("\n".join(train) + "\n")
    (root / "eval_kitti.txt").write_text("\n".join(test) + "\n")
    return root


@pytest.fixture(scope="session")
def objects_root(tmp_path_factory) -> Path:
    return make_objects_root(tmp_path_factory.mktemp("chairs_64"))


@pytest.fixture(scope="session")
def scenes_root(tmp_path_factory) -> Path:
    return make_scenes_root(tmp_path_factory.mktemp("drive_64"))


def compose_train(overrides=(), config_name: str = "train"):
    """The real train.yaml with overrides, composed outside a Hydra run (hydra.* interpolations left unresolved)."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=config_name, overrides=list(overrides), return_hydra_config=False)


def fixture_batch(B: int = 2, S: int = 64, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[120.0, 0.0, 31.625], [0.0, 120.0, 31.625], [0.0, 0.0, 1.0]])
    T = torch.eye(4)
    c = torch.tensor([0.0, 0.0, 2.0])
    from scipy.spatial.transform import Rotation

    R = torch.from_numpy(Rotation.from_euler("y", 20, degrees=True).as_matrix()).float()
    T[:3, :3] = R
    T[:3, 3] = c - R @ c
    return {
        "src": torch.rand(B, 3, S, S, generator=g),
        "tgt": torch.rand(B, 3, S, S, generator=g),
        "K": K.expand(B, 3, 3).clone(),
        "T_tgt_src": T.expand(B, 4, 4).clone(),
        "pivot": c.expand(B, 3).clone(),
        "depth_src": torch.full((B, 1, S, S), 2.0),
        "depth_tgt": torch.full((B, 1, S, S), 2.0),
        "id_src": [f"a{i}" for i in range(B)],
        "id_tgt": [f"b{i}" for i in range(B)],
    }
