"""Report section 4: Adam steps with anomaly detection on adversarial batches, counting non-finite steps."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from nvs.stress.batches import batch_family
from nvs.stress.harness import all_finite, quiet
from nvs.stress.options import other_models, train_config


@dataclass
class StressRun:
    """What a stress training run saw: losses per step and the first non-finite event."""

    losses: list[float] = field(default_factory=list)
    nonfinite_loss: int = 0
    nonfinite_grad: int = 0
    nonfinite_param: int = 0
    error: str = ""


def train_under_stress(module, batches: Callable[[int], dict], steps: int, lr: float = 1e-3,
                       autocast: torch.dtype | None = None) -> StressRun:
    """Adam steps on ``batches(step)`` with anomaly detection (and CPU autocast to ``autocast`` if given); counts steps
    with a non-finite loss, gradient or weight."""
    opt = torch.optim.Adam([p for p in module.parameters() if p.requires_grad], lr=lr)
    run = StressRun()
    module.train()
    for step in range(steps):
        batch = batches(step)
        opt.zero_grad(set_to_none=True)
        amp = torch.autocast("cpu", dtype=autocast) if autocast else contextlib.nullcontext()
        try:
            with torch.autograd.set_detect_anomaly(True), quiet():
                with amp:
                    out = module(batch, module.train_needs)
                    loss, _ = module.loss(out, batch)
                loss.backward()
        except RuntimeError as err:  # anomaly detection names the backward op that produced NaN
            run.error = f"step {step}: {str(err).splitlines()[0][:150]}"
            break
        value = float(loss.detach())
        run.losses.append(value)
        run.nonfinite_loss += not math.isfinite(value)
        run.nonfinite_grad += not all_finite(*(p.grad for p in module.parameters() if p.grad is not None))
        opt.step()
        run.nonfinite_param += not all_finite(*module.parameters())
    return run


def stress_configs(steps: int) -> list[tuple[str, list[str], str, int, torch.dtype | None]]:
    """(label, overrides, batch family, steps per batch kind, autocast dtype) of the modules trained under stress.

    The paper's model gets ``steps`` per kind (half under bf16 autocast), its one-kind families three times that, the
    baselines a third.
    """
    no_vgg = "loss=[recon,depth_consistency,edge_smooth,warp]"
    return [
        ("nvs (depth 1..3)", ["model=nvs", no_vgg], "all", steps, None),
        ("nvs under bf16 autocast (depth 1..3)", ["model=nvs", no_vgg], "all", max(1, steps // 2), torch.bfloat16),
        ("nvs + vgg (depth 1..3)", ["model=nvs"], "constant", steps, None),
        ("nvs, tiny depth range 1e-4..2e-4", ["model=nvs", no_vgg, "data.depth_head.min_depth=1e-4",
                                              "data.depth_head.max_depth=2e-4"], "tiny", 3 * steps, None),
        ("nvs, huge depth range 1e-4..1e4 (disparity)", ["experiment=nvs_drive", no_vgg,
                                                         "data.depth_head.max_disparity=1e4",
                                                         "data.depth_head.min_disparity=1e-4"], "huge", 3 * steps,
         None),
    ] + [(name, ov, "all", max(1, steps // 3), None) for name, ov in other_models()]


def training_section(work: str, steps_per_kind: int) -> tuple[list[list], int]:
    """(rows, total steps) of every stress config across its batch family."""
    from nvs.run.build import build_module

    rows, total = [], 0
    for label, overrides, family, n, autocast in stress_configs(steps_per_kind):
        try:
            torch.manual_seed(0)
            module = build_module(train_config(overrides, work))
        except Exception as err:  # noqa: BLE001
            rows.append([label, "-", 0, "-", "-", "-", "-", f"does not build: {err.__class__.__name__}: {err}"[:160]])
            continue
        for kind, batches in batch_family(family):
            run = train_under_stress(module, batches, n, autocast=autocast)
            total += len(run.losses)
            finite_losses = [v for v in run.losses if math.isfinite(v)]
            span = f"{run.losses[0]:.3g} → {run.losses[-1]:.3g}" if run.losses else "-"
            rows.append([label, kind, len(run.losses), span,
                         f"{max(finite_losses):.3g}" if finite_losses else "-",
                         run.nonfinite_loss, f"{run.nonfinite_grad} / {run.nonfinite_param}", run.error])
    return rows, total
