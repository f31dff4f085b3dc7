"""Loss terms, one class each: ``term(outputs, batch) -> scalar`` (unweighted); the module applies ``weight``.

Each class declares ``needs``: the network extras (see ``nvs.core.types.Extras``) it reads, so a forward computes
only what the enabled losses use; ``check_network`` is its build-time check against the network (``nvs.run.build``).
Every option is resolved in ``__init__`` (a function or a tuple chosen once), so ``forward`` tests no flag.
Image-space terms are computed on the [-1,1] range, as the paper's code does.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F

from nvs.core.choices import check_choice
from nvs.core.errors import UserError
from nvs.core.protocols import MultiScale
from nvs.core.scales import UPSAMPLES, upsample_side
from nvs.core.types import Batch, Extras, Outputs, to_model_range
from nvs.models.perceptual import VGG16Features


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

    def check_network(self, net: nn.Module, key: str) -> None:
        """Build time: raise a UserError if this term cannot be computed on ``net``'s outputs (``key``: its config key)."""


def _identity(x: torch.Tensor) -> torch.Tensor:
    return x


# model: [-1,1] (what the authors' code feeds its losses); image: [0,1]
IMAGE_RANGES = {"model": to_model_range, "image": _identity}


class ReconLoss(LossTerm):
    """Multi-scale L1: sum_i w_i |up(I~_t^i) - I_t| on [-1,1]; ``scale_weights`` run from the finest scale to coarser.

    ``scale_weights=[1]`` is "w/o multi-scale" (final scale only). ``side_upsample``: how the coarser predictions
    are brought to full size, ``nearest`` (the authors' code) or ``bilinear``. At build time the network's
    ``n_scales`` (the length of its ``rgb_scales``) must cover the weights.
    """

    def __init__(self, weight: float = 10.0, scale_weights: Sequence[float] = (1.0, 0.5, 0.2, 0.1), side_upsample: str = "nearest"):
        super().__init__(weight)
        self.scale_weights = [float(w) for w in scale_weights]
        if not self.scale_weights:
            raise ValueError("scale_weights must list at least the final scale")
        self.side_upsample = check_choice(side_upsample, UPSAMPLES, "side_upsample")

    key = "loss.recon"  # its config key, set by the build check

    def _too_many(self, n_scales: int) -> UserError:
        return UserError(f"{self.key}.scale_weights has {len(self.scale_weights)} weights but the model predicts "
                         f"{n_scales} scale(s); use loss=[recon_final,...] or {self.key}.scale_weights=[1.0]")

    def check_network(self, net: nn.Module, key: str) -> None:
        self.key = key
        n_scales = net.n_scales if isinstance(net, MultiScale) else None
        if n_scales is not None and len(self.scale_weights) > n_scales:
            raise self._too_many(n_scales)

    def forward(self, out: Outputs, batch: Batch) -> torch.Tensor:
        tgt = to_model_range(batch["tgt"])
        preds = out["rgb_scales"][::-1][:len(self.scale_weights)]  # finest first
        try:
            pairs = list(zip(self.scale_weights, preds, strict=True))
        except ValueError:  # too few predictions from a network without ``n_scales`` (unchecked at build time)
            raise self._too_many(len(preds)) from None
        total = tgt.new_zeros(())
        for w, p in pairs:
            p = upsample_side(p, tuple(tgt.shape[-2:]), self.side_upsample)
            total = total + w * (up(p) - tgt).abs().mean()
        return total


class VGGLoss(LossTerm):
    """Perceptual loss: sum over VGG16 layers of the mean L1 between features (ImageNet weights, frozen).

    ``image_range``: ``model`` feeds the [-1,1] images into the ImageNet normalisation, as the authors' code does;
    ``image`` feeds [0,1] images, as ImageNet's statistics assume. ``size``: both images resized bilinearly to
    size x size first (the code: 224), or ``null`` for the native size.
    """

    def __init__(self, weight: float = 1.0, layers: Sequence[str] = ("relu1_2", "relu2_2", "relu3_3", "relu4_3"),
                 image_range: str = "model", size: int | None = 224):
        super().__init__(weight)
        self.image_range = check_choice(image_range, IMAGE_RANGES, "vgg_range")
        self.to_range = IMAGE_RANGES[image_range]
        if size is not None and (not isinstance(size, int) or size < 32):
            raise ValueError(f"vgg_size={size!r}: an image size of at least 32, or null for the native size")
        self.size = size
        self.resize = _identity if size is None else self._resize
        self.vgg = VGG16Features(tuple(layers))

    def _resize(self, x: torch.Tensor) -> torch.Tensor:
        if tuple(x.shape[-2:]) == (self.size, self.size):
            return x
        return F.interpolate(x, size=(self.size, self.size), mode="bilinear", align_corners=False)

    def _input(self, img: torch.Tensor) -> torch.Tensor:
        return self.resize(self.to_range(img))

    def forward(self, out: Outputs, batch: Batch) -> torch.Tensor:
        pred, tgt = out["rgb"], batch["tgt"]
        # Target features need no graph: batching them with the prediction would make backward run through both.
        with torch.no_grad():
            feats_tgt = self.vgg(self._input(tgt.to(pred.dtype)))
        feats_pred = self.vgg(self._input(pred))
        return sum((up(fp) - up(ft)).abs().mean() for fp, ft in zip(feats_pred, feats_tgt))


class DepthConsistencyLoss(LossTerm):
    """|psi_d(z_t) - psi_d(z~_t)|: the depth of the target's own latent against that of the transformed latent."""

    needs = frozenset({Extras.DEPTH_FROM_TGT})

    def __init__(self, weight: float = 10.0):
        super().__init__(weight)

    def forward(self, out: Outputs, batch: Batch) -> torch.Tensor:
        return (up(out[Extras.DEPTH_FROM_TGT]) - up(out["depth"])).abs().mean()


def edge_aware_smoothness(depth: torch.Tensor, image: torch.Tensor, factor: float) -> torch.Tensor:
    """mean |d_x D| exp(-factor mean_c |d_x I|) + the same along y; depth (B,1,H,W), image (B,C,H,W) -> scalar."""
    dd_y, dd_x = depth[:, :, 1:] - depth[:, :, :-1], depth[..., 1:] - depth[..., :-1]
    di_y, di_x = image[:, :, 1:] - image[:, :, :-1], image[..., 1:] - image[..., :-1]
    w_y = torch.exp(-factor * di_y.abs().mean(1, keepdim=True))
    w_x = torch.exp(-factor * di_x.abs().mean(1, keepdim=True))
    return (dd_x.abs() * w_x).mean() + (dd_y.abs() * w_y).mean()


class EdgeSmoothLoss(LossTerm):
    """Edge-aware smoothness |dD| exp(-factor |dI|) of the predicted target depth (and the source depth).

    The authors' code: ``factor=10`` on [-1,1] images (``image_range=model``), on the target and the source depth
    (``on_source``); the paper's text: factor 1, target only (with ``image_range=image`` this is kornia's
    ``inverse_depth_smoothness_loss``).
    """

    def __init__(self, weight: float = 10.0, on_source: bool = True, factor: float = 10.0,
                 image_range: str = "model"):
        super().__init__(weight)
        if not factor >= 0:
            raise ValueError(f"smooth_factor={factor!r}: must be >= 0")
        self.factor = float(factor)
        self.image_range = check_choice(image_range, IMAGE_RANGES, "smooth_range")
        self.to_range = IMAGE_RANGES[image_range]
        # The source term is a build-time choice: the (depth, image) pairs summed, one loop over them.
        self.pairs = (("depth", "tgt"), (Extras.DEPTH_SRC, "src")) if on_source else (("depth", "tgt"),)
        self.needs = frozenset({Extras.DEPTH_SRC}) if on_source else frozenset()

    def forward(self, out: Outputs, batch: Batch) -> torch.Tensor:
        return sum(edge_aware_smoothness(up(out[depth_key]), self.to_range(up(batch[image_key])), self.factor)
                   for depth_key, image_key in self.pairs)


class WarpLoss(LossTerm):
    """L1 between the source image warped by the predicted target depth and the target, on [-1,1].

    ``pixels``: ``all`` averages every pixel (the authors' code, whose warp pads with the border), ``valid``
    averages only the pixels whose source point is in front of the source camera and inside the source image.
    """

    needs = frozenset({Extras.WARPED_SRC})

    def __init__(self, weight: float = 10.0, pixels: str = "all"):
        super().__init__(weight)
        self.masked = check_choice(pixels, ("all", "valid"), "warp_loss_pixels") == "valid"
        self.reduce = _valid_mean if self.masked else _all_mean

    def forward(self, out: Outputs, batch: Batch) -> torch.Tensor:
        diff = (to_model_range(up(out[Extras.WARPED_SRC])) - to_model_range(batch["tgt"])).abs()
        return self.reduce(diff, out)


def _all_mean(diff: torch.Tensor, out: Outputs) -> torch.Tensor:
    """Mean of (B,3,H,W) over every pixel."""
    return diff.mean()


def _valid_mean(diff: torch.Tensor, out: Outputs) -> torch.Tensor:
    """Mean of (B,3,H,W) over the pixels where ``out["warp_valid"]`` (B,1,H,W) is 1."""
    valid = up(out["warp_valid"])
    return (diff * valid).sum() / (valid.sum() * diff.shape[1]).clamp_min(1.0)
