"""A loss term outside nvs: ``term(outputs, batch) -> scalar`` (unweighted; the module applies ``weight``)."""

from __future__ import annotations

import torch

from nvs.losses.terms import LossTerm


class DepthTV(LossTerm):
    """Total variation of the log of the predicted depth: piecewise-smooth depth, scale-free."""

    def forward(self, out: dict, batch: dict) -> torch.Tensor:
        d = out["depth"].float().clamp_min(1e-6).log()
        return (d[..., 1:, :] - d[..., :-1, :]).abs().mean() + (d[..., :, 1:] - d[..., :, :-1]).abs().mean()
