"""Per-image evaluation metrics; every function returns a float32 (B,) tensor, one value per image.

Their names, directions and decimals are ``nvs.core.metric_spec``'s; the tables below hold exactly its names.

Convention: images are (B,3,H,W) in [0,1]; depths are (B,1,H,W) in scene units with 0 (or non-finite) in the
ground truth meaning "no data". Inputs of any float dtype (bf16 included) are evaluated in float32.
"""

from __future__ import annotations

import functools
from typing import Callable

import torch
import torch.nn.functional as F
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

from nvs.core import metric_spec
from nvs.models.perceptual import LPIPS

# Smallest predicted depth used in ratios and logs, so a non-positive prediction scores a large finite error.
MIN_PRED_DEPTH = 1e-6
# Half-width of the standard SSIM window (11x11, sigma 1.5).
_SSIM_RADIUS = 5


def _f32(*xs: torch.Tensor) -> tuple[torch.Tensor, ...]:
    return tuple(x.float() for x in xs)


def _no_autocast(fn: Callable[..., torch.Tensor]) -> Callable[..., torch.Tensor]:
    """Run a metric with autocast off: Lightning evaluates under bf16 autocast, which would downcast convs."""

    @functools.wraps(fn)
    def wrapper(pred: torch.Tensor, *args, **kwargs) -> torch.Tensor:
        with torch.autocast(device_type=pred.device.type, enabled=False):
            return fn(pred, *args, **kwargs)

    return wrapper


def _check_images(pred: torch.Tensor, tgt: torch.Tensor) -> None:
    if pred.shape != tgt.shape or pred.dim() != 4:
        raise ValueError(f"expected two (B,C,H,W) images of equal shape, got {tuple(pred.shape)}, {tuple(tgt.shape)}")


@_no_autocast
def l1(pred: torch.Tensor, tgt: torch.Tensor) -> torch.Tensor:
    """Mean absolute error on the [-1,1] range (the paper's convention, = 2 x the [0,1] MAE). (B,3,H,W) -> (B,)."""
    _check_images(pred, tgt)
    pred, tgt = _f32(pred, tgt)
    return (2 * (pred - tgt)).abs().flatten(1).mean(dim=1)


def _gaussian_window(size: int, sigma: float, device: torch.device) -> torch.Tensor:
    x = torch.arange(size, device=device, dtype=torch.float32) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).view(1, 1, size, size)


@_no_autocast
def ssim_paper(pred: torch.Tensor, tgt: torch.Tensor) -> torch.Tensor:
    """The paper's SSIM: grey = RGB mean, 11x11 Gaussian sigma=0.5, zero padding, full-size map mean. (B,3,H,W) -> (B,).

    Not the standard SSIM (see `ssim`): the narrow window and zero padding (which darkens the borders) follow
    the paper's evaluation code, so numbers are comparable with its tables only.
    """
    _check_images(pred, tgt)
    pred, tgt = _f32(pred, tgt)
    x, y = pred.mean(dim=1, keepdim=True), tgt.mean(dim=1, keepdim=True)
    w = _gaussian_window(11, 0.5, x.device)

    def blur(z: torch.Tensor) -> torch.Tensor:
        return F.conv2d(z, w, padding=5)

    c1, c2 = 0.01**2, 0.03**2
    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x**2
    var_y = blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * cov + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    return (num / den).flatten(1).mean(dim=1)


@_no_autocast
def ssim(pred: torch.Tensor, tgt: torch.Tensor) -> torch.Tensor:
    """Standard SSIM (Wang et al. 2004): 11x11 Gaussian sigma=1.5 per RGB channel, data range 1. (B,3,H,W) -> (B,).

    Averaged over the valid region only (the 5-pixel border, whose windows leave the image, is dropped), as in
    the reference MATLAB code and skimage. torchmetrics' own mean also counts reflect-padded border pixels,
    which moves the score by ~1e-2 on small images, so its SSIM map is cropped here before averaging.
    """
    _check_images(pred, tgt)
    if min(pred.shape[-2:]) < 2 * _SSIM_RADIUS + 1:
        raise ValueError(f"SSIM needs images of at least 11x11 pixels, got {tuple(pred.shape[-2:])}")
    pred, tgt = _f32(pred, tgt)
    _, ssim_map = structural_similarity_index_measure(
        pred, tgt, gaussian_kernel=True, sigma=1.5, kernel_size=11, data_range=1.0, reduction="none",
        return_full_image=True,
    )
    r = _SSIM_RADIUS
    return ssim_map[..., r:-r, r:-r].flatten(1).mean(dim=1)


@_no_autocast
def psnr(pred: torch.Tensor, tgt: torch.Tensor) -> torch.Tensor:
    """PSNR in dB with data range 1, per image (inf for identical images). (B,3,H,W) -> (B,)."""
    _check_images(pred, tgt)
    pred, tgt = _f32(pred, tgt)
    return peak_signal_noise_ratio(pred, tgt, data_range=1.0, reduction="none", dim=(1, 2, 3))


@functools.lru_cache(maxsize=4)
def _lpips_module(device: torch.device) -> LPIPS:
    return LPIPS().to(device)


@_no_autocast
def lpips(pred: torch.Tensor, tgt: torch.Tensor) -> torch.Tensor:
    """LPIPS-VGG v0.1 distance (lower is better), float32, no autocast. (B,3,H,W) -> (B,)."""
    _check_images(pred, tgt)
    pred, tgt = _f32(pred, tgt)
    with torch.no_grad():
        return _lpips_module(pred.device)(pred, tgt)


def _depth_valid(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    if pred.shape != gt.shape or pred.dim() != 4 or pred.shape[1] != 1:
        raise ValueError(f"expected two (B,1,H,W) depths of equal shape, got {tuple(pred.shape)}, {tuple(gt.shape)}")
    valid = (gt > 0) & torch.isfinite(gt)
    if mask is not None:
        valid = valid & mask.bool().expand_as(gt)
    return valid


def _masked_mean(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    # 0/0 = NaN for an image without a valid pixel: "no data" must not read as a perfect score.
    x = torch.where(valid, x, torch.zeros_like(x))
    return x.flatten(1).sum(dim=1) / valid.flatten(1).sum(dim=1)


@_no_autocast
def depth_l1(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """L1-all: mean |gt - pred| over valid pixels (gt > 0, finite, in mask); NaN if none. (B,1,H,W) -> (B,)."""
    valid = _depth_valid(pred, gt, mask)
    pred, gt = _f32(pred, gt)
    return _masked_mean((gt - pred).abs(), valid)


@_no_autocast
def depth_l1_rel(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """L1-rel: mean |gt - pred| / gt over valid pixels; NaN if none. (B,1,H,W) -> (B,)."""
    valid = _depth_valid(pred, gt, mask)
    pred, gt = _f32(pred, gt)
    gt_safe = torch.where(valid, gt, torch.ones_like(gt))
    return _masked_mean((gt - pred).abs() / gt_safe, valid)


@_no_autocast
def depth_l1_inv(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """L1-inv: mean |1/gt - 1/pred| over valid pixels, pred clamped to MIN_PRED_DEPTH; NaN if none. (B,1,H,W) -> (B,)."""
    valid = _depth_valid(pred, gt, mask)
    pred, gt = _f32(pred, gt)
    gt_safe = torch.where(valid, gt, torch.ones_like(gt))
    return _masked_mean((1 / gt_safe - 1 / pred.clamp_min(MIN_PRED_DEPTH)).abs(), valid)


@_no_autocast
def depth_sc_inv(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Scale-invariant log error sqrt(mean d^2 - (mean d)^2), d = log pred - log gt, on valid pixels. (B,1,H,W) -> (B,).

    pred is clamped to MIN_PRED_DEPTH; NaN for an image without valid pixels.
    """
    valid = _depth_valid(pred, gt, mask)
    pred, gt = _f32(pred, gt)
    gt_safe = torch.where(valid, gt, torch.ones_like(gt))
    d = torch.log(pred.clamp_min(MIN_PRED_DEPTH)) - torch.log(gt_safe)
    # Rounding can make the variance slightly negative when d is constant; clamp before the root.
    return (_masked_mean(d**2, valid) - _masked_mean(d, valid) ** 2).clamp_min(0).sqrt()


# The functions under nvs.core.metric_spec's keys: one list of names, which every table and figure reads.
_FUNCTIONS: dict[str, Callable[..., torch.Tensor]] = {
    "l1": l1, "ssim_paper": ssim_paper, "ssim": ssim, "psnr": psnr, "lpips": lpips,
    "depth_l1": depth_l1, "depth_l1_rel": depth_l1_rel, "depth_l1_inv": depth_l1_inv, "depth_sc_inv": depth_sc_inv,
}
if set(_FUNCTIONS) != set(metric_spec.METRICS):  # a metric added to one list and not the other fails at import
    raise ImportError(f"nvs.metrics.per_image computes {sorted(_FUNCTIONS)} but nvs.core.metric_spec specifies "
                      f"{sorted(metric_spec.METRICS)}")

# In nvs.core.metric_spec's order (the per-image CSV's columns).
IMAGE_METRICS: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {
    name: _FUNCTIONS[name] for name in metric_spec.IMAGE_METRICS}
DEPTH_METRICS: dict[str, Callable[..., torch.Tensor]] = {name: _FUNCTIONS[name] for name in metric_spec.DEPTH_METRICS}


@torch.no_grad()
def compute_all(
    pred: torch.Tensor,
    tgt: torch.Tensor,
    depth_pred: torch.Tensor | None = None,
    depth_gt: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Every image metric, plus every depth metric when both depths are given. Images (B,3,H,W) -> {name: (B,)}."""
    out = {name: fn(pred, tgt) for name, fn in IMAGE_METRICS.items()}
    if depth_pred is not None and depth_gt is not None:
        out.update({name: fn(depth_pred, depth_gt) for name, fn in DEPTH_METRICS.items()})
    return out
