"""``nvs.evaluate time_sizes=[...]`` (nvs.run.size_timing): the option's checks, the batch resized with its camera,
the configuration rebuilt at another size, and the timing record's arithmetic (route mix and speed-up)."""

from __future__ import annotations

import math

import pytest
import torch
from omegaconf import OmegaConf

from nvs.core.errors import UserError
from nvs.core.geometry import project_to_source
from nvs.core.types import ROUTES
from nvs.models.route import RoutedNet
from nvs.models.route_rule import RouteRule
from nvs.run.size_timing import FORCED, config_at, resized_batch, sizes_option, timing_by_size
from tests.conftest import compose_train, fixture_batch


@pytest.mark.parametrize("value, repeats, message", [
    ("256", 5, "time_sizes=256"), ([64, 4], 5, "time_sizes"), ([64, True], 5, "time_sizes"),
    ([64.5], 5, "time_sizes"), ([64], 0, "time_repeats=0"), ([64], "3", "time_repeats=3")])
def test_a_bad_time_sizes_option_is_one_error_naming_the_key(value, repeats, message):
    with pytest.raises(UserError, match=message):
        sizes_option(value, repeats)


def test_sizes_are_sorted_once_each_and_null_is_none():
    assert sizes_option([256, 64, 256], 3) == ([64, 256], 3)
    assert sizes_option(OmegaConf.create([128]), 2) == ([128], 2)
    assert sizes_option(None, 5) == ([], 5)


def test_the_resized_batch_keeps_its_geometry():
    batch = fixture_batch(2, 32)
    big = resized_batch(batch, 64)
    assert big["src"].shape == (2, 3, 64, 64) and big["depth_tgt"].shape[-2:] == (64, 64)
    assert torch.equal(big["T_tgt_src"], batch["T_tgt_src"])
    # the same surface seen at twice the resolution lands at twice the (centre-convention) pixel position
    uv_small, _, _ = project_to_source(batch["depth_tgt"], batch["K"], batch["T_tgt_src"])
    uv_big, _, _ = project_to_source(big["depth_tgt"], big["K"], big["T_tgt_src"])
    # a constant-depth target: the big image's pixel (2i+0.5, 2j+0.5) is the small one's (i, j); compare at the
    # small pixel (i, j) through the affine map u' = 2 (u + 0.5) - 0.5 that the intrinsics follow
    torch.testing.assert_close(2 * (uv_small + 0.5) - 0.5, (uv_big[:, ::2, ::2] + uv_big[:, 1::2, 1::2]) / 2,
                               atol=1e-3, rtol=0)
    assert big["depth_tgt"].unique().tolist() == batch["depth_tgt"].unique().tolist()  # nearest: no new depths


def _module(tmp_path, size: int):
    from nvs.run.build import build_module

    cfg = compose_train([f"paths.root_dir={tmp_path}", "loss=[recon_final]", f"data.size={size}"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    torch.manual_seed(0)
    module = build_module(cfg)
    module.net.eval()
    return module, OmegaConf.create(module.run_config)


def test_another_size_is_the_same_configuration_built_there(tmp_path):
    _, run = _module(tmp_path, 64)
    cfg = config_at(run, 128)
    assert cfg.data.size == 128 and cfg.model.image_size == 128 and run.model.image_size == 64
    assert OmegaConf.to_container(cfg.model.skips) == OmegaConf.to_container(run.model.skips)


def test_the_timing_record_mixes_the_routes_at_the_test_shares(tmp_path):
    module, run = _module(tmp_path, 64)
    module.net = RoutedNet(module.net, RouteRule()).eval()
    shares = {"copy": 0.25, "warp": 0.5, "full": 0.25}
    record = timing_by_size(module, run, fixture_batch(2, 64), [64, 80], 1, "32-true", shares)
    assert sorted(record) == ["64", "80"]
    for entry in record.values():
        routes = entry["routes_ms_per_image"]
        assert sorted(routes) == sorted(ROUTES) and all(v > 0 for v in routes.values())
        assert math.isclose(entry["routed_ms_per_image"], sum(shares[r] * routes[r] for r in ROUTES))
        assert math.isclose(entry["speedup"], entry["network_ms_per_image"] / entry["routed_ms_per_image"])
    assert isinstance(module.net, RoutedNet) and not module.net.training  # the evaluated network is left as it was


def test_without_a_route_only_the_network_is_timed(tmp_path):
    module, run = _module(tmp_path, 64)
    record = timing_by_size(module, run, fixture_batch(2, 64), [64], 1, "32-true", None)
    assert list(record["64"]) == ["network_ms_per_image"] and record["64"]["network_ms_per_image"] > 0


def test_the_forced_rules_send_every_pair_down_their_route(tmp_path):
    module, _ = _module(tmp_path, 64)
    batch = fixture_batch(3, 64)
    with torch.no_grad():
        for index, route in enumerate(ROUTES):
            out = RoutedNet(module.net, FORCED[route])(batch)
            assert out["route"].tolist() == [index] * 3, route


def test_a_size_the_network_cannot_take_is_one_error_naming_the_option(tmp_path):
    module, run = _module(tmp_path, 64)
    with pytest.raises(UserError, match="time_sizes: .* 40x40"):
        timing_by_size(module, run, fixture_batch(2, 64), [40], 1, "32-true", None)


def test_time_sizes_needs_a_checkpoint(tmp_path):
    from nvs.evaluate import evaluate
    from nvs.run.compose import compose

    cfg = compose("evaluate", ["model=copy_source", "data=chairs", f"paths.root_dir={tmp_path}",
                               "time_sizes=[64]"])
    cfg.paths.output_dir = cfg.out_dir = str(tmp_path / "out")
    with pytest.raises(UserError, match="time_sizes"):
        evaluate(cfg, tmp_path / "out")
    assert not (tmp_path / "out" / "metrics.json").exists()
