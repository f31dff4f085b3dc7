"""Where the target depth comes from (Hydra group ``model/depth``): the paper's depth decoder on the latent, a single
fronto-parallel plane per sample predicted from the latent, or the data's ground truth (an upper bound).

Every source is called as ``source(z_t, z_s, encode_target, batch, needs) -> {"depth": (B,1,S,S), extras...}``:
the target depth of the transformed latent z_t (B,n,3) plus the depth extras the losses asked for (``needs``,
see ``nvs.core.types.Extras``). ``encode_target()`` returns the target image's own latent and is called only when
depth consistency asks for it.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn as nn

from nvs.core.choices import check_choice
from nvs.core.errors import UserError
from nvs.core.types import Batch, Extras, Outputs
from nvs.models.depth_decoder import DepthDecoder


NORM_BATCHES = ("separate", "joint")


class _LatentDepth(nn.Module):
    """Depth decoded from latents: the transformed latent, then (when the losses ask) the source's and the target's
    own. ``norm_batches``: ``separate`` decodes each in its own call, as the authors' code does (a BatchNorm in the
    decoder normalises each with its own statistics and updates its running statistics three times a step);
    ``joint`` decodes them in one batch (one set of statistics per step)."""

    def __init__(self, norm_batches: str = "separate"):
        super().__init__()
        self.norm_batches = check_choice(norm_batches, NORM_BATCHES, "depth_norm_batches")
        self.decode_all = self._separately if norm_batches == "separate" else self._jointly  # chosen once

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """(N,n,3) -> (N,1,S,S)."""
        raise NotImplementedError

    def forward(self, z_t: torch.Tensor, z_s: torch.Tensor, encode_target: Callable[[], torch.Tensor], batch: Batch,
                needs: frozenset[str]) -> Outputs:
        # The code's order: transformed latent, source latent, target's own latent.
        extras = [key for key in (Extras.DEPTH_SRC, Extras.DEPTH_FROM_TGT) if key in needs]
        latents = [z_t] + [encode_target() if key == Extras.DEPTH_FROM_TGT else z_s for key in extras]
        depths = self.decode_all(latents) if extras else [self.decode(z_t)]
        return {"depth": depths[0], **dict(zip(extras, depths[1:]))}

    def _separately(self, latents: list[torch.Tensor]) -> list[torch.Tensor]:
        return [self.decode(z) for z in latents]

    def _jointly(self, latents: list[torch.Tensor]) -> list[torch.Tensor]:
        return list(self.decode(torch.cat(latents)).chunk(len(latents)))


class PredictedDepth(_LatentDepth):
    """The paper: a per-pixel depth map from the depth decoder psi_d."""

    def __init__(self, image_size: int, n_points: int, head: nn.Module, norm_batches: str = "separate"):
        super().__init__(norm_batches)
        self.decoder = DepthDecoder(image_size, n_points, head)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self.decoder(z)


class PlaneDepth(_LatentDepth):
    """One fronto-parallel plane per sample: an MLP on the flattened latent -> one raw value -> the data's depth head.

    No depth decoder. The last layer starts at zero, so every plane starts where the head maps 0 (depth 2 for
    objects: the object centre; disparity 5 for scenes). Edge smoothness of a plane is identically 0; depth consistency compares the
    planes of the target's own latent and of the transformed one.
    """

    def __init__(self, image_size: int, n_points: int, head: nn.Module, hidden: int = 256):
        super().__init__("joint")
        self.image_size = image_size
        self.mlp = nn.Sequential(nn.Linear(n_points * 3, hidden), nn.LeakyReLU(0.2), nn.Linear(hidden, 1))
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)
        self.head = head

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        S = self.image_size
        return self.head(self.mlp(z.flatten(1)).view(-1, 1, 1, 1)).expand(-1, 1, S, S)


class OracleDepth(nn.Module):
    """The ground-truth target depth of the data (``batch["depth_tgt"]``): an upper bound, never a default.

    No parameters and no depth decoder. The depth extras are ground truth too (the target's own depth is the same
    map, the source's is ``depth_src``), so depth consistency is 0 and edge smoothness and the warp loss are constants:
    they train nothing (the module warns once) and can be dropped from ``loss=[...]``.
    """

    def __init__(self, image_size: int | None = None, n_points: int | None = None):
        super().__init__()

    @staticmethod
    def _read(batch: Batch, key: str) -> torch.Tensor:
        if key not in batch:
            raise UserError(f"model/depth=oracle reads the ground-truth '{key}', which this data has none of: use "
                            "rendered data with depth (data.loader.with_depth=true, depth/ files) or another "
                            "model/depth option")
        return batch[key]

    def forward(self, z_t: torch.Tensor, z_s: torch.Tensor, encode_target: Callable[[], torch.Tensor], batch: Batch,
                needs: frozenset[str]) -> Outputs:
        depth = self._read(batch, "depth_tgt")
        out = {"depth": depth}
        if Extras.DEPTH_FROM_TGT in needs:
            out[Extras.DEPTH_FROM_TGT] = depth
        if Extras.DEPTH_SRC in needs:
            out[Extras.DEPTH_SRC] = self._read(batch, "depth_src")
        return out
