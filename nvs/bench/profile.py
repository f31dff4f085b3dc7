"""A torch.profiler profile of one model option's training step: top operators by self time, copies and casts summed.

Copies are classified by the operator that asked for them (the profiler's parent chain of each ``aten::copy_``):
dtype/layout conversions (``aten::to`` / ``_to_copy``: autocast's casts, channels_last conversions), clones and
``contiguous``, and the rest (in-place copies such as ``index_put_`` or optimiser updates).
"""

from __future__ import annotations

import torch
from torch.profiler import ProfilerActivity, profile

from nvs.bench.contenders import make_batches, nvs_contender
from nvs.provenance import markdown as provenance_markdown

_CONVERSIONS = ("aten::to", "aten::_to_copy", "aten::to_dtype", "aten::_autocast_to_reduced_precision",
                "aten::_autocast_to_full_precision")
_CLONES = ("aten::clone", "aten::contiguous")


def _copy_kind(evt) -> str:
    parent = evt.cpu_parent
    while parent is not None:
        if parent.name in _CONVERSIONS:
            return "dtype/layout conversions (aten::to, _to_copy: autocast casts, memory-format changes)"
        if parent.name in _CLONES:
            return "clones and contiguous"
        parent = parent.cpu_parent
    return "other copy_ (in place)"


def profile_step(overrides: list[str], mode: str, size: int, batch: int, device: torch.device, root_dir: str,
                 warmup: int = 2, steps: int = 3) -> dict:
    """-> {"ops": [(name, self ms/step, calls/step)], "copies": {kind: ms/step}, "total_ms": ms/step, ...}."""
    contender = nvs_contender(overrides, mode, make_batches(size, batch, 1, None, device), device, root_dir, size)
    for _ in range(warmup):
        contender.train()
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        for _ in range(steps):
            contender.train()
    events = prof.events()
    ops: dict[str, list[float]] = {}
    copies: dict[str, float] = {}
    for evt in events:
        ms = evt.self_cpu_time_total / 1000 / steps
        entry = ops.setdefault(evt.name, [0.0, 0])
        entry[0] += ms
        entry[1] += 1 / steps
        if evt.name == "aten::copy_":
            kind = _copy_kind(evt)
            copies[kind] = copies.get(kind, 0.0) + ms
    total = sum(v[0] for v in ops.values())
    ranked = sorted(((k, v[0], v[1]) for k, v in ops.items()), key=lambda x: -x[1])
    return {"size": size, "batch": batch, "mode": mode, "overrides": list(overrides), "steps": steps,
            "total_ms": total, "ops": ranked, "copies": copies}


def markdown(head: dict, prof: dict, top: int = 30) -> str:
    total = prof["total_ms"]
    lines = [f"# Profile of the training step, {prof['size']}², batch {prof['batch']}, {prof['mode']}", "",
             provenance_markdown(head), "",
             f"`torch.profiler` over {prof['steps']} steps after warm-up (model overrides: "
             f"`{' '.join(prof['overrides']) or 'none (the full model)'}`); self CPU time per step summed over "
             f"every operator: **{total:.0f} ms** (profiler overhead included).", "",
             "## Copies and dtype casts (self time of `aten::copy_`, by the operator that asked for it)", "",
             "| kind | ms/step | share of step |", "|---|---:|---:|"]
    for kind, ms in sorted(prof["copies"].items(), key=lambda x: -x[1]):
        lines.append(f"| {kind} | {ms:.1f} | {100 * ms / total:.1f}% |")
    all_copies = sum(prof["copies"].values())
    lines += [f"| **all copies** | **{all_copies:.1f}** | **{100 * all_copies / total:.1f}%** |", "",
              f"## Top {top} operators by self time", "", "| operator | self ms/step | share | calls/step |",
              "|---|---:|---:|---:|"]
    for name, ms, calls in prof["ops"][:top]:
        lines.append(f"| `{name}` | {ms:.1f} | {100 * ms / total:.1f}% | {calls:.0f} |")
    return "\n".join(lines) + "\n"
