"""What the bench times: an nvs model option in one execution mode, or the authors' code, on the same batches.

A contender holds three callables on fixed synthetic batches of the data contract: ``train`` (one optimiser step
as training runs it: forward, the critic's update where a term owns one, ``NVSModule.loss``, backward, Adam),
``eval`` (a novel view of the eval batch, as evaluation runs it) and ``throughput`` (a large eval batch).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from nvs.bench.measure import state_bytes
from nvs.bench.reference import Reference
from nvs.core.protocols import HasCritic
from nvs.data.synthetic import synthetic_batch
from nvs.run.compose import compose

MODES = {
    # name: (channels_last, autocast dtype or None, compile)
    "fp32": (False, None, False),
    "cl": (True, None, False),
    "bf16": (False, torch.bfloat16, False),
    "bf16_cl": (True, torch.bfloat16, False),
    # bf16_cl with torch.compile of the whole training step's forward and losses (backward compiled with them by
    # AOTAutograd) and of the eval forward
    "compile": (True, torch.bfloat16, True),
}


@dataclass
class Contender:
    train: Callable[[], object]
    eval: Callable[[], object]
    throughput: Callable[[], object] | None
    params: int
    state: Callable[[], int]  # bytes that persist between steps (parameters, buffers, optimiser state)
    extra: dict[str, Callable[[], object]] = field(default_factory=dict)  # further eval paths (the authors')
    compiled: bool = False
    module: torch.nn.Module | None = None  # the NVSModule (nvs rows), for inspection


@dataclass
class Batches:
    train: dict
    eval: dict
    throughput: dict | None


def make_batches(size: int, train_batch: int, eval_batch: int, throughput_batch: int | None,
                 device: torch.device) -> Batches:
    """Chair-like batches (the objects camera, 20° about the object centre, depth noise in [1.5, 2.5])."""
    def batch(B, seed):
        return synthetic_batch(B, size, "objects", seed=seed, depth=(1.5, 2.5), device=device)

    return Batches(batch(train_batch, 0), batch(eval_batch, 1),
                   batch(throughput_batch, 2) if throughput_batch else None)


def train_config(overrides: list[str], size: int, root_dir: str, channels_last: bool):
    return compose("train", list(overrides) + [f"data.size={size}", f"paths.root_dir={root_dir}",
                                               "paths.output_dir=/tmp", f"channels_last={channels_last}"],
                   resolve=True)


def nvs_contender(overrides: list[str], mode: str, batches: Batches, device: torch.device, root_dir: str,
                  size: int) -> Contender:
    """A model option (train.yaml overrides) in one of MODES."""
    from nvs.run.build import build_module, parameter_count

    channels_last, dtype, compiled = MODES[mode]
    module = build_module(train_config(overrides, size, root_dir, channels_last)).to(device)
    opt = module.configure_optimizers()
    opt = opt["optimizer"] if isinstance(opt, dict) else opt
    critics = [t for t in module.losses.values() if isinstance(t, HasCritic)]

    def autocast():
        return torch.autocast(device.type, dtype=dtype) if dtype else contextlib.nullcontext()

    def forward_loss(batch):
        batch = dict(batch)  # the module puts src and tgt in its memory format, as in training_step, whose
        out = module(batch, module.train_needs)  # losses then read that batch
        for term in critics:  # as training_step: a critic steps on the detached predictions first
            term.update_critic(out, batch)
        return module.loss(out, batch)[0]

    def infer(batch):
        return module(dict(batch))["rgb"]

    if compiled:
        forward_loss, infer = torch.compile(forward_loss), torch.compile(infer)

    def train():
        module.train()
        with autocast():
            total = forward_loss(batches.train)
        total.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)

    def evaluate(batch):
        def run():
            module.eval()
            with torch.no_grad(), autocast():
                infer(batch)
        return run

    return Contender(train=train, eval=evaluate(batches.eval),
                     throughput=evaluate(batches.throughput) if batches.throughput else None,
                     params=parameter_count(module.net), state=lambda: state_bytes([module], [opt]),
                     compiled=compiled, module=module)


def reference_contender(path: str, batches: Batches, device: torch.device) -> Contender:
    """The authors' code: their train.py iteration, their novel view and their eval.py forward (fp32, as it runs)."""
    ref = Reference(path, device)
    train, view = Reference.inputs(batches.train), Reference.inputs(batches.eval)
    thr = Reference.inputs(batches.throughput) if batches.throughput else None
    return Contender(train=lambda: ref.train_step(train), eval=lambda: ref.novel_view(view),
                     throughput=(lambda: ref.novel_view(thr)) if thr else None, params=ref.parameter_count(),
                     state=lambda: state_bytes(ref.networks(), [ref.model.optimizer_G]),
                     extra={"eval_path": lambda: ref.eval_path(view)})
