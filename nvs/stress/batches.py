"""The batches the stress sections feed: plausible ones per data kind and adversarial ones, all nvs.data.synthetic's.

The stress cameras put the principal point at the image centre (S-1)/2 (the data cameras: 0.125 px right and down
at 64^2); the objects' focal length is the chairs' at 64^2, the scenes' a wide 40 px.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from nvs.core.geometry import pose_matrix
from nvs.data.synthetic import about_point, rotation, synthetic_batch

OBJECT_F, SCENE_F, CENTRE = 120.0, 40.0, (0.0, 0.0, 2.0)


def batch_of(kind: str, images, pose: torch.Tensor | None = None, focal: float | None = None,
             depth: float | None = None, seed: int = 0, B: int = 2, S: int = 64) -> dict:
    """A stress batch of ``kind`` ('objects' | 'scenes'): nvs.data.synthetic's with the stress camera."""
    if not isinstance(images, str):
        B, _, S, _ = images[0].shape
    focal = (OBJECT_F if kind == "objects" else SCENE_F) if focal is None else focal
    return synthetic_batch(B, S, kind, images, seed, focal=focal, centre=(S - 1) / 2, pose=pose, depth=depth)


def stress_batch(kind: str, B: int = 2, S: int = 64, seed: int = 0) -> dict:
    """A plausible batch of the data kind, images of flat rectangles on white ('objects': 20° about the centre at
    depth 2; 'scenes': 2° of yaw and 0.02 forward at depth 0.4)."""
    return batch_of(kind, "blobs", seed=seed, B=B, S=S)


def adversarial_batches(S: int = 64, B: int = 2, seed: int = 0) -> dict[str, Callable[[int], dict]]:
    """name -> step -> batch: constant and textureless images, extreme poses and focal lengths."""

    def rand(step, k):
        return torch.rand(B, 3, S, S, generator=torch.Generator().manual_seed(seed + 7919 * step + k))

    def pair(step):
        return rand(step, 0), rand(step, 1)

    def random_rotation(step):
        rv = Rotation.random(random_state=seed + step).as_rotvec()
        rv *= math.pi / max(np.linalg.norm(rv), 1e-9) * ((step % 4 + 1) / 4)  # angles up to 180°
        return torch.from_numpy(Rotation.from_rotvec(rv).as_matrix()).float()

    def objects(images, pose=None, focal=None):
        return batch_of("objects", images, about_point(rotation("y", 20), CENTRE) if pose is None else pose, focal,
                        depth=2.0)

    zeros, ones = torch.zeros(B, 3, S, S), torch.ones(B, 3, S, S)
    far = pose_matrix(torch.eye(3)[None], torch.tensor([[1e3, 0.0, 1e3]]))[0]
    near_singular = pose_matrix((rotation("y", 30) * 1e-6)[None], torch.tensor([[0.0, 0.0, 1.0]]))[0]
    return {
        "constant black images": lambda i: objects((zeros, zeros)),
        "constant white images": lambda i: objects((ones, ones)),
        "textureless grey source, random target": lambda i: objects((0.5 * ones, rand(i, 1))),
        "180° rotation about the object": lambda i: objects(pair(i), about_point(rotation("y", 180), CENTRE)),
        "random rotations up to 180°": lambda i: objects(pair(i), about_point(random_rotation(i), CENTRE)),
        "translation 1e3 (no valid warp)": lambda i: objects(pair(i), far),
        "near-singular pose (R scaled 1e-6)": lambda i: objects(pair(i), near_singular),
        "focal 1 px": lambda i: objects(pair(i), focal=1.0),
        "focal 1e5 px": lambda i: objects(pair(i), focal=1e5),
    }


def batch_family(family: str) -> list[tuple[str, Callable[[int], dict]]]:
    """(name, step -> batch) for 'all' adversarial kinds, the 'constant' images, or the depth-range families
    ('tiny': an object 1.5e-4 from the camera; 'huge': scene motion from 1e-3 to 1e3)."""
    adv = adversarial_batches()
    if family == "all":
        return list(adv.items())
    if family == "constant":
        return [(k, adv[k]) for k in ("constant black images", "constant white images")]
    if family == "tiny":
        def tiny(i):
            b = adv["random rotations up to 180°"](i)
            c = torch.tensor([0.0, 0.0, 1.5e-4])
            R = b["T_tgt_src"][0, :3, :3]
            b["T_tgt_src"] = about_point(R, c).expand_as(b["T_tgt_src"]).clone()
            b["pivot"] = c.expand_as(b["pivot"]).clone()
            return b
        return [("rotations up to 180° about a centre at 1.5e-4", tiny)]

    def huge(i):
        t = torch.tensor([[0.0, 0.0, -float(10 ** (i % 7 - 3))]])  # 1e-3 .. 1e3 forward motion
        return batch_of("scenes", "random", pose_matrix(rotation("y", 3 * (i % 5))[None], t)[0], depth=2.0, seed=i)
    return [("scene motion 1e-3..1e3 with yaw", huge)]
