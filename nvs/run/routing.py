"""``nvs.evaluate route=off|fit|<rule.json>``: the route rule fitted on the validation pairs of a checkpoint, written
and read as a small JSON, and the module's network put behind it (``nvs.models.route``; docs/skipping.md).

The rule file (``route_rule.json``, written into the evaluation's run directory by ``route=fit``):
    kind, version          "nvs-route-rule", 1
    rule                   {copy_pose_px, warp_disocclusion, warp_displacement_px}: a number or null (never)
    tolerance, candidates  the fit's settings (``calibration.*``)
    costs                  {route: cost per pair, in units of the full network's FLOPs}
    checkpoint             {path, weights_sha256}: the checkpoint it was fitted on; loading it for another is refused
    validation             the fit's statistics on the validation pairs (n_pairs, l1_<route>, l1_routed, l1_budget,
                           share_<route>, cost, cost_full)
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch.utils.data import default_collate

from nvs.core.atomic import write_json
from nvs.core.errors import UserError
from nvs.core.protocols import DepthBeforePixels
from nvs.core.weights_digest import KEY, digest
from nvs.data.datamodule import NVSDataModule
from nvs.metrics import per_image as M
from nvs.models.route import RoutedNet, route_costs
from nvs.models.route_rule import FEATURES, RouteRule, fit_rule
from nvs.module.lightning_module import NVSModule
from nvs.run.validation_pass import Calibration, validation_columns

KIND, VERSION = "nvs-route-rule", 1
RULE_FILE = "route_rule.json"
_KEYS = ("kind", "version", "rule", "tolerance", "candidates", "costs", "checkpoint", "validation")


def route_option(value) -> str | None:
    """``route=``: None (off), ``"fit"`` or the path of a rule file; anything else is one UserError."""
    if value is None or value is False or (isinstance(value, str) and value.lower() == "off"):
        return None
    if not isinstance(value, str) or not value:
        raise UserError(f"route={value!r}: expected off, fit or the path of a {RULE_FILE}")
    if value == "fit" or Path(value).is_file():
        return value
    raise UserError(f"route={value}: no such file (expected off, fit or the path of a {RULE_FILE} written by "
                    "route=fit)")


def weights_id(ckpt: dict) -> str:
    """The content hash of a checkpoint's weights (stored when it was written; computed for an older one)."""
    return ckpt.get(KEY) or digest(ckpt["state_dict"])


def routed(module: NVSModule, rule: RouteRule) -> RoutedNet:
    if not isinstance(module.net, DepthBeforePixels):
        raise UserError(f"route: model '{module.model_name}' predicts no depth apart from its pixel decoder, so it "
                        "cannot be routed (route=... takes a checkpoint of model 'nvs')")
    return RoutedNet(module.net, rule)


def _route_table(net: RoutedNet, batch) -> dict[str, torch.Tensor]:
    feats, images = net.all_routes(batch)
    return {**feats, **{f"l1_{route}": M.l1(rgb, batch["tgt"]) for route, rgb in images.items()}}


def fit(module: NVSModule, datamodule: NVSDataModule, ckpt: dict, settings: Calibration, placement: dict,
        precision) -> dict:
    """Fit the rule on the validation pairs (every route of every pair, the full decoder included) -> the rule file's
    payload."""
    net = routed(module, RouteRule())
    # the costs are counted on one validation pair, on the CPU, before the pass moves the network
    costs = route_costs(module.net, default_collate([datamodule.dataset("val")[0]]))
    table = validation_columns(net, datamodule, _route_table, settings, placement, precision)
    try:
        rule, stats = fit_rule({k: table[k] for k in FEATURES},
                               {r: table[f"l1_{r}"] for r in ("copy", "warp", "full")}, costs, settings.tolerance,
                               settings.candidates)
    except ValueError as err:
        raise UserError(f"route=fit with calibration.tolerance={settings.tolerance}: {err}") from None
    if not stats["margin_met"]:
        print(f"route=fit: no rule that routes a pair elsewhere beats the full decoder's validation L1 "
              f"({stats['l1_full']:.5f}) by the margin calibration.tolerance={settings.tolerance:g}; every pair runs "
              "the full decoder", flush=True)
    return {"kind": KIND, "version": VERSION, "rule": rule.as_dict(), "tolerance": settings.tolerance,
            "candidates": settings.candidates, "costs": costs,
            "checkpoint": {"path": str(ckpt.get("path")), "weights_sha256": weights_id(ckpt)}, "validation": stats}


def write_rule(path: str | Path, payload: dict) -> None:
    write_json(path, payload)


def read_rule(path: str | Path, ckpt: dict) -> tuple[RouteRule, dict]:
    """The rule of a rule file, checked: it must be readable JSON of this schema, fitted on ``ckpt``'s weights; every
    problem is one UserError naming the file and the key."""
    try:
        payload = json.loads(Path(path).read_text())
    except OSError as err:
        raise UserError(f"{path}: cannot read the route rule ({err.strerror or err})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise UserError(f"{path}: not a JSON route rule ({err})") from None
    if not isinstance(payload, dict):
        raise UserError(f"{path}: not a route rule (expected a JSON object with {', '.join(_KEYS)})")
    missing = [k for k in _KEYS if k not in payload]
    if missing:
        raise UserError(f"{path}: missing key '{missing[0]}' (a route rule has {', '.join(_KEYS)})")
    if payload["kind"] != KIND or payload["version"] != VERSION:
        raise UserError(f"{path}: kind/version {payload['kind']!r}/{payload['version']!r}: expected {KIND!r}/{VERSION}")
    try:
        rule = RouteRule.from_dict(payload["rule"], f"{path}: rule")
    except ValueError as err:
        raise UserError(str(err)) from None
    fitted = payload["checkpoint"].get("weights_sha256") if isinstance(payload["checkpoint"], dict) else None
    if not isinstance(fitted, str):
        raise UserError(f"{path}: checkpoint.weights_sha256 is missing (the weights the rule was fitted on)")
    if fitted != weights_id(ckpt):
        raise UserError(f"{path}: checkpoint.weights_sha256: the rule was fitted on other weights "
                        f"({payload['checkpoint'].get('path')}), not on {ckpt.get('path')}; fit one with route=fit")
    return rule, payload


def route_record(payload: dict, source: str) -> dict:
    """``metrics.json``'s ``route`` entry: where the rule came from (``fit`` or its file) and the rule file's facts."""
    return {"route": {"source": source, **{k: payload[k] for k in ("rule", "tolerance", "costs", "checkpoint",
                                                                      "validation")}}}
