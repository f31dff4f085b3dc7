"""What the baselines share: the pose code of their pose branches, the encoder depth, outputs that name a missing key."""

from __future__ import annotations

from typing import Any

import torch

from nvs.core.errors import UserError
from nvs.core.geometry import about_pivot

# Length of the pose code fed to the baselines' pose branches (see ``pose_code``).
POSE_DIM = 12


class MissingOutputError(UserError, KeyError):
    """A loss read an output the model does not produce (a KeyError, so ``in``/``get`` semantics stay dict-like)."""

    def __str__(self) -> str:
        # KeyError quotes its message; this one is read by people.
        return str(self.args[0])


class BaselineOutputs(dict):
    """Outputs dict whose missing keys raise one clear error naming the model (``get`` still returns None)."""

    def __init__(self, model: str, **items: Any):
        super().__init__(**items)
        self.model = model

    def __missing__(self, key: str):
        raise MissingOutputError(
            f"model '{self.model}' does not output '{key}', which an enabled loss reads; "
            f"drop that term from loss=[...] (this model outputs: {', '.join(sorted(self))})")


def pose_code(T_tgt_src: torch.Tensor, pivot: torch.Tensor) -> torch.Tensor:
    """Relative pose as 12 numbers: [R|t] of T_tgt_src expressed about the pivot, row-major. (B,4,4), (B,3) -> (B,12).

    About the object centre an object pose is [R|0] (R's entries are the cos/sin products of the view angles);
    for scenes (pivot 0) it is the camera motion [R|t] with the data config's translation scale.
    """
    return about_pivot(T_tgt_src.float(), pivot.float())[:, :3, :4].flatten(1)


def halvings(image_size: int) -> int:
    """Stride-2 stages from S down to the bottleneck: as many as keep the map integral and at least 4x4.

    Powers of two end at 4x4 (64 -> 4 stages, 256 -> 6); other multiples of 16 stop at the first size that is odd or
    would drop below 4 when halved (80 -> 5x5, 96 -> 6x6, 144 -> 9x9).
    """
    if image_size % 16 or image_size < 64:
        raise ValueError(f"image_size={image_size} must be a multiple of 16 and at least 64")
    k = 4
    while image_size % 2 ** (k + 1) == 0 and image_size // 2 ** (k + 1) >= 4:
        k += 1
    return k
