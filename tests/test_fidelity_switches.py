"""Every fidelity switch (nvs/core/fidelity.py) reaches its component: flipping it alone changes what it should change,
fidelity=corrected flips them all, and an unknown key or value is one clear error."""

from __future__ import annotations

import pytest
import torch

from nvs.core.errors import UserError
from nvs.core.fidelity import SWITCHES
from nvs.run.build import build_module
from tests.conftest import compose_train, fixture_batch

BASE = ["paths.output_dir=/tmp/nvs_switches", "channels_last=false"]


def _other(key: str):
    sw = SWITCHES[key]
    if sw.corrected != sw.code:
        return sw.corrected
    return next(c for c in sw.choices if c != sw.code)


def _value(v) -> str:
    return "null" if v is None else str(v).lower() if isinstance(v, bool) else str(v)


NO_VGG = "loss=[recon,depth_consistency,edge_smooth,warp]"  # VGG at 224^2 is the slow part: only where it is read


def _run(overrides, vgg: bool = False):
    torch.manual_seed(0)
    module = build_module(compose_train(BASE + ([] if vgg else [NO_VGG]) + list(overrides)))
    module.train()
    batch = fixture_batch(B=1)
    torch.manual_seed(1)
    out = module.net(batch, module.train_needs)
    losses = {name: term(out, batch).detach() for name, term in module.losses.items()}
    return module, out, losses


def _largest_change(a, b) -> float:
    (ma, oa, la), (mb, ob, lb) = a, b
    diffs = [(oa["depth"] - ob["depth"]).abs().max()]
    diffs += [(x - y).abs().max() for x, y in zip(oa["rgb_scales"], ob["rgb_scales"])]
    diffs += [(la[k] - lb[k]).abs() for k in la]
    pa, pb = dict(ma.net.named_parameters()), dict(mb.net.named_parameters())
    diffs += [(pa[k] - pb[k]).abs().max() for k in pa if pa[k].shape == pb[k].shape]
    betas = [ma.configure_optimizers().param_groups[0]["betas"], mb.configure_optimizers().param_groups[0]["betas"]]
    diffs.append(torch.tensor(abs(betas[0][0] - betas[1][0])))
    return max(float(d) for d in diffs)


@pytest.fixture(scope="module")
def code_runs():
    return {False: _run([]), True: _run([], vgg=True)}


@pytest.mark.parametrize("key", sorted(SWITCHES))
def test_each_switch_changes_the_model_or_its_losses(code_runs, key):
    vgg = key.startswith("vgg")
    flipped = _run([f"fidelity.{key}={_value(_other(key))}"], vgg=vgg)
    assert _largest_change(code_runs[vgg], flipped) > 1e-6, f"fidelity.{key} changed nothing"


def test_corrected_preset_flips_every_switch_to_its_corrected_value():
    cfg = compose_train(["fidelity=corrected"])
    assert {k: cfg.fidelity[k] for k in SWITCHES} == {k: sw.corrected for k, sw in SWITCHES.items()}
    cfg = compose_train([])
    assert {k: cfg.fidelity[k] for k in SWITCHES} == {k: sw.code for k, sw in SWITCHES.items()}


def test_switches_reach_the_components():
    module = build_module(compose_train(BASE + ["fidelity=corrected"]))
    net = module.net
    assert net.latent_rotation == "exact" and (net.warp_align, net.warp_padding) == ("exact", "zeros")
    assert net.skips.depth_downsample == "area" and net.skips.intrinsics_scaling == "exact"
    assert net.pixel_decoder.side_upsample == "bilinear" and net.depth.norm_batches == "joint"
    assert isinstance(net.pixel_decoder.up8.norm, torch.nn.BatchNorm2d)
    assert net.encoder.conv0[0][0].padding_mode == "reflect"
    losses = module.losses
    assert losses["vgg"].image_range == "image" and losses["vgg"].size is None
    assert losses["edge_smooth"].factor == 1.0 and len(losses["edge_smooth"].pairs) == 1
    assert losses["warp"].masked and losses["recon"].side_upsample == "bilinear"
    assert module.configure_optimizers().param_groups[0]["betas"][0] == 0.9
    # ... as the functions they choose at construction (forward tests no switch)
    from nvs.core import geometry
    from nvs.losses import terms as L

    assert net.skips.downsample is geometry.downsample_depth and net.skips.scale_K is geometry.scale_intrinsics
    assert net.depth.decode_all == net.depth._jointly
    assert losses["vgg"].to_range is L.IMAGE_RANGES["image"] and losses["warp"].reduce is L._valid_mean


@pytest.mark.parametrize("norm_batches, calls", [("separate", [1, 1, 1]), ("joint", [3])])
def test_depth_norm_batches_decodes_the_three_latents_in_one_call_or_three(norm_batches, calls):
    module = build_module(compose_train(BASE + [NO_VGG, f"fidelity.depth_norm_batches={norm_batches}"]))
    seen = []
    module.net.depth.decoder.register_forward_hook(lambda m, args, out: seen.append(out.shape[0]))
    module.net(fixture_batch(B=1), module.train_needs)
    assert seen == calls  # batch sizes: transformed, source and target latents, alone or stacked


@pytest.mark.parametrize("override, message", [
    ("fidelity.latent_rotation=sideways", r"fidelity.latent_rotation='sideways': choose one of \['code', 'exact'\]"),
    ("fidelity.smooth_factor=-1", r"fidelity.smooth_factor=-1: a number >= 0"),
    ("+fidelity.latent_rot=exact", r"fidelity.latent_rot: no such switch"),
])
def test_unknown_values_and_keys_are_one_clear_error(override, message):
    with pytest.raises(UserError, match=message):
        build_module(compose_train(BASE + [override]))
