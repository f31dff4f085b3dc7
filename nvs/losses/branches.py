"""Reconstruction of each branch of a blending model (Sun et al.: the flow module's and the pixel module's outputs)."""

from __future__ import annotations

import torch

from nvs.core.types import RGB_BRANCHES, Batch, Outputs, to_model_range
from nvs.losses.terms import LossTerm, up


class BranchReconLoss(LossTerm):
    """sum over branches b of mean |I_b - I_t| on [-1,1]; ``outputs["rgb_branches"]`` = {name: (B,3,H,W) in [0,1]}."""

    needs = frozenset({RGB_BRANCHES})

    def __init__(self, weight: float = 10.0):
        super().__init__(weight)

    def forward(self, out: Outputs, batch: Batch) -> torch.Tensor:
        tgt = to_model_range(batch["tgt"])
        branches = out[RGB_BRANCHES]
        if not branches:
            raise ValueError("the model returned no branches to supervise")
        return sum((to_model_range(up(img)) - tgt).abs().mean() for img in branches.values())
