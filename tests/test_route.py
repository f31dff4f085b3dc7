"""Routing at inference (nvs.models.route, nvs.run.routing): the features on constructed cases, that only the pairs
routed ``full`` run the pixel decoder, the fit against the tolerance and an exhaustive search, the rule file and its
bad forms, the viewer's switch, and ``nvs.evaluate route=...`` end to end on the fixture data."""

from __future__ import annotations

import itertools
import json
import math
from unittest import mock

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from nvs.core.errors import UserError
from nvs.core.geometry import pose_matrix
from nvs.core.types import ROUTES
from nvs.core.weights_digest import KEY, stamp
from nvs.data.synthetic import about_point, rotation, synthetic_batch
from nvs.models.route import RoutedNet, pose_bound, route_costs, warp_source
from nvs.models.route_rule import RouteRule, fit_rule
from nvs.run.routing import read_rule, route_option, write_rule
from tests.conftest import compose_train
from tests.viewer_helpers import built_net

S, F = 64, 120.0  # the fixture objects camera at 64^2: f = 480 * 64 / 256
COPY, WARP, FULL = range(3)


def _translation(tx: float) -> torch.Tensor:
    """T_tgt_src (4,4): the target camera sees every point shifted by tx along x."""
    return pose_matrix(torch.eye(3)[None], torch.tensor([[tx, 0.0, 0.0]]))[0]


def _yaws(*degrees: float) -> torch.Tensor:
    return torch.stack([about_point(rotation("y", d), (0.0, 0.0, 2.0)) for d in degrees])


# -- the features on constructed cases ---------------------------------------------------------------------------------
def test_identity_pose_is_zero_displacement_and_the_copy_route_is_the_source_exactly(tmp_path):
    net = built_net(tmp_path)
    batch = synthetic_batch(2, S, pose=torch.eye(4))
    with torch.no_grad():
        out = RoutedNet(net, RouteRule(copy_pose_px=0.0))(batch)
    assert out["route"].tolist() == [COPY, COPY]
    assert torch.equal(out["rgb"], batch["src"]) and torch.equal(out["route_features"]["pose_px"], torch.zeros(2))
    assert torch.isnan(out["depth"]).all() and torch.isnan(out["route_features"]["disocclusion"]).all()
    # the warp by any depth under the identity pose moves nothing and hides nothing
    warped, f = warp_source(batch["src"], torch.rand(2, 1, S, S) + 1.5, batch["K"], batch["T_tgt_src"])
    torch.testing.assert_close(warped, batch["src"], atol=1e-5, rtol=0)
    assert f["disp_max_px"].abs().max() < 1e-4 and torch.equal(f["disocclusion"], torch.zeros(2))


def test_a_sideways_translation_moves_every_pixel_by_f_t_over_d():
    # depth 2, t_x = 0.05: u_src = u - f t_x / d = u - 3 px; the 3 leftmost target columns land outside the source
    batch = synthetic_batch(1, S, images="blobs", pose=_translation(0.05))
    warped, f = warp_source(batch["src"], torch.full((1, 1, S, S), 2.0), batch["K"], batch["T_tgt_src"])
    assert f["disp_mean_px"].item() == pytest.approx(3.0, abs=1e-4)
    assert f["disp_max_px"].item() == pytest.approx(3.0, abs=1e-4)
    assert f["disocclusion"].item() == pytest.approx(3 / S)
    torch.testing.assert_close(warped[..., 3:], batch["src"][..., :-3], atol=1e-5, rtol=0)
    torch.testing.assert_close(warped[..., :3], batch["src"][..., :3])  # disoccluded: the source pixel there
    # the pose alone bounds it over the depth head's range (1, 3): f t_x / 1, exactly for a sideways shift
    assert pose_bound(batch["K"], batch["T_tgt_src"], (1.0, 3.0), (S, S)).item() == pytest.approx(F * 0.05)
    assert math.isinf(pose_bound(batch["K"], batch["T_tgt_src"], None, (S, S)).item())


def test_target_pixels_hidden_behind_a_nearer_surface_count_as_disoccluded():
    # background at depth 4 (moves 3 px), a square at depth 1 (moves 12 px) in rows/columns 20..29: the background
    # target pixels of those rows in columns 11..19 land on the source pixels the square covers, behind it
    batch = synthetic_batch(1, S, pose=_translation(0.1))
    depth = torch.full((1, 1, S, S), 4.0)
    depth[..., 20:30, 20:30] = 1.0
    _, f = warp_source(batch["src"], depth, batch["K"], batch["T_tgt_src"])
    outside, occluded = 3 * S, 10 * 9
    assert f["disocclusion"].item() == pytest.approx((outside + occluded) / S**2)
    # the same depth and pose without the square hide nothing: the count above is the z-buffer's
    _, flat = warp_source(batch["src"], torch.full_like(depth, 4.0), batch["K"], batch["T_tgt_src"])
    assert flat["disocclusion"].item() == pytest.approx(outside / S**2)


def test_the_routed_network_reads_the_predicted_depth(tmp_path):
    # model/depth=oracle predicts the ground truth (depth 2): a 0.05 sideways shift is 3 px on every pixel
    net = built_net(tmp_path, "model/depth=oracle")
    batch = synthetic_batch(2, S, pose=_translation(0.05), depth=2.0)
    with torch.no_grad():
        out = RoutedNet(net, RouteRule(None, 1.0, 3.5))(batch)
    f = out["route_features"]
    assert out["route"].tolist() == [WARP, WARP] and torch.equal(out["depth"], batch["depth_tgt"])
    torch.testing.assert_close(f["disp_mean_px"], torch.full((2,), 3.0), atol=1e-4, rtol=0)
    assert torch.isinf(f["pose_px"]).all()  # no depth head, no range: the pose alone bounds nothing, nothing copied


# -- only what a route needs runs --------------------------------------------------------------------------------------
def _count_calls(module: torch.nn.Module) -> list[int]:
    sizes: list[int] = []
    module.register_forward_hook(lambda m, args, out: sizes.append(args[0].shape[0]))
    return sizes


def test_only_the_pairs_routed_full_run_the_pixel_decoder(tmp_path):
    net = built_net(tmp_path)
    batch = synthetic_batch(4, S, pose=_yaws(0.0, 3.0, 30.0, 30.0), seed=1)
    router = RoutedNet(net, RouteRule())
    with torch.no_grad():
        feats, images = router.all_routes(batch)
        reference = net(batch)["rgb"]
    disp = feats["disp_mean_px"]
    assert disp[1] < disp[2] and disp[1] < disp[3], disp  # the 3 degree turn moves less than the 30 degree ones
    # between the small turn's displacement and the large ones' (the subset's depth may differ in the last bit)
    router.rule = RouteRule(0.0, 1.0, float(disp[1] + disp[2:].min()) / 2)
    decoder, encoder = _count_calls(net.pixel_decoder), _count_calls(net.encoder)
    with torch.no_grad():
        out = router(batch)
    assert out["route"].tolist() == [COPY, WARP, FULL, FULL]
    assert decoder == [2] and encoder == [3]  # the full pairs only; every pair but the copied one
    assert torch.equal(out["rgb"][0], batch["src"][0])
    torch.testing.assert_close(out["rgb"][1], images["warp"][1])
    torch.testing.assert_close(out["rgb"][2:], reference[2:], atol=1e-5, rtol=0)
    for k, v in feats.items():
        torch.testing.assert_close(out["route_features"][k][1:], v[1:].float())
    decoder.clear(), encoder.clear()
    router.rule = RouteRule(copy_pose_px=1e9)
    with torch.no_grad():
        assert router(batch)["route"].tolist() == [COPY] * 4
    assert decoder == [] and encoder == []
    # a rule that never warps (the all-full fit of a margin no rule meets) skips the warp: the network's own output
    router.rule = RouteRule()
    with torch.no_grad(), mock.patch("nvs.models.route.warp_source", side_effect=AssertionError("warped")):
        out = router(batch)
    assert out["route"].tolist() == [FULL] * 4 and torch.isnan(out["route_features"]["disocclusion"]).all()
    torch.testing.assert_close(out["rgb"], reference, atol=1e-5, rtol=0)


def test_costs_are_counted_flops_with_copy_free_and_full_whole(tmp_path):
    costs = route_costs(built_net(tmp_path), synthetic_batch(2, S))
    assert costs["copy"] == 0.0 and costs["full"] == 1.0 and 0.2 < costs["warp"] < 0.9


# -- the fit -----------------------------------------------------------------------------------------------------------
COSTS = {"copy": 0.0, "warp": 0.5, "full": 1.0}
# six pairs: copying is good for small motions, warping for small disocclusions, the full decoder 0.3 everywhere
TABLE = ({"pose_px": np.array([0.0, 1, 5, 10, 20, 40]), "disocclusion": np.array([0.0, 0, 0.01, 0.02, 0.2, 0.5]),
          "disp_mean_px": np.array([0.0, 0.5, 2, 4, 8, 16])},
         {"copy": np.array([0.0, 0.1, 0.5, 1, 2, 4]), "warp": np.array([0.05, 0.1, 0.2, 0.3, 1.2, 2]),
          "full": np.full(6, 0.3)})


def test_the_fit_finds_the_cheapest_rule_within_the_tolerance_on_a_hand_made_table():
    rule, stats = fit_rule(*TABLE, COSTS, tolerance=0.0)
    # copy pairs 0-2, warp pair 3, full 4-5: L1 1.5 <= 6 x 0.3, cost 2.5; copying pair 3 as well would cost L1 2.2
    assert rule == RouteRule(5.0, 0.02, 4.0)
    assert stats["l1_routed"] == pytest.approx(1.5 / 6) and stats["cost"] == pytest.approx(2.5 / 6)
    assert (stats["share_copy"], stats["share_warp"], stats["share_full"]) == pytest.approx((0.5, 1 / 6, 1 / 3))
    # budget 2.7: copy pairs 0-3 (L1 2.2, cost 2); warping 3 and 4 instead of copying 3 costs as much for L1 2.4
    rule, stats = fit_rule(*TABLE, COSTS, tolerance=0.5)
    assert rule == RouteRule(10.0, None, None) and stats["cost"] == pytest.approx(2 / 6)
    # nothing cheaper is good enough: all full, every threshold "never"
    worse = {"copy": np.full(6, 9.0), "warp": np.full(6, 9.0), "full": np.full(6, 0.3)}
    assert fit_rule(TABLE[0], worse, COSTS, tolerance=0.01)[0] == RouteRule()
    # a negative tolerance asks for a margin below the full decoder: L1 1.5 = (1 - 1/6) x 1.8 is still reached
    rule, stats = fit_rule(*TABLE, COSTS, tolerance=-1 / 6)
    assert rule == RouteRule(5.0, 0.02, 4.0) and stats["l1_budget"] == pytest.approx(1.5 / 6)
    assert stats["margin_met"] is True


def test_a_margin_no_rule_meets_keeps_the_full_decoder_on_every_pair():
    # the best any rule can do here is L1 1.2 (each pair's best route): half the full decoder's 1.8 is out of reach
    rule, stats = fit_rule(*TABLE, COSTS, tolerance=-0.5)
    assert rule == RouteRule() and stats["margin_met"] is False
    assert stats["share_full"] == 1.0 and stats["l1_routed"] == pytest.approx(0.3)
    assert stats["cost"] == pytest.approx(COSTS["full"]) and stats["l1_budget"] == pytest.approx(0.15)
    assert fit_rule(*TABLE, COSTS, tolerance=0.0)[1]["margin_met"] is True


def _exhaustive(features, l1, costs, tolerance):
    """The least cost over every threshold triple of observed values (and never): what the fit must reach."""
    pose, disocc, disp = features["pose_px"], features["disocclusion"], features["disp_mean_px"]
    table = np.stack([l1[r] for r in ROUTES])
    values = [np.concatenate([[-np.inf], np.unique(x)]) for x in (pose, disocc, disp)]
    best = math.inf
    for a, b, c in itertools.product(*values):
        routes = RouteRule(*(None if np.isneginf(x) else x for x in (a, b, c))).routes(pose, disocc, disp)
        if table[routes, np.arange(len(pose))].sum() <= (1 + tolerance) * table[2].sum() * (1 + 1e-12):
            best = min(best, float(np.asarray([costs[r] for r in ROUTES])[routes].mean()))
    return best


@pytest.mark.parametrize("seed, tolerance", [(0, 0.0), (1, 0.01), (2, 0.05), (3, 0.2)])
def test_the_fit_obeys_the_tolerance_and_matches_an_exhaustive_search(seed, tolerance):
    rng = np.random.default_rng(seed)
    n = 9
    features = {"pose_px": rng.uniform(0, 10, n), "disocclusion": rng.uniform(0, 0.3, n),
                "disp_mean_px": rng.uniform(0, 5, n)}
    # copying hurts with the motion, warping with the disocclusion: both sometimes beat the full decoder
    l1 = {"copy": 0.05 * features["pose_px"] + rng.uniform(0, 0.1, n),
          "warp": 0.1 + features["disocclusion"] + rng.uniform(0, 0.1, n), "full": 0.2 + rng.uniform(0, 0.1, n)}
    rule, stats = fit_rule(features, l1, COSTS, tolerance, candidates=n)
    routes = rule.routes(features["pose_px"], features["disocclusion"], features["disp_mean_px"])
    routed = np.stack([l1[r] for r in ROUTES])[routes, np.arange(n)].mean()
    assert routed == pytest.approx(stats["l1_routed"])
    assert routed <= (1 + tolerance) * l1["full"].mean() * (1 + 1e-12)
    assert stats["cost"] == pytest.approx(_exhaustive(features, l1, COSTS, tolerance))
    assert fit_rule(features, l1, COSTS, tolerance, candidates=n) == (rule, stats)  # deterministic


def test_the_fit_refuses_what_it_cannot_fit():
    with pytest.raises(ValueError, match="tolerance=-1"):
        fit_rule(*TABLE, COSTS, tolerance=-1)
    with pytest.raises(ValueError, match="same positive number of pairs"):
        fit_rule({**TABLE[0], "pose_px": np.zeros(5)}, TABLE[1], COSTS, 0.01)
    with pytest.raises(ValueError, match="non-finite"):
        fit_rule(TABLE[0], {**TABLE[1], "full": np.full(6, np.nan)}, COSTS, 0.01)


# -- the rule file -----------------------------------------------------------------------------------------------------
CKPT = {KEY: "ab" * 32, "path": "runs/x/checkpoints/last.ckpt"}


def _payload(**changes) -> dict:
    payload = {"kind": "nvs-route-rule", "version": 1, "rule": RouteRule(5.0, 0.02, 4.0).as_dict(),
               "tolerance": 0.01, "candidates": 32, "costs": COSTS,
               "checkpoint": {"path": CKPT["path"], "weights_sha256": CKPT[KEY]}, "validation": {"n_pairs": 6}}
    payload.update(changes)
    return payload


def test_the_rule_file_round_trips(tmp_path):
    path = tmp_path / "route_rule.json"
    write_rule(path, _payload())
    rule, payload = read_rule(path, CKPT)
    assert rule == RouteRule(5.0, 0.02, 4.0) and payload == json.loads(path.read_text())
    assert route_option(str(path)) == str(path) and route_option("fit") == "fit"
    assert route_option("off") is None and route_option(False) is None and route_option(None) is None


@pytest.mark.parametrize("content, message", [
    ("{not json", "not a JSON route rule"),
    ("[1, 2]", "not a route rule (expected a JSON object"),
    (_payload(rule={"copy_pose_px": 1.0, "warp_disocclusion": None}), "rule: missing key 'warp_displacement_px'"),
    (_payload(rule={**_payload()["rule"], "copy_px": 1.0}), "rule: unknown key 'copy_px'"),
    (_payload(rule={**_payload()["rule"], "copy_pose_px": "small"}), "rule.copy_pose_px: 'small' is not a finite"),
    (_payload(kind="something else"), "kind/version 'something else'/1: expected 'nvs-route-rule'/1"),
    ({k: v for k, v in _payload().items() if k != "costs"}, "missing key 'costs'"),
    (_payload(checkpoint={"path": "a.ckpt"}), "checkpoint.weights_sha256 is missing"),
    (_payload(checkpoint={"path": "other.ckpt", "weights_sha256": "cd" * 32}),
     "checkpoint.weights_sha256: the rule was fitted on other weights (other.ckpt), not on runs/x/checkpoints/last"),
])
def test_a_bad_rule_file_is_one_error_naming_the_file_and_key(tmp_path, content, message):
    path = tmp_path / "rule.json"
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    with pytest.raises(UserError) as err:
        read_rule(path, CKPT)
    assert str(err.value).startswith(f"{path}: ") and message in str(err.value), str(err.value)


def test_a_route_option_that_is_no_file_is_one_error(tmp_path):
    with pytest.raises(UserError, match=r"route=.*nope.json: no such file \(expected off, fit or the path"):
        route_option(str(tmp_path / "nope.json"))


# -- the viewer's switch -----------------------------------------------------------------------------------------------
def test_the_viewer_routes_a_view_when_asked_and_names_the_route(tmp_path):
    from nvs.viewer.controls import ObjectControls
    from nvs.viewer.server import view_json
    from nvs.viewer.session import Source, ViewSession

    net = built_net(tmp_path)
    batch = synthetic_batch(1, S)
    image = (batch["src"][0] * 255).to(torch.uint8)
    gallery = [Source("g0", "m_0_0", image, {"azimuth": 0.0, "elevation": 0.0})]
    session = ViewSession(net, S, batch["K"][0], batch["pivot"][0], ObjectControls(40, (0.0, 0.0, 2.0)), gallery,
                          None, router=RoutedNet(net, RouteRule(copy_pose_px=1e-3)))
    same = session.view("g0", {"azimuth": 0.0, "elevation": 0.0}, route=True)  # the source's own pose: copied
    assert same.route == "copy" and same.depth is None and np.array_equal(same.rgb, image.permute(1, 2, 0).numpy())
    moved = session.view("g0", {"azimuth": 20.0, "elevation": 0.0}, route=True)
    plain = session.view("g0", {"azimuth": 20.0, "elevation": 0.0})
    assert moved.route == "full" and plain.route is None and session.encoder_runs == 1
    assert np.abs(moved.rgb.astype(int) - plain.rgb.astype(int)).max() <= 1  # full is the network's own view
    answer = view_json(session, "g0", {"azimuth": 0.0, "elevation": 0.0}, True)
    assert answer["route"] == "copy" and answer["route_features"]["disocclusion"] is None
    json.dumps(answer, allow_nan=False)  # what the page receives is plain JSON
    session.router = None
    with pytest.raises(UserError, match="routing is off: start the viewer with route="):
        session.view("g0", {"azimuth": 0.0, "elevation": 0.0}, route=True)


# -- nvs.evaluate route=... --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def random_ckpt(tmp_path_factory, objects_root):
    """A randomly initialised full model on the fixture objects, saved as a checkpoint (nothing trained)."""
    from nvs.run.build import build_module

    tmp = tmp_path_factory.mktemp("route_ckpt")
    cfg = compose_train([f"paths.root_dir={tmp}", f"data.root={objects_root}", "loss=[recon]"])
    cfg.paths.output_dir = str(tmp)
    OmegaConf.resolve(cfg)
    torch.manual_seed(0)
    module = build_module(cfg)
    ckpt = {"state_dict": module.state_dict(), "nvs_config": module.run_config, "global_step": 0}
    stamp(ckpt)
    torch.save(ckpt, tmp / "model.ckpt")
    return tmp / "model.ckpt"


def _evaluate(tmp_path, ckpt, *overrides):
    from nvs.evaluate import evaluate
    from nvs.run.compose import compose

    out = tmp_path / "_".join(o.split("=")[0].strip("+") for o in overrides) if overrides else tmp_path / "plain"
    cfg = compose("evaluate", [f"ckpt_path={ckpt}", f"paths.root_dir={tmp_path}", "precision=32-true",
                               "+trainer.enable_progress_bar=false", *overrides])
    cfg.paths.output_dir = cfg.out_dir = str(out)
    return evaluate(cfg, out), out


@pytest.mark.slow
def test_evaluate_fits_writes_and_reloads_the_rule_and_reports_the_routes(random_ckpt, tmp_path):
    import pandas as pd

    from nvs.run.artifacts import summary_line

    plain, _ = _evaluate(tmp_path, random_ckpt)
    assert "route" not in plain and not any(k.startswith("route_") for k in plain["test"])  # off: as before
    fitted, out = _evaluate(tmp_path, random_ckpt, "route=fit", "calibration.tolerance=0.05")
    rule_file = out / "route_rule.json"
    payload = json.loads(rule_file.read_text())
    assert payload["checkpoint"]["path"] == str(random_ckpt) and payload["tolerance"] == 0.05
    val = payload["validation"]
    assert val["n_pairs"] > 0 and val["l1_routed"] <= (1 + 0.05) * val["l1_full"] * (1 + 1e-12)
    test = fitted["test"]
    assert sum(test[f"route_share_{r}"] for r in ROUTES) == pytest.approx(1.0)
    assert fitted["route"]["source"] == "fit" and fitted["route"]["rule"] == payload["rule"]
    rows = pd.read_csv(out / "test_per_image.csv")
    assert set(rows["route"]) <= set(ROUTES) and len(rows) == test["n_pairs"] == plain["test"]["n_pairs"]
    for r in ROUTES:
        mine = rows[rows["route"] == r]
        assert test[f"route_share_{r}"] == pytest.approx(len(mine) / len(rows))
        assert (test[f"route_l1_{r}"] is None) == mine.empty
    assert summary_line(test).startswith("test: l1=")
    # a rule that routes every pair full is the network's own evaluation, pair for pair
    all_full = tmp_path / "all_full.json"
    all_full.write_text(json.dumps({**payload, "rule": RouteRule().as_dict()}))
    full, out_full = _evaluate(tmp_path, random_ckpt, f"route={all_full}", "limit=3")
    assert full["test"]["route_share_full"] == 1.0 and full["test"]["route_l1_copy"] is None
    np.testing.assert_allclose(pd.read_csv(out_full / "test_per_image.csv")["l1"],
                               pd.read_csv(tmp_path / "plain" / "test_per_image.csv")["l1"][:3], atol=1e-5)
    # the written rule, loaded, routes the same pairs the same way
    again, out2 = _evaluate(tmp_path, random_ckpt, f"route={rule_file}")
    assert again["route"]["source"] == str(rule_file) and not (out2 / "route_rule.json").exists()
    assert list(pd.read_csv(out2 / "test_per_image.csv")["route"]) == list(rows["route"])
    # a rule for other weights, and routing without a trained network, are refused
    other = tmp_path / "other.json"
    other.write_text(json.dumps({**payload, "checkpoint": {"path": "b.ckpt", "weights_sha256": "0" * 64}}))
    with pytest.raises(UserError, match="fitted on other weights"):
        _evaluate(tmp_path, random_ckpt, f"route={other}")
    with pytest.raises(UserError, match="route=bogus: no such file"):
        _evaluate(tmp_path, random_ckpt, "route=bogus")


def test_the_viewer_offers_the_switch_for_a_rule_of_its_checkpoint(random_ckpt, tmp_path):
    from nvs.run.compose import compose
    from nvs.viewer.build import build_session

    rule = tmp_path / "route_rule.json"
    sha = torch.load(random_ckpt, weights_only=False)[KEY]
    write_rule(rule, _payload(checkpoint={"path": str(random_ckpt), "weights_sha256": sha}))
    cfg = compose("viewer", [f"ckpt_path={random_ckpt}", f"route={rule}", "gallery=1", f"paths.root_dir={tmp_path}",
                             "precision=32-true"])
    cfg.paths.output_dir = str(tmp_path)
    session, meta = build_session(cfg)
    assert meta["route"]["rule"] == RouteRule(5.0, 0.02, 4.0).as_dict() and session.router.rule.copy_pose_px == 5.0
    first = next(iter(session.gallery.values()))
    assert session.view(first.key, session.controls.initial(first.meta), route=True).route in ROUTES
    write_rule(rule, _payload())  # fitted on other weights
    with pytest.raises(UserError, match="fitted on other weights"):
        build_session(cfg)


def test_the_new_evaluate_keys_leave_committed_evaluations_current(tmp_path):
    from nvs.run.compose import compose
    from nvs.sweep.jobs import config_changes

    new = OmegaConf.to_container(compose("evaluate", ["model=copy_source", "data=chairs"]), resolve=False)
    old = {k: v for k, v in new.items()
           if k not in ("route", "skips_threshold", "calibration", "time_sizes", "time_repeats")}
    assert config_changes(old, new) == [] and new["route"] == "off" and new["skips_threshold"] is None
    assert new["time_sizes"] is None
