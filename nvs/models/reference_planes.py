"""Reference rows that predict one depth plane and warp the source with it (no training): the floors of a depth table.

``ConstantDepthWarp``: the same fronto-parallel plane for every image, at a depth fixed before testing (the mean
depth of the training views, computed by ``nvs.run.mean_depth``): it reads no test ground truth, so a trained depth
decoder must beat it. ``GroundTruthPlaneWarp``: each test image's own plane at the mean of its ground-truth depth,
an oracle (it reads the target's depth) that shows what the best single plane per image reaches. Both warp the
source by their plane as ``GroundTruthWarp`` does (pixels with no correspondence: white for objects, the source pixel
for scenes, chosen by ``sky_disparity`` as there).
"""

from __future__ import annotations

import torch

from nvs.core.geometry import inverse_warp
from nvs.core.types import Batch, Outputs
from nvs.models.reference import GroundTruthWarp


class _PlaneWarp(GroundTruthWarp):
    """Warps the source by a per-sample plane ``plane(batch) -> (B,1,H,W)``; outputs the image and that depth."""

    def plane(self, batch: Batch) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        depth = self.plane(batch)
        warp_depth, fill = self.missing(depth, batch["src"])
        warped, valid = inverse_warp(batch["src"], warp_depth, batch["K"], batch["T_tgt_src"])
        rgb = warped * valid + fill * (1 - valid)
        return {"rgb": rgb, "rgb_scales": [rgb * 2 - 1], "depth": depth}


class ConstantDepthWarp(_PlaneWarp):
    """One plane at ``depth`` (data units, > 0) for every image: the floor that uses no test ground truth."""

    def __init__(self, depth: float, image_size: int | None = None, fill: float = 1.0,
                 sky_disparity: float | None = None):
        super().__init__(image_size, fill, sky_disparity)
        if not depth > 0:
            raise ValueError(f"depth={depth!r}: a positive plane depth")
        self.depth = float(depth)

    def plane(self, batch: Batch) -> torch.Tensor:
        src = batch["src"]
        B, _, H, W = src.shape
        return torch.full((B, 1, H, W), self.depth, dtype=src.dtype, device=src.device)


class GroundTruthPlaneWarp(_PlaneWarp):
    """Each image's plane at the mean of its ground-truth target depth (valid pixels: > 0): an oracle reference."""

    def plane(self, batch: Batch) -> torch.Tensor:
        if "depth_tgt" not in batch:
            raise KeyError("GroundTruthPlaneWarp needs ground-truth target depth (data.loader.with_depth=true, "
                           "depth/ files)")
        gt = batch["depth_tgt"]
        valid = (gt > 0) & torch.isfinite(gt)
        count = valid.flatten(1).sum(dim=1)
        if bool((count == 0).any()):
            bad = [batch["id_tgt"][i] if "id_tgt" in batch else str(i) for i in (count == 0).nonzero().flatten()]
            raise ValueError(f"target view(s) {bad[:3]} have no valid ground-truth depth: no plane to fit")
        mean = torch.where(valid, gt, torch.zeros_like(gt)).flatten(1).sum(dim=1) / count
        return mean.view(-1, 1, 1, 1).expand_as(gt).to(batch["src"].dtype)
