"""Loss terms, one class each: ``term(outputs, batch) -> scalar`` (unweighted); the module applies ``weight``.

Each class declares ``needs``: the network extras (see ``nvs.models.net.Extras``) it reads, so a forward computes
only what the enabled losses use. Image-space terms are computed on the [-1,1] range, as the paper's code does.
"""

from __future__ import annotations

import kornia
import torch
import torch.nn as nn
import torch.nn.functional as F

from nvs.errors import UserError
from nvs.models.net import Extras, to_model_range
from nvs.types import Batch, Outputs


def up(x: torch.Tensor) -> torch.Tensor:
    """bf16/fp16 -> float32 for the loss arithmetic; float32 and float64 stay as they are (float64 gradchecks)."""
    return x.to(torch.promote_types(x.dtype, torch.float32))


class LossTerm(nn.Module):
    needs: frozenset[str] = frozenset()

    def __init__(self, weight: float):
        super().__init__()
        if weight < 0:
            raise ValueError(f"loss weight must be >= 0, got {weight}")
        self.weight = float(weight)


class ReconLoss(LossTerm):
    """Multi-scale L1: sum_i w_i |up(I~_t^i) - I_t|; ``scale_weights`` run from the finest scale to coarser ones.

    ``scale_weights=[1]`` is "w/o multi-scale" (final scale only).
    """

    def __init__(self, weight: float = 10.0, scale_weights=(1.0, 0.5, 0.2, 0.1)):
        super().__init__(weight)
        self.scale_weights = [float(w) for w in scale_weights]
        if not self.scale_weights:
            raise ValueError("scale_weights must list at least the final scale")

    def forward(self, out: Outputs, batch: Batch) -> torch.Tensor:
        tgt = to_model_range(batch["tgt"])
        preds = out["rgb_scales"][::-1]  # finest first
        if len(self.scale_weights) > len(preds):
            raise UserError(f"loss.recon.scale_weights has {len(self.scale_weights)} weights but the model predicts "
                            f"{len(preds)} scale(s); use loss=[recon_final,...] or loss.recon.scale_weights=[1.0]")
        total = tgt.new_zeros(())
        for w, p in zip(self.scale_weights, preds):
            if p.shape[-2:] != tgt.shape[-2:]:
                p = F.interpolate(p, size=tgt.shape[-2:], mode="bilinear", align_corners=False)
            total = total + w * (up(p) - tgt).abs().mean()
        return total


class VGGLoss(LossTerm):
    """Perceptual loss: sum over VGG16 layers of the mean L1 between features (ImageNet weights, frozen)."""

    def __init__(self, weight: float = 1.0, layers=("relu1_2", "relu2_2", "relu3_3", "relu4_3")):
        super().__init__(weight)
        from nvs.models.vgg import VGG16Features

        self.vgg = VGG16Features(tuple(layers))

    def forward(self, out: Outputs, batch: Batch) -> torch.Tensor:
        pred, tgt = out["rgb"], batch["tgt"]
        # Target features need no graph: batching them with the prediction would make backward run through both.
        with torch.no_grad():
            feats_tgt = self.vgg(tgt.to(pred.dtype))
        feats_pred = self.vgg(pred)
        return sum((up(fp) - up(ft)).abs().mean() for fp, ft in zip(feats_pred, feats_tgt))


class DepthConsistencyLoss(LossTerm):
    """|psi_d(z_t) - psi_d(z~_t)|: the depth of the target's own latent against that of the transformed latent."""

    needs = frozenset({Extras.DEPTH_FROM_TGT})

    def __init__(self, weight: float = 10.0):
        super().__init__(weight)

    def forward(self, out: Outputs, batch: Batch) -> torch.Tensor:
        return (up(out[Extras.DEPTH_FROM_TGT]) - up(out["depth"])).abs().mean()


class EdgeSmoothLoss(LossTerm):
    """Edge-aware smoothness |dD| exp(-|dI|) of the predicted target depth (and the source depth, as the paper's code)."""

    def __init__(self, weight: float = 10.0, on_source: bool = True):
        super().__init__(weight)
        self.on_source = on_source
        self.needs = frozenset({Extras.DEPTH_SRC}) if on_source else frozenset()

    @staticmethod
    def _term(depth: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        # kornia's smoothness is written for inverse depth but is the same operator on any map.
        return kornia.losses.inverse_depth_smoothness_loss(up(depth), up(image))

    def forward(self, out: Outputs, batch: Batch) -> torch.Tensor:
        loss = self._term(out["depth"], batch["tgt"])
        if self.on_source:
            loss = loss + self._term(out[Extras.DEPTH_SRC], batch["src"])
        return loss


class WarpLoss(LossTerm):
    """L1 between the source image warped by the predicted target depth and the target, on valid pixels."""

    needs = frozenset({Extras.WARPED_SRC})

    def __init__(self, weight: float = 10.0):
        super().__init__(weight)

    def forward(self, out: Outputs, batch: Batch) -> torch.Tensor:
        valid = up(out["warp_valid"])
        diff = (to_model_range(up(out[Extras.WARPED_SRC])) - to_model_range(batch["tgt"])).abs() * valid
        return diff.sum() / (valid.sum() * diff.shape[1]).clamp_min(1.0)
