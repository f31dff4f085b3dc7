"""Depth parameterisations (a data-config fact): raw decoder output (B,1,H,W) -> depth > 0 (B,1,H,W)."""

from __future__ import annotations

import torch
import torch.nn as nn


def _at_least_fp32(x: torch.Tensor) -> torch.Tensor:
    # A bf16 depth of 2 is only good to 0.008, which moves warped pixels; float64 stays float64.
    return x.to(torch.promote_types(x.dtype, torch.float32))


class BoundedDepth(nn.Module):
    """depth = tanh(x) * (max-min)/2 + (max+min)/2 in (min, max); objects use (1, 3), i.e. tanh(x) + 2."""

    def __init__(self, min_depth: float = 1.0, max_depth: float = 3.0):
        super().__init__()
        if not 0 < min_depth < max_depth:
            raise ValueError(f"need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
        self.scale, self.bias = (max_depth - min_depth) / 2, (max_depth + min_depth) / 2
        self.min_depth, self.max_depth = min_depth, max_depth

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.tanh(_at_least_fp32(x)) * self.scale + self.bias


class DisparityDepth(nn.Module):
    """depth = 1 / (a * sigmoid(x) + b), the paper's scenes parameterisation with a=10, b=0.01: depth in (1/(a+b), 1/b)."""

    def __init__(self, max_disparity: float = 10.0, min_disparity: float = 0.01):
        super().__init__()
        if min_disparity <= 0 or max_disparity <= 0:
            raise ValueError("disparities must be positive")
        self.a, self.b = max_disparity, min_disparity
        self.min_depth, self.max_depth = 1.0 / (max_disparity + min_disparity), 1.0 / min_disparity

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 1.0 / (self.a * torch.sigmoid(_at_least_fp32(x)) + self.b)
