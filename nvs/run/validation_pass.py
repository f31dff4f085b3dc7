"""What the inference-time fits (``nvs.run.routing``, ``nvs.run.skips_calibration``) share: their settings
(``calibration`` in conf/evaluate.yaml) and one pass over the validation pairs that returns per-pair columns."""

from __future__ import annotations

import math
from dataclasses import dataclass

import lightning as L
import numpy as np
import torch
import torch.nn as nn
from torch.utils.data import DataLoader, Subset

from nvs.core.errors import UserError
from nvs.data.datamodule import NVSDataModule
from nvs.module.pair_pass import Columns, PairPass


@dataclass(frozen=True)
class Calibration:
    """``calibration.*``: the L1 margin a fit may spend, the validation pairs it reads, the thresholds it tries."""

    tolerance: float = 0.01  # mean validation L1 at most (1 + tolerance) x the reference's (< 0: routes only)
    val_pairs: int | None = None  # the first N validation pairs (None: all)
    candidates: int = 32  # thresholds tried per feature by the route fit

    @classmethod
    def from_config(cls, node) -> Calibration:
        node = dict(node or {})
        unknown = sorted(set(node) - {"tolerance", "val_pairs", "candidates"})
        if unknown:
            raise UserError(f"calibration.{unknown[0]}: no such key (calibration takes tolerance, val_pairs, "
                            "candidates)")
        out = cls(**node)
        t = out.tolerance
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t <= -1:
            raise UserError(f"calibration.tolerance={t!r}: expected a number > -1 (0.01: 1% more L1 allowed; "
                            "-0.05: the route rule must be 5% better than the full decoder)")
        for key in ("val_pairs", "candidates"):
            v = getattr(out, key)
            if (v is not None or key == "candidates") and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise UserError(f"calibration.{key}={v!r}: expected a positive integer"
                                + (" or null (all)" if key == "val_pairs" else ""))
        return out


def validation_columns(net: nn.Module, datamodule: NVSDataModule, columns: Columns, settings: Calibration,
                       placement: dict, precision) -> dict[str, np.ndarray]:
    """``columns(net, batch)`` over the validation pairs (the first ``settings.val_pairs``), concatenated: {name: (n,)}.

    One device of the evaluation's accelerator, at its precision; the validation split is the training run's own
    (never the test pairs)."""
    if str(placement.get("devices", 1)) != "1" or str(placement.get("num_nodes", 1)) != "1":
        raise UserError("route=fit / skips_threshold=calibrate fit on one device: run them with trainer.devices=1, "
                        "then evaluate on several with route=<its route_rule.json> / skips_threshold=<px>")
    datamodule.validate(("val",))
    dataset = datamodule.dataset("val")
    n = len(dataset) if settings.val_pairs is None else min(len(dataset), settings.val_pairs)
    if n == 0:
        raise UserError("the validation split has no pairs to fit on (data.loader.val_fraction, val_pairs_per_model)")
    loader = DataLoader(Subset(dataset, range(n)), batch_size=datamodule.loader.eval_batch_size, shuffle=False,
                        num_workers=datamodule.loader.num_workers)
    trainer = L.Trainer(accelerator=placement.get("accelerator", "auto"), devices=1, precision=precision,
                        logger=False, enable_progress_bar=False, enable_model_summary=False)
    parts = trainer.predict(PairPass(net, columns), dataloaders=loader)
    return {k: torch.cat([p[k] for p in parts]).numpy() for k in parts[0]}
