"""The skipping ``nvs.evaluate`` applies at inference to a trained network (docs/skipping.md): the adaptive skips'
threshold (``skips_threshold``) first, then the route (``route``), whose rule is then fitted on the network the
test runs."""

from __future__ import annotations

from nvs.data.datamodule import NVSDataModule
from nvs.models.route_rule import RouteRule
from nvs.module.lightning_module import NVSModule
from nvs.run.routing import fit, read_rule, route_record, routed
from nvs.run.skips_calibration import calibrate, set_threshold
from nvs.run.validation_pass import Calibration


def skip_at_inference(module: NVSModule, datamodule: NVSDataModule, ckpt: dict | None, route: str | None,
                      threshold: str | float | None, settings: Calibration, placement: dict,
                      precision) -> tuple[dict, dict | None]:
    """Apply ``skips_threshold`` (None: as trained; ``calibrate``; px) and ``route`` (None: off; ``fit``; a rule
    file) to ``module`` -> (the entries they add to metrics.json, the payload of a rule fitted here or None)."""
    extra: dict = {}
    if threshold is not None:
        extra["skips_threshold"] = (calibrate(module, datamodule, settings, placement, precision)
                                    if threshold == "calibrate" else set_threshold(module, threshold))
    if not route:
        return extra, None
    fitted = fit(module, datamodule, ckpt, settings, placement, precision) if route == "fit" else None
    if fitted is not None:
        rule, payload = RouteRule.from_dict(fitted["rule"], "the fitted rule"), fitted
    else:
        rule, payload = read_rule(route, ckpt)
    module.net = routed(module, rule)
    return {**extra, **route_record(payload, route)}, fitted
