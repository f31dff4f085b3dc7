"""Loss terms are >= 0, zero on a perfect prediction where that holds, and declare what they need."""

import pytest
import torch

from nvs.core.errors import UserError
from nvs.core.types import Extras
from nvs.losses.terms import DepthConsistencyLoss, EdgeSmoothLoss, ReconLoss, VGGLoss, WarpLoss
from tests.conftest import fixture_batch


def _perfect_outputs(batch):
    tgt = batch["tgt"]
    scales = [torch.nn.functional.interpolate(tgt, scale_factor=1 / s, mode="area") * 2 - 1 for s in (8, 4, 2)]
    depth = torch.full_like(batch["depth_tgt"], 2.0)
    return {
        "rgb": tgt.clone(),
        "rgb_scales": scales + [tgt * 2 - 1],
        "depth": depth,
        Extras.DEPTH_FROM_TGT: depth.clone(),
        Extras.DEPTH_SRC: depth.clone(),
        Extras.WARPED_SRC: tgt.clone(),
        "warp_valid": torch.ones_like(depth),
    }


def test_final_scale_recon_and_aux_terms_are_zero_on_perfect_prediction():
    batch = fixture_batch()
    out = _perfect_outputs(batch)
    assert ReconLoss(scale_weights=[1.0])(out, batch) == 0
    assert DepthConsistencyLoss()(out, batch) == 0
    assert EdgeSmoothLoss()(out, batch) == 0  # constant depth is perfectly smooth
    assert WarpLoss()(out, batch) == 0
    assert VGGLoss()(out, batch) == 0


def test_terms_are_positive_on_wrong_predictions():
    batch = fixture_batch()
    out = _perfect_outputs(batch)
    out["rgb"] = batch["src"]
    out["rgb_scales"] = [s.flip(-1) for s in out["rgb_scales"]]
    out["depth"] = torch.rand_like(out["depth"]) + 1
    out[Extras.WARPED_SRC] = batch["src"]
    for term in (ReconLoss(), DepthConsistencyLoss(), EdgeSmoothLoss(), WarpLoss(), VGGLoss()):
        assert term(out, batch) > 0, term


def test_multiscale_weights_apply_finest_first():
    batch = fixture_batch()
    batch["tgt"] = torch.full_like(batch["tgt"], 0.25)  # constant: every scale is exact after upsampling
    out = _perfect_outputs(batch)
    out["rgb_scales"][0] = out["rgb_scales"][0] + 0.5  # only the coarsest (1/8) scale is wrong
    assert ReconLoss(scale_weights=[1.0])(out, batch) == 0
    full = ReconLoss(scale_weights=[1.0, 0.5, 0.2, 0.1])(out, batch)
    assert full.item() == pytest.approx(0.1 * 0.5, abs=1e-6)
    out["rgb_scales"][-1] = out["rgb_scales"][-1] + 0.5  # and now the finest
    assert ReconLoss(scale_weights=[1.0, 0.5, 0.2, 0.1])(out, batch).item() == pytest.approx(0.55, abs=1e-6)


def test_warp_loss_ignores_invalid_pixels_only_when_asked():
    batch = fixture_batch()
    out = _perfect_outputs(batch)
    out[Extras.WARPED_SRC] = torch.zeros_like(batch["tgt"])
    out["warp_valid"] = torch.zeros_like(out["warp_valid"])
    assert WarpLoss(pixels="valid")(out, batch) == 0
    # the authors' code averages every pixel: the (border-padded) invalid ones count
    expected = (0 * 2 - 1 - (batch["tgt"] * 2 - 1)).abs().mean()
    assert WarpLoss(pixels="all")(out, batch).item() == pytest.approx(expected.item(), rel=1e-6)


def test_edge_smoothness_matches_kornia_with_the_papers_settings():
    import kornia

    batch = fixture_batch()
    depth = torch.rand(2, 1, 64, 64) + 1
    ours = EdgeSmoothLoss(on_source=False, factor=1.0, image_range="image")({"depth": depth}, batch)
    ref = kornia.losses.inverse_depth_smoothness_loss(depth, batch["tgt"])
    assert ours.item() == pytest.approx(ref.item(), rel=1e-6)


def test_edge_weight_of_the_code_is_stronger_at_image_edges():
    """exp(-10 mean|dI|) on [-1,1] images (the code) weights an edge far less than exp(-|dI|) on [0,1]."""
    img = torch.zeros(1, 3, 8, 8)
    img[..., 4:] = 0.4  # a vertical edge of 0.4 (0.8 on [-1,1])
    depth = torch.ones(1, 1, 8, 8)
    depth[..., 4:] = 2.0  # a depth edge at the image edge
    batch = {"tgt": img}
    code = EdgeSmoothLoss(on_source=False, factor=10.0, image_range="model")({"depth": depth}, batch)
    paper = EdgeSmoothLoss(on_source=False, factor=1.0, image_range="image")({"depth": depth}, batch)
    # per edge pixel: exp(-10 * 0.8) vs exp(-0.4)
    assert code.item() == pytest.approx(paper.item() * torch.exp(torch.tensor(-8.0 + 0.4)).item(), rel=1e-5)


def test_needs_declare_extras():
    assert DepthConsistencyLoss.needs == {Extras.DEPTH_FROM_TGT}
    assert EdgeSmoothLoss(on_source=True).needs == {Extras.DEPTH_SRC}
    assert EdgeSmoothLoss(on_source=False).needs == frozenset()
    assert WarpLoss.needs == {Extras.WARPED_SRC}
    assert ReconLoss.needs == frozenset()


def test_vgg_loss_has_no_trainable_parameters_and_passes_gradient():
    batch = fixture_batch()
    term = VGGLoss()
    assert not any(p.requires_grad for p in term.parameters())
    pred = batch["src"].clone().requires_grad_(True)
    term({"rgb": pred}, batch).backward()
    assert pred.grad is not None and pred.grad.abs().sum() > 0


def test_negative_weight_is_refused():
    with pytest.raises(ValueError, match="weight"):
        ReconLoss(weight=-1.0)


def test_too_many_scale_weights_are_refused_when_the_module_is_built(tmp_path):
    from nvs.core.errors import UserError
    from nvs.run.build import build_module
    from tests.conftest import compose_train

    cfg = compose_train(["experiment=tatarchenko_chairs", "loss.recon.scale_weights=[1.0,0.5,0.2,0.1]",
                         f"paths.root_dir={tmp_path}"])
    cfg.paths.output_dir = str(tmp_path)
    with pytest.raises(UserError, match=r"loss\.recon\.scale_weights has 4 weights but the model predicts 1 scale"):
        build_module(cfg)


def test_recon_on_a_network_of_unknown_scales_still_refuses_too_few_predictions():
    """A network without ``n_scales`` is not checked at build time; the loss then fails with the build check's line
    rather than drop weights."""
    batch = fixture_batch()
    out = _perfect_outputs(batch)
    out["rgb_scales"] = out["rgb_scales"][-1:]
    loss = ReconLoss(scale_weights=[1.0, 0.5])
    loss.check_network(torch.nn.Identity(), "loss.recon")  # nothing to check against
    with pytest.raises(UserError, match=r"^loss.recon.scale_weights has 2 weights but the model predicts 1 scale"):
        loss(out, batch)


def test_options_are_resolved_at_construction():
    """forward tests no flag: the range, resize, pixel reduction and source term are chosen in __init__."""
    import inspect

    for cls in (VGGLoss, EdgeSmoothLoss, WarpLoss, ReconLoss):
        src = inspect.getsource(cls.forward)
        assert " if " not in src and "image_range" not in src and "masked" not in src, cls.__name__
    assert EdgeSmoothLoss(on_source=False).pairs == (("depth", "tgt"),)
    assert VGGLoss(size=None).resize(torch.zeros(1, 3, 40, 40)).shape[-1] == 40
    assert VGGLoss(size=64).resize(torch.zeros(1, 3, 40, 40)).shape[-1] == 64
