"""Per-image metrics pinned against skimage, scipy and hand-worked cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import correlate, gaussian_filter
from skimage.metrics import peak_signal_noise_ratio as sk_psnr
from skimage.metrics import structural_similarity as sk_ssim

from nvs.metrics import per_image as M
from nvs.models.perceptual import LPIPS


def image_pair(shape=(2, 3, 40, 36), noise: float = 0.1, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A smooth image and a noisy copy, float64 in [0,1]."""
    rng = np.random.default_rng(seed)
    tgt = np.clip(gaussian_filter(rng.random(shape), (0, 0, 2, 2)) * 3 - 1, 0, 1)
    pred = np.clip(tgt + noise * rng.standard_normal(shape), 0, 1)
    return pred, tgt


def t(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(x)).float()


# --- L1 ---


def test_l1_is_mae_on_minus_one_one_range():
    pred = torch.full((2, 3, 4, 4), 0.25)
    tgt = torch.full((2, 3, 4, 4), 0.75)
    tgt[1] = 0.25
    tgt[1, 0, 0, 0] = 1.0  # one pixel off by 0.75 in [0,1] = 1.5 in [-1,1]
    torch.testing.assert_close(M.l1(pred, tgt), torch.tensor([1.0, 1.5 / 48]))


# --- SSIM, the paper's variant ---


def test_ssim_paper_identical_images_is_one():
    pred, _ = image_pair()
    torch.testing.assert_close(M.ssim_paper(t(pred), t(pred)), torch.ones(2), atol=1e-6, rtol=0)


def window_mass(h: int, w: int, sigma: float = 0.5, radius: int = 5) -> np.ndarray:
    """Per pixel, the Gaussian window weight that falls inside an (h,w) image (1 away from the border)."""
    g = np.exp(-(np.arange(-radius, radius + 1) ** 2) / (2 * sigma**2))
    g /= g.sum()
    inside = lambda n: np.array([sum(g[k + radius] for k in range(-radius, radius + 1) if 0 <= i + k < n)
                                 for i in range(n)])
    return np.outer(inside(h), inside(w))


def test_ssim_paper_constant_images_closed_form():
    # Constant grey levels a, b: with zero padding, at a pixel whose in-image window mass is m,
    # mu = a m, var = a^2 (m - m^2), cov = a b (m - m^2), so SSIM is a closed form of m only.
    h, w = 16, 12
    pred = torch.tensor([0.2, 0.3, 0.4]).view(1, 3, 1, 1).expand(1, 3, h, w)  # grey 0.3
    tgt = torch.tensor([0.5, 0.6, 0.7]).view(1, 3, 1, 1).expand(1, 3, h, w)  # grey 0.6
    a, b, c1, c2 = 0.3, 0.6, 0.01**2, 0.03**2
    m = window_mass(h, w)
    s = m - m**2
    ssim_map = ((2 * a * b * m**2 + c1) * (2 * a * b * s + c2)) / (((a**2 + b**2) * m**2 + c1) * ((a**2 + b**2) * s + c2))
    assert M.ssim_paper(pred, tgt).item() == pytest.approx(ssim_map.mean(), abs=1e-5)
    # The interior alone would give (2ab + c1) / (a^2 + b^2 + c1); the zero-padded border moves the mean.
    assert abs(ssim_map.mean() - (2 * a * b + c1) / (a**2 + b**2 + c1)) > 1e-3


def test_ssim_paper_matches_scipy_reference():
    pred, tgt = image_pair()
    g = np.exp(-(np.arange(-5, 6) ** 2) / (2 * 0.5**2))
    win = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01**2, 0.03**2
    ref = []
    for p, q in zip(pred, tgt):
        x, y = p.mean(0), q.mean(0)
        blur = lambda z: correlate(z, win, mode="constant", cval=0.0)
        mx, my = blur(x), blur(y)
        vx, vy, cxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
        ref.append((((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))).mean())
    np.testing.assert_allclose(M.ssim_paper(t(pred), t(tgt)).numpy(), ref, atol=1e-5)


# --- standard SSIM and PSNR against skimage ---


@pytest.mark.parametrize("noise", [0.05, 0.3])
def test_ssim_matches_skimage(noise):
    pred, tgt = image_pair(noise=noise, seed=1)
    ref = [
        sk_ssim(p, q, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=0)
        for p, q in zip(pred, tgt)
    ]
    # Both average over the valid region; float32 vs float64 is the only difference (~1e-6).
    np.testing.assert_allclose(M.ssim(t(pred), t(tgt)).numpy(), ref, atol=1e-4)


def test_ssim_rejects_images_smaller_than_window():
    with pytest.raises(ValueError, match="11x11"):
        M.ssim(torch.rand(1, 3, 10, 32), torch.rand(1, 3, 10, 32))


def test_psnr_matches_skimage():
    pred, tgt = image_pair(noise=0.05)
    ref = [sk_psnr(q, p, data_range=1.0) for p, q in zip(pred, tgt)]
    np.testing.assert_allclose(M.psnr(t(pred), t(tgt)).numpy(), ref, rtol=1e-5)
    assert torch.isinf(M.psnr(t(pred), t(pred))).all()


# --- LPIPS wrapper ---


def test_lpips_metric_matches_module_and_is_float32():
    pred, tgt = image_pair(shape=(2, 3, 32, 32))
    got = M.lpips(t(pred).bfloat16(), t(tgt).bfloat16())
    assert got.shape == (2,) and got.dtype == torch.float32
    ref = LPIPS()(t(pred).bfloat16().float(), t(tgt).bfloat16().float())
    torch.testing.assert_close(got, ref)
    assert M.lpips(t(tgt), t(tgt)).abs().max() < 1e-7


# --- depth ---


def depth_case() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Three 2x2 depth maps: one with a no-data pixel, one with NaN gt and a masked pixel, one with nothing valid."""
    nan = float("nan")
    gt = torch.tensor([[[1.0, 2.0], [4.0, 0.0]], [[nan, 3.0], [3.0, 3.0]], [[0.0, 0.0], [0.0, 0.0]]]).unsqueeze(1)
    pred = torch.tensor([[[2.0, 2.0], [2.0, 5.0]], [[1.0, 6.0], [3.0, 100.0]], [[1.0, 1.0], [1.0, 1.0]]]).unsqueeze(1)
    mask = torch.tensor([[[1, 1], [1, 1]], [[1, 1], [1, 0]], [[1, 1], [1, 1]]], dtype=torch.bool).unsqueeze(1)
    return pred, gt, mask


LN2 = math.log(2)


@pytest.mark.parametrize(
    "name, expected",
    [
        # image 0: valid (gt, pred) = (1,2), (2,2), (4,2); image 1: (3,6), (3,3)
        ("depth_l1", [(1 + 0 + 2) / 3, (3 + 0) / 2]),
        ("depth_l1_rel", [(1 / 1 + 0 + 2 / 4) / 3, (3 / 3 + 0) / 2]),
        ("depth_l1_inv", [(0.5 + 0 + 0.25) / 3, (1 / 3 - 1 / 6 + 0) / 2]),
        # d = log(pred/gt): image 0 (ln2, 0, -ln2) -> sqrt(2 ln2^2 / 3); image 1 (ln2, 0) -> ln2 / 2
        ("depth_sc_inv", [LN2 * math.sqrt(2 / 3), LN2 / 2]),
    ],
)
def test_depth_metrics_hand_worked(name, expected):
    pred, gt, mask = depth_case()
    got = M.DEPTH_METRICS[name](pred, gt, mask)
    assert got.shape == (3,)
    torch.testing.assert_close(got[:2], torch.tensor(expected), atol=1e-6, rtol=1e-6)
    assert torch.isnan(got[2])  # no valid pixel: NaN, not a perfect score


def test_depth_mask_changes_result():
    pred, gt, _ = depth_case()
    # Without the mask, image 1 also counts the (gt 3, pred 100) pixel.
    assert M.depth_l1(pred, gt)[1].item() == pytest.approx((3 + 0 + 97) / 3)


def test_sc_inv_is_scale_invariant_and_zero_for_scaled_depth():
    gt = 1 + 4 * torch.rand(2, 1, 8, 8, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(M.depth_sc_inv(3.0 * gt, gt), torch.zeros(2), atol=1e-3, rtol=0)
    pred = gt * (1 + 0.2 * torch.rand(gt.shape, generator=torch.Generator().manual_seed(1)))
    torch.testing.assert_close(M.depth_sc_inv(2.5 * pred, gt), M.depth_sc_inv(pred, gt), atol=1e-5, rtol=1e-4)


def test_nonpositive_prediction_gives_finite_error():
    gt = torch.full((1, 1, 2, 2), 2.0)
    pred = torch.tensor([[[[0.0, -1.0], [2.0, 2.0]]]])
    for fn in M.DEPTH_METRICS.values():
        assert torch.isfinite(fn(pred, gt)).all()


# --- registry ---


def test_compute_all_images_only_and_with_depth():
    pred, tgt = image_pair(shape=(2, 3, 32, 32))
    out = M.compute_all(t(pred), t(tgt))
    assert set(out) == set(M.IMAGE_METRICS) == {"l1", "ssim_paper", "ssim", "psnr", "lpips"}
    d_pred, d_gt, _ = depth_case()
    d_pred, d_gt = d_pred[:2].repeat(1, 1, 16, 16), d_gt[:2].repeat(1, 1, 16, 16)
    out = M.compute_all(t(pred), t(tgt), depth_pred=d_pred, depth_gt=d_gt)
    assert set(out) == set(M.IMAGE_METRICS) | set(M.DEPTH_METRICS)
    assert all(v.shape == (2,) and v.dtype == torch.float32 for v in out.values())


def test_function_tables_hold_exactly_the_metric_spec_names_in_its_order():
    from nvs.core import metric_spec

    assert tuple(M.IMAGE_METRICS) == metric_spec.IMAGE_METRICS
    assert tuple(M.DEPTH_METRICS) == metric_spec.DEPTH_METRICS
    d_pred, d_gt, _ = depth_case()
    pred, tgt = image_pair(shape=(1, 3, 32, 32))
    out = M.compute_all(t(pred), t(tgt), depth_pred=d_pred[:1].repeat(1, 1, 16, 16),
                        depth_gt=d_gt[:1].repeat(1, 1, 16, 16))
    assert tuple(out) == metric_spec.METRICS  # the per-image CSV's column order


def test_a_metric_missing_from_the_spec_fails_at_import(monkeypatch):
    import importlib

    from nvs.core import metric_spec

    monkeypatch.setattr(metric_spec, "METRICS", metric_spec.METRICS[:-1])
    try:
        with pytest.raises(ImportError, match="nvs.core.metric_spec specifies"):
            importlib.reload(M)
    finally:
        monkeypatch.undo()
        importlib.reload(M)


def test_compute_all_is_float32_under_bf16_autocast():
    pred, tgt = image_pair(shape=(2, 3, 32, 32))
    ref = M.compute_all(t(pred), t(tgt))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = M.compute_all(t(pred), t(tgt))
    for name in ref:
        assert got[name].dtype == torch.float32
        torch.testing.assert_close(got[name], ref[name], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("name", ["l1", "ssim_paper", "ssim", "psnr", "lpips"])
def test_image_metrics_reject_mismatched_shapes(name):
    with pytest.raises(ValueError):
        M.IMAGE_METRICS[name](torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 12))
