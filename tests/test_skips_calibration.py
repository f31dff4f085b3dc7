"""The adaptive skips' threshold calibrated on validation pairs (nvs.run.skips_calibration): the pick on a hand-made
table, the per-pair table against the network run at each threshold, and ``nvs.evaluate skips_threshold=...``."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from nvs.core.errors import UserError
from nvs.core.types import to_image_range
from nvs.core.weights_digest import stamp
from nvs.data.synthetic import about_point, rotation, synthetic_batch
from nvs.metrics import per_image as M
from nvs.run.skips_calibration import _columns, pick_threshold, threshold_option
from tests.conftest import compose_train
from tests.viewer_helpers import built_net

# three pairs, two levels. Pair 0 loses nothing when its 0.1 px level is skipped and 0.3 with both; pair 1's levels
# tie at 0.3 (skipped together); pair 2's first level has no bound (never skipped).
BOUNDS = np.array([[0.1, 2.0], [0.3, 0.3], [math.inf, 1.0]])
L1 = np.array([[1.0, 1.0, 1.3], [1.0, 1.0, 1.05], [1.0, 1.02, 1.02]])


@pytest.mark.parametrize("tolerance, threshold, l1", [
    (0.0, 0.3, 1.0),  # below 0.3 only pair 0's first level is skipped, at no cost
    (0.01, 0.3, 1.0),  # 1.0 would skip pair 1's tied levels: mean 3.05 / 3 > 1.01
    (0.02, 1.0, 3.05 / 3),  # 2.0 would skip pair 2's second level as well: 3.07 / 3 > 1.02
    (0.2, np.nextafter(2.0, np.inf), 3.37 / 3),  # just above the largest bound: every finite bound skipped
])
def test_the_largest_threshold_within_the_tolerance_is_picked(tolerance, threshold, l1):
    picked, stats = pick_threshold(BOUNDS, L1, tolerance)
    assert picked == threshold and stats["l1_at_threshold"] == pytest.approx(l1)
    assert stats["l1_at_zero"] == 1.0 and stats["l1_at_threshold"] <= (1 + tolerance) * 1.0 + 1e-12
    skipped = (BOUNDS < picked).sum()
    assert stats["skipped_at_threshold"] == skipped / BOUNDS.size and stats["candidates"] == 6


def test_the_table_is_the_network_run_at_each_pairs_own_thresholds(tmp_path):
    net = built_net(tmp_path, "model/skips=adaptive")
    skips = net.skips
    poses = torch.stack([about_point(rotation("y", d), (0.0, 0.0, 2.0)) for d in (2.0, 15.0)])
    batch = synthetic_batch(2, 64, pose=poses, seed=3)
    with torch.no_grad():
        table = _columns(skips)(net, batch)
    bounds = torch.stack([table[f"bound_{lv}"] for lv in skips.levels], 1)
    assert torch.isfinite(bounds).all() and (bounds > 0).all()
    for i in range(2):
        one = {k: v[i:i + 1] for k, v in batch.items() if torch.is_tensor(v)}
        ordered = bounds[i].sort().values
        for k in range(len(skips.levels) + 1):
            # the scalar threshold just above the k-th smallest bound skips exactly the k smallest-bound levels
            skips.threshold_px = 0.0 if k == 0 else float(np.nextafter(ordered[k - 1].item(), np.inf))
            with torch.no_grad():
                l1 = M.l1(to_image_range(net(one)["rgb_scales"][-1]), one["tgt"])
            assert l1.item() == pytest.approx(table[f"l1_{k}"][i].item(), abs=1e-5), (i, k)
    assert not torch.allclose(table["l1_0"], table[f"l1_{len(skips.levels)}"])  # skipping changes the output


def test_the_threshold_option():
    assert threshold_option(None) is None and threshold_option("calibrate") == "calibrate"
    assert threshold_option(2) == 2.0
    for bad in (-1, "auto", True, math.inf):
        with pytest.raises(UserError, match="skips_threshold="):
            threshold_option(bad)


def test_the_tolerance_may_be_negative_for_a_margin_but_not_minus_one_or_less():
    from nvs.run.validation_pass import Calibration

    assert Calibration.from_config({"tolerance": -0.05}).tolerance == -0.05
    for bad in (-1, -2.0, True, math.nan, "0.01"):
        with pytest.raises(UserError, match="calibration.tolerance="):
            Calibration.from_config({"tolerance": bad})


@pytest.mark.slow
def test_evaluate_calibrates_the_threshold_on_the_validation_pairs(objects_root, tmp_path):
    from nvs.evaluate import evaluate
    from nvs.run.build import build_module
    from nvs.run.compose import compose

    def random_ckpt(*overrides):
        cfg = compose_train([f"paths.root_dir={tmp_path}", f"data.root={objects_root}", "loss=[recon]", *overrides])
        cfg.paths.output_dir = str(tmp_path)
        OmegaConf.resolve(cfg)
        torch.manual_seed(0)
        module = build_module(cfg)
        ckpt = {"state_dict": module.state_dict(), "nvs_config": module.run_config, "global_step": 0}
        stamp(ckpt)
        path = tmp_path / f"{'_'.join(o.replace('/', '-').replace('=', '-') for o in overrides) or 'default'}.ckpt"
        torch.save(ckpt, path)
        return path

    def run(ckpt, *overrides):
        cfg = compose("evaluate", [f"ckpt_path={ckpt}", f"paths.root_dir={tmp_path}", "precision=32-true",
                                   "+trainer.enable_progress_bar=false", *overrides])
        cfg.paths.output_dir = cfg.out_dir = str(tmp_path / "e")
        return evaluate(cfg, tmp_path / "e")

    adaptive = random_ckpt("model/skips=adaptive")
    m = run(adaptive, "skips_threshold=calibrate", "calibration.tolerance=0.02")
    record = m["skips_threshold"]
    assert record["source"] == "calibrate" and record["trained_threshold_px"] == 0.5
    stats = record["validation"]
    assert stats["n_pairs"] > 0 and stats["l1_at_threshold"] <= 1.02 * stats["l1_at_zero"] * (1 + 1e-12)
    assert "warp_skipped" in m["test"]
    given = run(adaptive, "skips_threshold=0")
    assert given["skips_threshold"]["threshold_px"] == 0.0 and given["test"]["warp_skipped"] == 0.0
    assert given["skips_threshold"]["trained_skips"] == "adaptive"
    # The paper's network, trained with warped skips: adaptive ones stand in for them, threshold 0 being the network
    # itself, so the calibration needs no retraining.
    warped = random_ckpt()
    plain = run(warped)
    at_zero = run(warped, "skips_threshold=0")
    assert at_zero["skips_threshold"]["trained_skips"] == "warped"
    assert at_zero["skips_threshold"]["trained_threshold_px"] == 0.0 and at_zero["test"]["warp_skipped"] == 0.0
    assert at_zero["test"]["l1"] == plain["test"]["l1"] and "warp_skipped" not in plain["test"]
    fitted = run(warped, "skips_threshold=calibrate", "calibration.tolerance=0.02")["skips_threshold"]
    assert fitted["trained_skips"] == "warped" and fitted["source"] == "calibrate"
    assert fitted["validation"]["l1_at_threshold"] <= 1.02 * fitted["validation"]["l1_at_zero"] * (1 + 1e-12)
    with pytest.raises(UserError, match="has no warped skips to skip"):
        run(random_ckpt("model/skips=none"), "skips_threshold=calibrate")
    with pytest.raises(UserError, match="calibration.tolerance=-0.05: skips_threshold=calibrate needs"):
        run(adaptive, "skips_threshold=calibrate", "calibration.tolerance=-0.05")
