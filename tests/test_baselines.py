"""Baselines: build from their experiment configs, honour the output contract, train, and fail clearly on bad losses."""

import json
import math
import subprocess
import sys
from pathlib import Path

import hydra
import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from nvs.core.errors import UserError
from nvs.core.geometry import inverse_warp, pose_matrix
from nvs.core.types import RGB_BRANCHES, Extras
from nvs.models.baselines.chen import warp_border
from nvs.models.baselines.common import halvings, pose_code
from nvs.models.baselines.sun import Sun
from nvs.models.baselines.tatarchenko import Tatarchenko
from nvs.run.build import build_module
from tests.conftest import compose_train, fixture_batch
from tests.run_helpers import cli_in_process

REPO = Path(__file__).resolve().parents[1]
BASELINES = ["tatarchenko", "chen", "sun"]
# Learning rates that fit a few steps; Sun et al.'s net has no norm layers and diverges at 1e-3 (theirs: 1e-4).
FAST_LR = {"tatarchenko": 1e-3, "chen": 1e-3, "sun": 3e-4}


def _module(name: str, tmp_path, *overrides, data: str = "chairs"):
    cfg = compose_train([f"experiment={name}_{data}", f"paths.root_dir={tmp_path}", *overrides])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    return build_module(cfg)


def _view_pair(B: int = 2, S: int = 64) -> dict:
    """A batch whose target really is the source seen from the fixture pose (a plane at depth 2.5, white elsewhere)."""
    batch = fixture_batch(B, S)
    g = torch.Generator().manual_seed(1)
    src = F.interpolate(torch.rand(B, 3, 8, 8, generator=g), size=(S, S), mode="bilinear", align_corners=False)
    depth = torch.full((B, 1, S, S), 2.5)
    warped, valid = inverse_warp(src, depth, batch["K"], batch["T_tgt_src"])
    batch.update(src=src, tgt=warped * valid + (1 - valid), depth_tgt=depth)
    return batch


def _train(module, batch, steps: int) -> list[float]:
    torch.manual_seed(0)
    opt = module.configure_optimizers()
    losses = []
    for i in range(steps):
        opt.zero_grad()
        loss = module.training_step(batch, i)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return losses


# -- config -> module -> forward/backward --------------------------------------------------------------------------
@pytest.mark.parametrize("name", BASELINES)
def test_builds_from_experiment_and_runs_forward_backward(name, tmp_path):
    module = _module(name, tmp_path)
    assert module.model_name == name
    batch = fixture_batch()
    out = module(batch, module.train_needs)
    assert out["rgb"].shape == (2, 3, 64, 64) and 0 <= out["rgb"].min() and out["rgb"].max() <= 1
    assert out["rgb_scales"][-1].shape == (2, 3, 64, 64)
    assert torch.allclose(out["rgb_scales"][-1], out["rgb"] * 2 - 1, atol=1e-6)
    loss = module.training_step(batch, 0)
    loss.backward()
    grads = {n: p.grad for n, p in module.net.named_parameters()}
    assert torch.isfinite(loss)
    assert all(g is not None and torch.isfinite(g).all() for g in grads.values()), \
        [n for n, g in grads.items() if g is None]


@pytest.mark.parametrize("name", BASELINES)
def test_scene_experiment_runs_on_a_scene_batch(name, tmp_path):
    module = _module(name, tmp_path, data="drive")
    batch = fixture_batch()
    batch["pivot"] = torch.zeros(2, 3)  # scenes: the camera moves (forward and a little to the side)
    batch["T_tgt_src"] = pose_matrix(torch.eye(3).expand(2, 3, 3), torch.tensor([[0.01, 0.0, -0.05]]).expand(2, 3))
    loss = module.training_step(batch, 0)
    loss.backward()
    assert torch.isfinite(loss)
    if name == "chen":  # the scenes' disparity head: depth within (1/(a+b), 1/b)
        depth = module(batch)["depth"]
        assert (depth > 1 / 10.01).all() and (depth < 100).all()


def test_chen_outputs_depth_and_the_extras_of_the_full_model(tmp_path):
    module = _module("chen", tmp_path)
    out = module(fixture_batch(), frozenset({Extras.DEPTH_FROM_TGT, Extras.DEPTH_SRC, Extras.WARPED_SRC}))
    for key in ("depth", Extras.DEPTH_FROM_TGT, Extras.DEPTH_SRC):
        assert out[key].shape == (2, 1, 64, 64) and (out[key] > 1).all() and (out[key] < 3).all()  # objects' head
    assert torch.equal(out[Extras.WARPED_SRC], out["rgb"]) and out["warp_valid"].shape == (2, 1, 64, 64)
    # The full model's loss list runs on Chen too (it has every extra those terms read).
    full = _module("chen", tmp_path, "loss=[recon,depth_consistency,edge_smooth,warp]", "loss.recon.scale_weights=[1.0]")
    assert torch.isfinite(full.training_step(fixture_batch(), 0))


@pytest.mark.parametrize("name,size", [("tatarchenko", 80), ("tatarchenko", 128), ("sun", 96), ("sun", 128),
                                       ("chen", 128)])
def test_other_image_sizes(name, size, tmp_path):
    module = _module(name, tmp_path, f"data.size={size}")
    out = module(fixture_batch(B=1, S=size))
    assert out["rgb"].shape == (1, 3, size, size)


def test_halvings_stop_between_4_and_odd_sizes():
    assert [halvings(s) for s in (64, 80, 96, 128, 256)] == [4, 4, 4, 5, 6]
    with pytest.raises(ValueError, match="multiple of 16"):
        halvings(72)


# -- unsupported losses: one clear message --------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["tatarchenko", "sun"])
def test_depth_losses_on_models_without_depth_are_one_clear_error(name, tmp_path):
    # An extra the model cannot compute is found when the module is built, before any step.
    with pytest.raises(UserError, match=f"model '{name}' cannot provide 'depth_from_tgt' that an enabled loss reads"):
        _module(name, tmp_path, "loss=[recon,depth_consistency]", "loss.recon.scale_weights=[1.0]")
    # A term that reads a plain output (edge smoothness on the target only reads 'depth'), not an extra.
    module = _module(name, tmp_path, "loss=[recon,edge_smooth]", "loss.recon.scale_weights=[1.0]",
                     "loss.edge_smooth.on_source=false")
    with pytest.raises(UserError, match=f"model '{name}' does not output 'depth'"):
        module.training_step(fixture_batch(), 0)


def test_branch_loss_on_a_model_without_branches_is_one_clear_error(tmp_path):
    with pytest.raises(UserError, match=f"cannot provide '{RGB_BRANCHES}'.*extras this model provides: none"):
        _module("tatarchenko", tmp_path, "loss=[recon,branches]")


def test_the_needs_check_runs_at_build_time_not_in_forward(tmp_path):
    """The baselines' forward no longer checks ``needs``: the built module's losses only ask for what it provides."""
    module = _module("chen", tmp_path, "loss=[recon,depth_consistency,edge_smooth,warp]",
                     "loss.recon.scale_weights=[1.0]")
    assert module.train_needs <= module.net.provides
    out = _module("tatarchenko", tmp_path).net(fixture_batch(), frozenset({"depth_from_tgt"}))
    assert "depth_from_tgt" not in out  # asked for directly, an extra it lacks is simply absent


def test_missing_output_reads_like_a_dict(tmp_path):
    out = _module("tatarchenko", tmp_path).net(fixture_batch())
    assert out.get("depth") is None and "depth" not in out
    with pytest.raises(KeyError):
        out["depth"]


# -- what each baseline computes ---------------------------------------------------------------------------------
def test_pose_code_is_the_relative_pose_about_the_pivot():
    batch = fixture_batch(B=1)
    code = pose_code(batch["T_tgt_src"], batch["pivot"])
    R = batch["T_tgt_src"][0, :3, :3]
    # An object orbit about its centre is [R|0] about the pivot, whatever the camera distance.
    assert torch.allclose(code[0].view(3, 4)[:, :3], R) and torch.allclose(code[0].view(3, 4)[:, 3], torch.zeros(3),
                                                                             atol=1e-6)
    # Scenes (pivot 0): the camera motion itself.
    T = pose_matrix(torch.eye(3)[None], torch.tensor([[0.1, -0.2, 0.3]]))
    assert torch.allclose(pose_code(T, torch.zeros(1, 3)), torch.tensor([[1, 0, 0, 0.1, 0, 1, 0, -0.2, 0, 0, 1, 0.3]]))


def test_tatarchenko_output_depends_on_the_pose():
    torch.manual_seed(0)
    net = Tatarchenko(64).eval()
    batch = fixture_batch(B=1)
    a = net(batch)["rgb"]
    batch["T_tgt_src"] = torch.eye(4)[None]
    assert not torch.allclose(a, net(batch)["rgb"])


def test_chen_warp_matches_inverse_warp_inside_and_replicates_the_border():
    batch = fixture_batch(B=1)
    src, K, T = batch["src"], batch["K"], batch["T_tgt_src"]
    depth = torch.full((1, 1, 64, 64), 2.5)
    ours, valid = warp_border(src, depth, K, T)
    ref, ref_valid = inverse_warp(src, depth, K, T)
    assert torch.equal(valid, ref_valid) and 0 < valid.mean() < 1
    assert torch.allclose(ours * valid, ref * valid, atol=1e-6)
    # Outside the source image: the nearest border pixel, so a flat-coloured border stays that colour (white renders).
    white = torch.ones_like(src)
    out, _ = warp_border(white, depth, K, T)
    assert torch.allclose(out, white, atol=1e-6)
    # Identity pose: an identity warp whatever the depth.
    same, same_valid = warp_border(src, depth, K, torch.eye(4)[None])
    assert torch.allclose(same, src, atol=1e-5) and same_valid.all()


def test_chen_is_their_auto_encoder():
    from nvs.models.baselines.chen import Chen, ChenDecoder, ChenEncoder
    from nvs.models.depth_head import BoundedDepth

    enc, dec = ChenEncoder(256), ChenDecoder(256)
    convs = [m for m in enc.convs if isinstance(m, torch.nn.Conv2d)]
    assert [c.out_channels for c in convs] == [64, 128, 256, 256, 256, 256, 256, 256]
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in enc.modules()) == 6  # none after the first and the last
    ups = [m for m in dec.ups if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d))]
    assert [type(m).__name__ for m in ups[:3]] == ["ConvTranspose2d", "ConvTranspose2d", "Conv2d"]
    assert [m.out_channels for m in ups] == [256, 256, 256, 256, 256, 128, 64, 32, 1]
    assert sum(isinstance(m, torch.nn.ReflectionPad2d) for m in dec.modules()) == 6
    # Smaller images drop stages; the widths of the finest stages stay theirs.
    assert [m.out_channels for m in ChenDecoder(64).ups if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d))] \
        == [256, 256, 256, 128, 64, 32, 1]
    with pytest.raises(ValueError, match="power of two"):
        ChenEncoder(96)
    torch.manual_seed(0)
    net = Chen(64, BoundedDepth())
    w = torch.cat([m.weight.flatten() for m in net.modules() if isinstance(m, torch.nn.Conv2d)])
    assert abs(w.std().item() - 0.02) < 0.002  # their init_weights('normal', 0.02)


def test_chen_latent_rotation_code_is_the_transpose_of_exact():
    from nvs.models.baselines.chen import transform_points

    batch = fixture_batch(B=1)
    z = torch.randn(1, 5, 3)
    code = transform_points(z, batch["T_tgt_src"], batch["pivot"], "code")
    exact = transform_points(z, batch["T_tgt_src"], batch["pivot"], "exact")
    R = batch["T_tgt_src"][0, :3, :3]
    assert torch.allclose(exact[0], z[0] @ R.T, atol=1e-6) and torch.allclose(code[0], z[0] @ R, atol=1e-6)
    assert not torch.allclose(code, exact, atol=1e-3)


def test_sun_trains_its_two_modules_with_their_own_adam_settings(tmp_path):
    module = _module("sun", tmp_path)
    flow, pixel = module.configure_optimizers().param_groups
    assert (flow["lr"], flow["betas"]) == (1e-4, (0.9, 0.999)) and (pixel["lr"], pixel["betas"]) == (5e-5, (0.5, 0.999))
    ids = [id(p) for g in (flow, pixel) for p in g["params"]]
    assert len(ids) == len(set(ids)) and set(ids) == {id(p) for p in module.net.parameters()}
    assert {id(p) for p in module.net.pixel_decoder.parameters()} <= {id(p) for p in pixel["params"]}


def test_sun_zero_flow_copies_the_source_and_the_blend_is_the_confidence_softmax():
    torch.manual_seed(0)
    net = Sun(64)
    last = net.flow_decoder.out[-1]  # the linear conv to (flow x, flow y, confidence)
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    batch = fixture_batch()
    out = net(batch)
    assert torch.allclose(out[RGB_BRANCHES]["flow"], batch["src"], atol=1e-5)
    w = out["confidence"]
    assert w.shape == (2, 2, 64, 64) and torch.allclose(w.sum(1), torch.ones(2, 64, 64), atol=1e-6)
    blend = w[:, :1] * out[RGB_BRANCHES]["flow"] + w[:, 1:] * out[RGB_BRANCHES]["pixel"]
    assert torch.allclose(out["rgb"], blend, atol=1e-6)


def test_sun_flow_is_in_their_units_and_their_layers_are_there():
    from nvs.models.baselines.sun import coordinate_channels, sample_flow

    # A flow of 2/W moves the sampling point by one pixel (their sampler reads pixel j at (x + 1) W / 2).
    src = torch.arange(8.0).view(1, 1, 1, 8).expand(1, 1, 8, 8).contiguous()
    flow = torch.zeros(1, 2, 8, 8)
    flow[:, 0] = 2.0 / 8
    moved = sample_flow(src, flow, "border")
    assert torch.allclose(moved[..., :-1], src[..., 1:]) and torch.allclose(moved[..., -1], src[..., -1])
    assert sample_flow(src, flow, "zeros")[..., -1].abs().max() < 0.51  # half a pixel of zeros blended in
    # Coordinates: pixel j at 2j/W - 1 (x) and 2i/H - 1 (y), as their add_image_coord.
    c = coordinate_channels(1, 4, 8, src)
    assert torch.allclose(c[0, 0, 0], torch.arange(8.0) / 4 - 1) and torch.allclose(c[0, 1, :, 0], torch.arange(4.0) / 2 - 1)
    net = Sun(64)
    assert [m[0].out_channels for m in net.flow_encoder.convs] == [32, 64, 128, 256, 512]
    assert len(net.flow_decoder.res) == 4 and len(net.pixel_decoder.res) == 0
    assert [len(s) for s in net.pixel_encoder.lstm] == [2, 2, 2] and len(net.flow_encoder.lstm) == 0
    assert [st[-2].out_channels for st in net.pixel_decoder.ups] == [256, 128, 64, 32, 16]
    # The pixel decoder reads the encoder at every stage after the bottleneck; the flow decoder never does.
    assert net.pixel_decoder.skip_at == [False, True, True, True, True] and not any(net.flow_decoder.skip_at)
    assert not any(isinstance(m, (torch.nn.BatchNorm2d, torch.nn.InstanceNorm2d)) for m in net.modules())
    with pytest.raises(ValueError, match="divisible by 2\\^n_layers"):
        Sun(80)


# -- training ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", BASELINES)
def test_loss_falls_in_a_few_steps(name, tmp_path):
    losses = _train(_module(name, tmp_path, f"optim.lr={FAST_LR[name]}"), _view_pair(), 8)
    assert all(math.isfinite(v) for v in losses)
    assert min(losses[-3:]) < 0.9 * losses[0], losses


@pytest.mark.slow
@pytest.mark.parametrize("name", BASELINES)
def test_overfits_one_batch(name, tmp_path):
    losses = _train(_module(name, tmp_path, f"optim.lr={FAST_LR[name]}"), _view_pair(), 50)
    assert min(losses[-5:]) < 0.6 * losses[0], losses[::5]


@pytest.mark.slow
@pytest.mark.parametrize("name", BASELINES)
def test_short_run_through_train_entry_point(name, objects_root, tmp_path):
    cmd = [sys.executable, "-m", "nvs.train", f"experiment={name}_chairs", f"data.root={objects_root}",
           f"paths.log_dir={tmp_path}", "trainer.enable_progress_bar=false", "trainer.max_steps=2",
           "trainer.val_check_interval=2", "data.loader.batch_size=2"]
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    m = json.loads(next(tmp_path.rglob("metrics.json")).read_text())
    assert m["model"] == name and m["params"] > 1_000_000 and m["test"]["n_pairs"] == 4
    assert ("depth_l1" in m["test"]) == (name == "chen")


def test_unsupported_loss_through_train_entry_point_is_one_line(objects_root, tmp_path, monkeypatch):
    argv = ["experiment=tatarchenko_chairs", "loss=[recon,warp]", f"data.root={objects_root}",
            f"paths.log_dir={tmp_path}", "trainer.enable_progress_bar=false", "trainer.max_steps=1",
            "data.loader.batch_size=2", "test=false"]
    code, err = cli_in_process("train", argv, monkeypatch)
    assert code == 2, err[-3000:]
    assert "model 'tatarchenko' cannot provide 'warped_src'" in err and "Traceback" not in err


def test_ground_truth_warp_treats_missing_depth_as_the_data_says():
    """Objects: no depth = background, filled white. Scenes: no depth = sky, warped as far away (kept, not white)."""
    from nvs.models.reference import GroundTruthWarp

    g = torch.Generator().manual_seed(0)
    src = torch.rand(1, 3, 16, 16, generator=g) * 0.5
    depth = torch.full((1, 1, 16, 16), 2.0)
    depth[..., :6, :] = 0.0  # top rows: no ground truth
    K = torch.tensor([[[20.0, 0.0, 7.5], [0.0, 20.0, 7.5], [0.0, 0.0, 1.0]]])
    batch = {"src": src, "depth_tgt": depth, "K": K, "T_tgt_src": torch.eye(4)[None]}
    objects = GroundTruthWarp()(batch)["rgb"]
    assert torch.all(objects[..., :6, :] == 1.0)
    torch.testing.assert_close(objects[..., 6:, :], src[..., 6:, :], atol=1e-5, rtol=0)
    scenes = GroundTruthWarp(sky_disparity=0.01)(batch)["rgb"]
    torch.testing.assert_close(scenes, src, atol=1e-5, rtol=0)
    # a small sideways step: near pixels shift by f*t/z = 20*0.1/2 = 1 px, the far sky by 0.02 px
    T = torch.eye(4)[None]
    T[0, 0, 3] = 0.1
    moved = GroundTruthWarp(sky_disparity=0.01)({**batch, "T_tgt_src": T})["rgb"]
    assert (moved[..., :6, 2:-2] - src[..., :6, 2:-2]).abs().max() < 0.02


@pytest.mark.parametrize("data,sky_depth", [("chairs", None), ("cars", None), ("drive", 100.0), ("drive_wide", 100.0),
                                            ("kitti", 100.0)])
def test_ground_truth_warp_reads_the_sky_from_the_data_config_not_its_name(data, sky_depth, tmp_path):
    """The model is told no dataset kind: scenes' sky sits at their disparity head's far limit, objects have none."""
    from nvs.models.reference import GroundTruthWarp
    from nvs.run.compose import compose

    cfg = compose("evaluate", ["model=gt_warp", f"data={data}", f"paths.root_dir={tmp_path}"])
    cfg.paths.output_dir = str(tmp_path)
    node = OmegaConf.to_container(cfg.model, resolve=True)
    assert "data_format" not in node
    net = hydra.utils.instantiate({k: v for k, v in node.items() if k != "name"})
    assert isinstance(net, GroundTruthWarp) and net.sky_depth == sky_depth
