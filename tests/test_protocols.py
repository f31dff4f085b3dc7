"""The protocols of nvs.core.protocols: the networks and loss terms of nvs implement them, and nvs asks them instead
of probing attributes by name."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from nvs.core.protocols import (CountsSkips, EncodeOnce, HasCritic, ListsExtras, LossTermLike, MultiScale, Network,
                                ParamGroups)
from nvs.models.skips import AdaptiveWarpedSkips, NoSkips, WarpedSkips
from tests.conftest import compose_train

REPO = Path(__file__).resolve().parents[1]
PROTOCOL_MEMBERS = {"n_scales", "provides", "param_groups", "encode", "render", "skip_fractions", "reset_counts",
                    "update_critic", "check_network", "needs"}


def _net(model: str):
    cfg = compose_train([f"model={model}", "data.size=64"])
    node = OmegaConf.to_container(cfg.model, resolve=True)  # the build's way: resolved against the whole config
    return instantiate({k: v for k, v in node.items() if k != "name"}, _convert_="all"), cfg


@pytest.mark.parametrize("model, capabilities", [
    ("nvs", {MultiScale, EncodeOnce}),
    ("tatarchenko", {MultiScale, ListsExtras}),
    ("chen", {MultiScale, ListsExtras}),
    ("sun", {MultiScale, ListsExtras, ParamGroups}),
])
def test_each_network_implements_the_protocols_it_claims(model, capabilities):
    net, _ = _net(model)
    assert isinstance(net, Network)
    everything = {MultiScale, ListsExtras, ParamGroups, EncodeOnce}
    assert {p for p in everything if isinstance(net, p)} == capabilities


def test_the_loss_terms_are_loss_terms_and_only_the_adversarial_one_has_a_critic():
    cfg = compose_train(["model=sun", "data.size=64"])
    terms = {name: instantiate(OmegaConf.to_container(term, resolve=True)) for name, term in cfg.loss.items()}
    assert terms and all(isinstance(t, LossTermLike) for t in terms.values())
    assert {n for n, t in terms.items() if isinstance(t, HasCritic)} == {n for n in terms if "adv" in n}


def test_only_the_adaptive_skips_count_what_they_skip():
    assert issubclass(AdaptiveWarpedSkips, CountsSkips)
    assert not issubclass(WarpedSkips, CountsSkips) and not issubclass(NoSkips, CountsSkips)


def test_the_extending_example_implements_network_and_multiscale():
    sys.path.insert(0, str(REPO / "docs" / "extending"))
    try:
        from mynvs.net import WarpRefine
    finally:
        sys.path.pop(0)
    net = WarpRefine(image_size=32)
    assert isinstance(net, Network) and isinstance(net, MultiScale) and not isinstance(net, EncodeOnce)


def test_nvs_asks_protocols_not_attribute_probes():
    # hasattr(x, "n_scales") / getattr(x, "provides", None) and the like: the question the protocols answer
    probes = []
    for path in sorted((REPO / "nvs").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("hasattr", "getattr")
                    and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
                    and node.args[1].value in PROTOCOL_MEMBERS):
                probes.append(f"{path.relative_to(REPO)}:{node.lineno} {node.func.id}(..., {node.args[1].value!r})")
    assert not probes, "\n".join(probes)
