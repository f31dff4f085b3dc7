"""Weight initialisers that two networks of different layers share (Sun et al.'s network and its critic)."""

from __future__ import annotations

import torch.nn as nn


def xavier_convs(module: nn.Module) -> None:
    """TF-slim's default for every ``Conv2d`` inside ``module``: Xavier-uniform weights, zero biases (in place)."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.xavier_uniform_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
