"""Synthetic data of the one data contract (nvs.core.types): in-memory batches and tiny on-disk datasets in both formats.

The one implementation that tests, ``nvs.stress`` and ``nvs.bench`` share. Cameras are the data configs' (pinned
against ``conf/data/*.yaml`` by tests/test_synthetic.py) scaled to the batch size; poses follow
``T_tgt_src`` (source-camera points into the target camera).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from nvs.core.geometry import pose_matrix, scale_intrinsics
from nvs.core.types import Batch

# kind -> (fx = fy, cx = cy, at size, pivot): conf/data/chairs.yaml (objects) and conf/data/drive.yaml (scenes).
CAMERAS = {"objects": (480.0, 128.0, 256, (0.0, 0.0, 2.0)), "scenes": (718.9, 128.0, 256, (0.0, 0.0, 0.0))}
# kind -> default (yaw in degrees, translation added to the rotation about the pivot, constant depth):
# objects turn 20° about their centre at depth 2; scenes yaw 2° while driving 0.02 forward, depth 0.4 (20 m).
MOTIONS = {"objects": (20.0, (0.0, 0.0, 0.0), 2.0), "scenes": (2.0, (0.0, 0.0, -0.02), 0.4)}
IMAGES = ("random", "blobs")


def rotation(axis: str, degrees: float, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(3,3) rotation about a camera axis ('x', 'y' or 'z'), computed in float64."""
    return torch.from_numpy(Rotation.from_euler(axis, degrees, degrees=True).as_matrix()).to(dtype)


def about_point(R: torch.Tensor, c) -> torch.Tensor:
    """T (4,4) rotating by R (3,3) about the point c (camera coordinates): [R | c - R c]."""
    c = torch.as_tensor(c, dtype=R.dtype)
    return pose_matrix(R[None], (c - R @ c)[None])[0]


def intrinsics(focal: float, size: int, B: int = 1, centre: float | None = None,
               dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """K (B,3,3) with focal length ``focal`` px; principal point ``centre`` (default: the image centre (size-1)/2)."""
    c = (size - 1) / 2 if centre is None else centre
    return torch.tensor([[focal, 0.0, c], [0.0, focal, c], [0.0, 0.0, 1.0]], dtype=dtype).expand(B, 3, 3).clone()


def camera(kind: str, size: int) -> torch.Tensor:
    """K (3,3) of the kind's data config at ``size``^2 (the integer pixel-centre scaling of nvs.core.geometry)."""
    f, c, at, _ = CAMERAS[_kind(kind)]
    return scale_intrinsics(torch.tensor([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]]), size / at)


def blob_images(B: int, S: int, seed: int = 0) -> torch.Tensor:
    """(B,3,S,S) in [0,1]: four flat dark rectangles on white, like the rendered objects (not pixel noise, whose every
    sub-pixel shift is a full-range change)."""
    g = torch.Generator().manual_seed(seed)
    img = torch.ones(B, 3, S, S)
    for b in range(B):
        for _ in range(4):
            x0, y0 = torch.randint(0, S // 2, (2,), generator=g).tolist()
            w, h = torch.randint(S // 8, S // 2, (2,), generator=g).tolist()
            img[b, :, y0:y0 + h, x0:x0 + w] = 0.8 * torch.rand(3, 1, 1, generator=g)
    return img


def synthetic_batch(B: int = 2, S: int = 64, kind: str = "objects",
                    images: str | tuple[torch.Tensor, torch.Tensor] = "random", seed: int = 0, *,
                    focal: float | None = None, centre: float | None = None, pose: torch.Tensor | None = None,
                    pivot=None, depth: float | tuple[float, float] | None = None,
                    device: torch.device | str | None = None) -> Batch:
    """A batch of the data contract (nvs.core.types) for ``kind`` 'objects' or 'scenes'.

    images: 'random' (uniform noise: src then tgt from one generator seeded ``seed``), 'blobs' (``blob_images``
        with seeds ``seed`` and ``seed + 1``) or an explicit (src, tgt) pair of (B,3,S,S) tensors.
    focal, centre: K's focal length and principal point in px (default: the kind's data camera at S^2).
    pose: T_tgt_src (4,4) or (B,4,4) (default: ``MOTIONS[kind]`` about the kind's pivot); pivot: (3,) point the
        latent rotates about (default: the data camera's).
    depth: depth_src and depth_tgt (B,1,S,S): a constant, or (low, high) for uniform noise (depth_tgt, then
        depth_src, drawn from the images' generator after the images); default ``MOTIONS[kind]``.
    -> {src, tgt, K, T_tgt_src, pivot, depth_src, depth_tgt, id_src, id_tgt} on ``device`` (float32).
    """
    kind = _kind(kind)
    g = torch.Generator().manual_seed(seed)
    if isinstance(images, str):
        if images == "random":
            src, tgt = torch.rand(B, 3, S, S, generator=g), torch.rand(B, 3, S, S, generator=g)
        elif images == "blobs":
            src, tgt = blob_images(B, S, seed), blob_images(B, S, seed + 1)
        else:
            raise ValueError(f"images must be one of {IMAGES} or a (src, tgt) pair, got {images!r}")
    else:
        src, tgt = images
        if src.shape != (B, 3, S, S) or tgt.shape != (B, 3, S, S):
            raise ValueError(f"images must both have shape {(B, 3, S, S)}, got {tuple(src.shape)} and "
                             f"{tuple(tgt.shape)}")
    yaw, shift, default_depth = MOTIONS[kind]
    centre_point = CAMERAS[kind][3] if pivot is None else tuple(float(v) for v in pivot)
    if pose is None:
        pose = about_point(rotation("y", yaw), centre_point)
        pose[:3, 3] += torch.tensor(shift)
    K = camera(kind, S)
    if focal is not None:
        K[0, 0] = K[1, 1] = focal
    if centre is not None:
        K[0, 2] = K[1, 2] = centre
    depth = default_depth if depth is None else depth
    if isinstance(depth, (tuple, list)):
        low, high = depth
        depth_tgt = low + (high - low) * torch.rand(B, 1, S, S, generator=g)
        depth_src = low + (high - low) * torch.rand(B, 1, S, S, generator=g)
    else:
        depth_tgt = depth_src = torch.full((B, 1, S, S), float(depth))
    batch = {
        "src": src, "tgt": tgt,
        "K": K.expand(B, 3, 3).clone(),
        "T_tgt_src": (pose.expand(B, 4, 4) if pose.dim() == 2 else pose).float().clone(),
        "pivot": torch.tensor(centre_point, dtype=torch.float32).expand(B, 3).clone(),
        "depth_src": depth_src.clone(), "depth_tgt": depth_tgt.clone(),
        "id_src": [f"a{i}" for i in range(B)], "id_tgt": [f"b{i}" for i in range(B)],
    }
    if device is not None:
        batch = {k: v.to(device) if torch.is_tensor(v) else v for k, v in batch.items()}
    return batch


def _kind(kind: str) -> str:
    if kind not in CAMERAS:
        raise ValueError(f"kind must be one of {tuple(CAMERAS)}, got {kind!r}")
    return kind


# -- tiny datasets on disk ------------------------------------------------------------------------------------------
def _blob_image(rng: np.random.Generator, size: int) -> np.ndarray:
    """(size,size,3) uint8: a white image with three coloured rectangles (something to learn, white like the renders)."""
    img = np.full((size, size, 3), 255, np.uint8)
    for _ in range(3):
        x0, y0 = rng.integers(0, size // 2, 2)
        w, h = rng.integers(size // 8, size // 2, 2)
        img[y0:y0 + h, x0:x0 + w] = rng.integers(0, 200, 3)
    return img


def write_objects_root(root: Path, models=("m0", "m1", "m2", "m3"), size: int = 64, category: str = "chair",
                       depth: bool = True, seed: int = 0) -> Path:
    """A dataset in the objects (ShapeNet-renders) format: every view of ``models``, constant depth 2; the last model
    is the test set (4 pairs in ``eval_<category>_40.txt``), the others ``id_train.txt``."""
    from PIL import Image

    from nvs.data.shapenet import AZIMUTHS, ELEVATIONS

    root = Path(root)
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
    (root / "id_train.txt").write_text("\n".join(models[:-1]) + "\n")
    test = models[-1]
    pairs = [f"{test}_{a}_0 {test}_{(a + 20) % 360}_10" for a in (0, 40, 80, 120)]
    (root / f"eval_{category}_40.txt").write_text("\n".join(pairs) + "\n")
    return root


def write_scenes_root(root: Path, n_seq: int = 2, n_frames: int = 12, size: int = 64, depth: bool = True,
                      seed: int = 0) -> Path:
    """A dataset in the scenes (KITTI-odometry) format: ``n_seq`` sequences driving forward 1 unit per frame,
    constant depth 20; consecutive frames are the pairs, the last sequence the test set."""
    from PIL import Image

    root = Path(root)
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
