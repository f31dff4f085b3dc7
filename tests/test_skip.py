"""Skipping what a scene does not need: the warp-displacement bound, adaptive per-level skips, the model/depth
options (predicted, plane, oracle), and that nothing is computed that no output or loss reads."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf
from scipy.spatial.transform import Rotation

from nvs.core.errors import UserError
from nvs.core.geometry import inverse_warp, max_warp_displacement, pose_matrix, project_to_source
from nvs.core.types import Extras
from nvs.models import skips as skips_mod
from nvs.models.depth_decoder import DepthDecoder
from nvs.models.skips import AdaptiveWarpedSkips, PlainSkips, WarpedSkips, level_displacement
from nvs.run.build import build_module
from tests.conftest import CONF_DIR, compose_train, fixture_batch

F64 = torch.float64

EXACT_WARP = dict(align="exact", padding="zeros", depth_downsample="area", intrinsics_scaling="exact")
EXACT = WarpedSkips(**EXACT_WARP)


def _module(tmp_path, *overrides):
    cfg = compose_train([*overrides, f"paths.root_dir={tmp_path}"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    return build_module(cfg)


def _identity(batch: dict) -> dict:
    batch = dict(batch)
    batch["T_tgt_src"] = torch.eye(4).expand_as(batch["T_tgt_src"]).clone()
    return batch


def _true_max_displacement(K, T, d_lo, d_hi, H, W, n_depths=40):
    """Brute force: max |p_s - p_t| over every pixel centre and depths spread in depth and in inverse depth.

    -> (max over points in front of the source camera, whether every point was in front).
    """
    depths = torch.cat([torch.linspace(d_lo, d_hi, n_depths, dtype=F64),
                        1 / torch.linspace(1 / d_hi, 1 / d_lo, n_depths, dtype=F64)])
    v, u = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    uv, _, front = project_to_source(depths.view(-1, 1, 1, 1).expand(-1, 1, H, W), K.expand(len(depths), 3, 3),
                                     T.expand(len(depths), 4, 4))
    disp = torch.hypot(uv[..., 0] - u, uv[..., 1] - v)
    return float(torch.where(front, disp, torch.zeros_like(disp)).max()), bool(front.all())


# -- the displacement bound -----------------------------------------------------------------------------------------
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(size=st.sampled_from([(4, 4), (8, 8), (16, 16), (6, 11), (16, 9)]),
       f_rel=st.floats(0.3, 3.0), aspect=st.floats(0.8, 1.25), c_off=st.tuples(st.floats(-2, 2), st.floats(-2, 2)),
       rotvec=st.tuples(*[st.floats(-0.5, 0.5)] * 3), t=st.tuples(*[st.floats(-0.5, 0.5)] * 3),
       t_scale=st.sampled_from([0.0, 0.01, 0.1, 1.0]), d_lo=st.floats(0.1, 3.0), d_ratio=st.floats(1.0, 20.0))
def test_displacement_bound_is_never_below_the_true_maximum(size, f_rel, aspect, c_off, rotvec, t, t_scale, d_lo,
                                                             d_ratio):
    H, W = size
    f = f_rel * W
    K = torch.tensor([[f, 0, (W - 1) / 2 + c_off[0]], [0, f * aspect, (H - 1) / 2 + c_off[1]], [0, 0, 1]], dtype=F64)
    R = torch.from_numpy(Rotation.from_rotvec(rotvec).as_matrix())
    T = pose_matrix(R[None], torch.tensor(t, dtype=F64)[None] * t_scale)
    d_hi = d_lo * d_ratio
    bound = float(max_warp_displacement(K[None], T, torch.tensor([d_lo], dtype=F64), torch.tensor([d_hi], dtype=F64),
                                       (H, W))[0])
    true_max, all_in_front = _true_max_displacement(K[None], T, d_lo, d_hi, H, W)
    assert bound >= true_max - 1e-9 * max(1.0, true_max), (bound, true_max)
    if not all_in_front:
        assert math.isinf(bound)  # no finite bound when a point of the range can fall behind the source camera


def test_displacement_bound_is_exactly_zero_for_the_identity_and_exact_for_a_sideways_shift():
    K = torch.tensor([[[40.0, 0, 31.625], [0, 40.0, 31.625], [0, 0, 1]]]).expand(3, 3, 3)
    T = torch.eye(4).expand(3, 4, 4).clone()
    lo, hi = torch.tensor([0.1, 1.0, 5.0]), torch.tensor([100.0, 3.0, 5.0])
    assert torch.equal(max_warp_displacement(K, T, lo, hi, (64, 64)), torch.zeros(3, dtype=F64))
    # A translation parallel to the image plane moves every pixel by f |t_x| / depth: the most at the nearest depth.
    T[:, 0, 3] = 0.05
    torch.testing.assert_close(max_warp_displacement(K, T, lo, hi, (64, 64)), 40 * 0.05 / lo.double())


def test_displacement_bound_is_infinite_without_a_usable_depth_range():
    K = torch.tensor([[[10.0, 0, 3.5], [0, 10.0, 3.5], [0, 0, 1]]]).expand(4, 3, 3)
    T = torch.eye(4).expand(4, 4, 4)
    lo = torch.tensor([0.0, float("nan"), 1.0, 1.0])
    hi = torch.tensor([1.0, 1.0, float("inf"), 2.0])
    assert max_warp_displacement(K, T, lo, hi, (8, 8)).tolist() == [math.inf, math.inf, math.inf, 0.0]
    # The depth map's own range: a pixel without data (0) means the warp zeroes it, so the sample must be warped.
    d = torch.full((2, 1, 8, 8), 2.0)
    d[1, 0, 3, 3] = 0.0
    assert level_displacement(d, K[:2], T[:2]).tolist() == [0.0, math.inf]


def test_the_bound_shrinks_with_the_level_resolution_on_a_forward_motion():
    """Driving forward: the coarse levels move by less than a pixel where the full resolution does not."""
    K = torch.tensor([[[40.0, 0, 31.625], [0, 40.0, 31.625], [0, 0, 1]]])
    T = torch.eye(4)[None].clone()
    T[0, 2, 3] = -0.02  # source-camera points come 0.02 closer in the target camera: the camera moved forward
    depth = torch.full((1, 1, 64, 64), 0.5)
    bounds = {}
    for lv, stride in skips_mod.SKIP_STRIDES.items():
        d, Ks = EXACT.at_level(lv, torch.zeros(1, 1, 64 // stride, 64 // stride), depth, K)
        bounds[lv] = float(level_displacement(d, Ks, T)[0])
    assert bounds["conv0"] > 1.0 > 0.5 > bounds["conv4"] > 0
    assert bounds["conv0"] > bounds["conv2"] > bounds["conv3"] > bounds["conv4"]


# -- adaptive skips ---------------------------------------------------------------------------------------------------
def _feats(B=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {lv: torch.rand(B, 4, 64 // s, 64 // s, generator=g) for lv, s in skips_mod.SKIP_STRIDES.items()}


def test_adaptive_skips_with_the_identity_pose_pass_the_features_unwarped_exactly():
    batch = _identity(fixture_batch(B=3))
    feats, depth = _feats(), torch.rand(3, 1, 64, 64, generator=torch.Generator().manual_seed(1)) + 1.5
    adaptive = AdaptiveWarpedSkips(**EXACT_WARP)
    out = adaptive(feats, depth, batch["K"], batch["T_tgt_src"])
    assert all(torch.equal(out[lv], feats[lv]) for lv in adaptive.levels)
    assert adaptive.skip_fractions()["all"] == 1.0
    # ... which is what the exact warp computes, up to the identity warp's round-off: the back-projected and reprojected
    # pixel coordinate (|u| <= 64) carries a few float32 ulps (64 * 2^-23 ~ 8e-6 each), and the features' neighbours
    # differ by up to 1, so the bilinear sample may move by ~1e-5 (1.3e-5 seen over 300 random depths): 1e-4 bounds it.
    warped = WarpedSkips(**EXACT_WARP)(feats, depth, batch["K"], batch["T_tgt_src"])
    assert all(torch.allclose(out[lv], warped[lv], atol=1e-4, rtol=0) for lv in adaptive.levels)


def test_network_with_adaptive_skips_and_identity_pose_equals_the_unwarped_network_exactly(tmp_path):
    torch.manual_seed(0)
    exact = ("fidelity.warp_align=exact", "fidelity.warp_padding=zeros")  # the code's alignment moves even identity
    adaptive = _module(tmp_path, "model/skips=adaptive", *exact).net.eval()
    plain = _module(tmp_path, "model/skips=plain", *exact).net.eval()
    warped = _module(tmp_path, "model/skips=warped", *exact).net.eval()
    plain.load_state_dict(adaptive.state_dict())
    warped.load_state_dict(adaptive.state_dict())
    batch = _identity(fixture_batch(B=2))
    with torch.no_grad():
        out_a, out_p, out_w = adaptive(batch)["rgb"], plain(batch)["rgb"], warped(batch)["rgb"]
    assert torch.equal(out_a, out_p)
    torch.testing.assert_close(out_a, out_w, atol=1e-4, rtol=0)


def test_adaptive_skips_warp_only_the_samples_above_the_threshold():
    """Sample 0 has the identity pose (skipped), sample 1 a rotation (warped): each equals its own computation."""
    batch = fixture_batch(B=2)
    T = batch["T_tgt_src"].clone()
    T[0] = torch.eye(4)
    feats, depth = _feats(B=2), torch.rand(2, 1, 64, 64) + 1.5
    adaptive = AdaptiveWarpedSkips(levels=("conv2", "conv4"))
    out = adaptive(feats, depth, batch["K"], T)
    ref = WarpedSkips(levels=("conv2", "conv4"))(feats, depth, batch["K"], T)
    for lv in ("conv2", "conv4"):
        assert torch.equal(out[lv][0], feats[lv][0])
        torch.testing.assert_close(out[lv][1], ref[lv][1])
        assert not torch.allclose(out[lv][1], feats[lv][1])
    assert adaptive.skipped == {"conv2": 1, "conv4": 1} and adaptive.seen == {"conv2": 2, "conv4": 2}
    assert adaptive.skip_fractions() == {"conv2": 0.5, "conv4": 0.5, "all": 0.5}
    adaptive.reset_counts()
    assert adaptive.skip_fractions() == {}


def test_adaptive_skips_from_warped_ones_keep_their_warp_and_start_at_threshold_zero():
    """What nvs.evaluate skips_threshold=... puts in place of a trained network's warped skips."""
    batch = fixture_batch(B=2)  # a 20 degree rotation
    feats, depth = _feats(B=2), torch.rand(2, 1, 64, 64) + 1.5
    for kwargs in ({}, EXACT_WARP):
        warped = WarpedSkips(levels=("conv0", "conv3"), **kwargs)
        adaptive = AdaptiveWarpedSkips.from_warped(warped)
        assert (adaptive.levels, adaptive.align, adaptive.padding, adaptive.depth_downsample,
                adaptive.intrinsics_scaling) == (warped.levels, warped.align, warped.padding, warped.depth_downsample,
                                                 warped.intrinsics_scaling)
        assert adaptive.threshold_px == 0.0 and adaptive.trained_as == "warped"
        out, ref = adaptive(feats, depth, batch["K"], batch["T_tgt_src"]), warped(feats, depth, batch["K"],
                                                                                  batch["T_tgt_src"])
        assert all(torch.equal(out[lv], ref[lv]) for lv in warped.levels)
        adaptive.threshold_px = math.inf  # every warp skipped
        out = adaptive(feats, depth, batch["K"], batch["T_tgt_src"])
        assert all(torch.equal(out[lv], feats[lv]) for lv in warped.levels)
    assert AdaptiveWarpedSkips().trained_as == "adaptive"


def test_adaptive_skips_gradients_flow_through_warped_and_skipped_samples():
    batch = fixture_batch(B=2)
    T = batch["T_tgt_src"].clone()
    T[0] = torch.eye(4)
    f = torch.rand(2, 4, 16, 16, requires_grad=True)
    depth = (torch.rand(2, 1, 64, 64) + 1.5).requires_grad_()
    out = AdaptiveWarpedSkips(levels=("conv2",))({"conv2": f}, depth, batch["K"], T)["conv2"]
    out.sum().backward()
    assert (f.grad[0] == 1).all()  # skipped: identity
    assert depth.grad[1].abs().sum() > 0 and depth.grad[0].abs().sum() == 0  # only the warped sample uses depth


def test_zero_threshold_warps_everything():
    batch = _identity(fixture_batch(B=2))
    feats, depth = _feats(B=2), torch.rand(2, 1, 64, 64) + 1.5
    out = AdaptiveWarpedSkips(threshold_px=0.0)(feats, depth, batch["K"], batch["T_tgt_src"])
    ref = WarpedSkips()(feats, depth, batch["K"], batch["T_tgt_src"])
    assert all(torch.equal(out[lv], ref[lv]) for lv in ref)


def test_forced_levels_skip_or_warp_every_sample_whatever_the_bounds():
    """What the timing of a study measures: each level skipped alone, the others warped (nvs.sweep.timing)."""
    batch = fixture_batch(B=2)  # a 20 degree rotation: every bound is far above 0
    feats, depth = _feats(B=2), torch.rand(2, 1, 64, 64) + 1.5
    ref = WarpedSkips()(feats, depth, batch["K"], batch["T_tgt_src"])
    adaptive = AdaptiveWarpedSkips(threshold_px=math.inf)  # unforced: every warp skipped
    with adaptive.levels_forced(()):
        out = adaptive(feats, depth, batch["K"], batch["T_tgt_src"])
    assert all(torch.equal(out[lv], ref[lv]) for lv in ref)
    adaptive.threshold_px = 0.0
    with adaptive.levels_forced(adaptive.levels):
        out = adaptive(feats, depth, batch["K"], batch["T_tgt_src"])
    assert all(torch.equal(out[lv], feats[lv]) for lv in adaptive.levels)
    with adaptive.levels_forced(["conv3"]):
        out = adaptive(feats, depth, batch["K"], batch["T_tgt_src"])
    assert torch.equal(out["conv3"], feats["conv3"])
    assert all(torch.equal(out[lv], ref[lv]) for lv in adaptive.levels if lv != "conv3")
    out = adaptive(feats, depth, batch["K"], batch["T_tgt_src"])  # the block left: the threshold decides again
    assert all(torch.equal(out[lv], ref[lv]) for lv in ref)
    with pytest.raises(ValueError, match="conv9"), adaptive.levels_forced(["conv9"]):
        pass


def test_test_summary_reports_the_skipped_fraction_per_level(tmp_path):
    module = _module(tmp_path, "model/skips=adaptive", "loss=[recon]")
    module.eval()
    module.on_test_epoch_start()
    batch = fixture_batch(B=2)  # a 20 degree rotation: nothing can be skipped
    with torch.no_grad():
        module.test_step(_identity(batch), 0)
        module.test_step(batch, 1)
    summary = module.test_summary()
    assert summary["warp_skipped"] == 0.5 and summary["n_pairs"] == 4
    assert all(summary[f"warp_skipped_{lv}"] == 0.5 for lv in ("conv0", "conv2", "conv3", "conv4"))
    module.on_test_epoch_start()  # counts from validation or an earlier test never leak into the next summary
    assert "warp_skipped" not in module.test_summary()


# -- model/depth options --------------------------------------------------------------------------------------------
DEPTH_OPTIONS = sorted(p.stem for p in (Path(CONF_DIR) / "model" / "depth").glob("*.yaml"))


def test_the_depth_options():
    assert DEPTH_OPTIONS == ["oracle", "plane", "predicted"]


@pytest.mark.parametrize("depth", DEPTH_OPTIONS)
@pytest.mark.parametrize("data", ["chairs", "drive"])
def test_every_depth_option_builds_and_trains_one_step(depth, data, tmp_path):
    module = _module(tmp_path, f"data={data}", f"model/depth={depth}")
    params = [p for p in module.net.parameters() if p.requires_grad]
    before = [p.detach().clone() for p in params]
    optimizer = torch.optim.Adam(params, lr=1e-3)
    loss = module.training_step(fixture_batch(), 0)
    loss.backward()
    optimizer.step()
    assert torch.isfinite(loss)
    assert any(not torch.equal(a, p) for a, p in zip(before, params))
    has_decoder = any(isinstance(m, DepthDecoder) for m in module.net.modules())
    assert has_decoder == (depth == "predicted")  # plane and oracle never build (or run) the depth decoder


def test_plane_depth_is_one_plane_per_sample_within_the_head_range(tmp_path):
    net = _module(tmp_path, "model/depth=plane", "data=drive").net.eval()
    with torch.no_grad():
        depth = net(fixture_batch(B=3))["depth"]
    assert depth.shape == (3, 1, 64, 64)
    assert (depth.amax((1, 2, 3)) == depth.amin((1, 2, 3))).all()
    head = net.depth.head
    assert ((depth > head.min_depth) & (depth < head.max_depth)).all()


def test_plane_depth_keeps_depth_consistency_and_chens_baseline_working(tmp_path):
    module = _module(tmp_path, "model/depth=plane", "loss=[recon,depth_consistency]")
    out = module.net(fixture_batch(), module.train_needs)
    assert out[Extras.DEPTH_FROM_TGT].shape == out["depth"].shape
    chen = _module(tmp_path, "model=chen", "model/depth=plane")
    assert torch.isfinite(chen.training_step(fixture_batch(), 0))


def test_oracle_depth_is_the_ground_truth_and_its_constant_losses_are_named_once(tmp_path):
    module = _module(tmp_path, "model/depth=oracle")  # the full loss list
    batch = fixture_batch()
    assert torch.equal(module.net(batch)["depth"], batch["depth_tgt"])
    with pytest.warns(UserWarning, match="depth_consistency, edge_smooth, warp depend on no trainable parameter"):
        module.training_step(batch, 0)


def test_oracle_depth_without_ground_truth_is_one_clear_error(tmp_path):
    net = _module(tmp_path, "model/depth=oracle").net
    batch = fixture_batch()
    del batch["depth_tgt"]
    with pytest.raises(UserError, match="model/depth=oracle reads the ground-truth 'depth_tgt'"):
        net(batch)


# -- compute only what is used --------------------------------------------------------------------------------------
def _count_calls(module: torch.nn.Module) -> list[int]:
    calls = [0]
    module.register_forward_hook(lambda *_: calls.__setitem__(0, calls[0] + 1))
    return calls


@pytest.mark.parametrize("depth", ["predicted", "plane"])
def test_target_is_encoded_only_when_depth_consistency_is_on(depth, tmp_path):
    full = _module(tmp_path, f"model/depth={depth}")
    calls = _count_calls(full.net.encoder)
    full.training_step(fixture_batch(), 0)
    assert calls[0] == 2  # source, and target for depth consistency
    without = _module(tmp_path, f"model/depth={depth}", "loss=[recon,vgg,edge_smooth,warp]")
    calls = _count_calls(without.net.encoder)
    without.training_step(fixture_batch(), 0)
    assert calls[0] == 1


@pytest.mark.parametrize("model,scales", [("nvs", "[1.0,0.5,0.2,0.1]"), ("chen", "[1.0]")])
def test_evaluation_encodes_once_and_computes_no_loss_extras(model, scales, tmp_path):
    module = _module(tmp_path, f"model={model}", "loss=[recon,depth_consistency,edge_smooth,warp]",
                     f"loss.recon.scale_weights={scales}")  # chen predicts one scale: checked at build time
    module.eval()
    calls = _count_calls(module.net.encoder)
    batch = fixture_batch()
    with torch.no_grad():
        out = module(batch)
        module.validation_step(batch, 0)
        module.on_test_epoch_start()
        module.test_step(batch, 0)
    assert calls[0] == 3
    assert not {Extras.DEPTH_FROM_TGT, Extras.DEPTH_SRC, Extras.WARPED_SRC, "warp_valid"} & set(out)


def test_skip_levels_that_are_off_are_neither_warped_nor_decoded(tmp_path, monkeypatch):
    warped = []

    def counting_warp(src, *args):
        warped.append(tuple(src.shape[-2:]))
        return real_warp(src, *args)

    real_warp = skips_mod.warp
    monkeypatch.setattr(skips_mod, "warp", counting_warp)
    net = _module(tmp_path, "model/skips=wo_conv0", "loss=[recon]").net
    with torch.no_grad():
        net(fixture_batch())
    assert warped == [(16, 16), (8, 8), (4, 4)]  # conv2, conv3, conv4; never conv0's full resolution
    assert net.pixel_decoder.fuse1[0].in_channels == 32 + 3  # no input channels for conv0


def test_every_encoder_stage_is_on_the_path_to_the_latent(tmp_path):
    """No encoder computation exists only for a skip level, so switching a level off leaves nothing to drop there
    (if a skip-only head is ever added, it must be built only for the levels that are on)."""
    enc = _module(tmp_path, "model/skips=none", "loss=[recon]").net.encoder
    z, _ = enc(torch.rand(2, 3, 64, 64) * 2 - 1)
    z.sum().backward()
    unused = [n for n, p in enc.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not unused


def test_plain_skips_need_no_depth_for_the_skips():
    assert not PlainSkips.needs_depth and AdaptiveWarpedSkips.needs_depth


# -- a short real run -----------------------------------------------------------------------------------------------
def test_short_run_reports_step_time_and_skipped_warps(objects_root, tmp_path):
    from tests.run_helpers import train_in_process

    steps = 7  # the step-time median leaves out the first 5 steps
    m = train_in_process(objects_root, tmp_path, f"trainer.max_steps={steps}", "trainer.val_check_interval=7",
                         "data.loader.batch_size=2", "loss=[recon,depth_consistency]", "model/skips=adaptive",
                         "model/depth=plane")
    assert m["steps"] == steps and 0 < m["train_step_ms"] < 1000 * m["train_wall_s"]
    # The fixture's test pairs turn by 20 degrees: every warp moves pixels by more than 0.5 px, nothing is skipped.
    assert m["test"]["warp_skipped"] == 0.0 and m["test"]["warp_skipped_conv4"] == 0.0
