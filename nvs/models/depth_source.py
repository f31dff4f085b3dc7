"""Where the target depth comes from (Hydra group ``model/depth``): the paper's depth decoder on the latent."""

from __future__ import annotations

import torch
import torch.nn as nn

from nvs.models.depth_decoder import DepthDecoder


class PredictedDepth(nn.Module):
    """Depth decoded from latents; several latents go through the decoder in one batch (one BatchNorm update)."""

    def __init__(self, image_size: int, n_points: int, head: nn.Module):
        super().__init__()
        self.decoder = DepthDecoder(image_size, n_points, head)

    def forward(self, latents: list[torch.Tensor]) -> list[torch.Tensor]:
        """list of (B,n,3) -> list of (B,1,S,S)."""
        if len(latents) == 1:
            return [self.decoder(latents[0])]
        return list(self.decoder(torch.cat(latents)).chunk(len(latents)))
