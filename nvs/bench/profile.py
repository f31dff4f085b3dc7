"""A torch.profiler profile of one model option's training step: top operators by self time, copies and casts summed.

Copies are classified by the operator that asked for them (the profiler's parent chain of each ``aten::copy_``):
dtype/layout conversions (``aten::to`` / ``_to_copy``: autocast's casts, channels_last conversions), clones and
``contiguous``, and the rest (in-place copies such as ``index_put_`` or optimiser updates).
"""

from __future__ import annotations

import torch
from torch.profiler import ProfilerActivity, profile

from nvs.bench.contenders import make_batches, nvs_contender
import nvs.bench.measure as measure
from nvs.core.provenance import markdown as provenance_markdown

_CONVERSIONS = ("aten::to", "aten::_to_copy", "aten::to_dtype", "aten::_autocast_to_reduced_precision",
                "aten::_autocast_to_full_precision")
_CLONES = ("aten::clone", "aten::contiguous")
_MATMULS = ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm", "aten::matmul", "aten::linear")


def is_matmul_or_conv(name: str) -> bool:
    """The operators whose FLOPs ``torch.utils.flop_counter`` counts: convolutions (forward, backward, and the
    dispatch above their kernels) and matmuls."""
    low = name.split("::")[-1].lower()
    return any(t in low for t in ("convolution", "conv2d", "conv_")) or name in _MATMULS


def _copy_kind(evt) -> tuple[str, str]:
    """-> (kind, the nearest operator above the copy that is not itself a copy or conversion)."""
    kind, parent = "other copy_ (in place)", evt.cpu_parent
    while parent is not None and (parent.name in _CONVERSIONS + _CLONES or parent.name == "aten::copy_"):
        if kind.startswith("other"):
            kind = ("dtype/layout conversions (aten::to, _to_copy: autocast casts, memory-format changes)"
                    if parent.name in _CONVERSIONS else "clones and contiguous")
        parent = parent.cpu_parent
    return kind, parent.name if parent is not None else "(top level)"


def profile_step(overrides: list[str], mode: str, size: int, batch: int, device: torch.device, root_dir: str,
                 warmup: int = 2, steps: int = 3) -> dict:
    """-> {"ops": [(name, self ms/step, calls/step)], "copies": {kind: ms/step}, "total_ms": ms/step, ...}."""
    contender = nvs_contender(overrides, mode, make_batches(size, batch, 1, None, device), device, root_dir, size)
    wall = measure.interleaved({"step": contender.train}, device, warmup, steps)["step"]
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        for _ in range(steps):
            contender.train()
    events = prof.events()
    ops: dict[str, list[float]] = {}
    copies: dict[str, float] = {}
    callers: dict[tuple[str, str], float] = {}
    for evt in events:
        ms = evt.self_cpu_time_total / 1000 / steps
        entry = ops.setdefault(evt.name, [0.0, 0])
        entry[0] += ms
        entry[1] += 1 / steps
        if evt.name == "aten::copy_":
            kind, caller = _copy_kind(evt)
            copies[kind] = copies.get(kind, 0.0) + ms
            callers[kind, caller] = callers.get((kind, caller), 0.0) + ms
    total = sum(v[0] for v in ops.values())
    counted = sum(v[0] for k, v in ops.items() if is_matmul_or_conv(k))
    ranked = sorted(((k, v[0], v[1]) for k, v in ops.items()), key=lambda x: -x[1])
    return {"size": size, "batch": batch, "mode": mode, "overrides": list(overrides), "steps": steps,
            "total_ms": total, "wall_ms": wall.get("median_ms"), "matmul_conv_share": counted / total if total else 0.0,
            "ops": ranked, "copies": copies,
            "copy_callers": sorted(((k, c, ms) for (k, c), ms in callers.items()), key=lambda x: -x[2])}


def markdown(head: dict, prof: dict, top: int = 30) -> str:
    total = prof["total_ms"]
    lines = [f"# Profile of the training step, {prof['size']}², batch {prof['batch']}, {prof['mode']}", "",
             provenance_markdown(head), "",
             f"`torch.profiler` over {prof['steps']} steps after warm-up (model overrides: "
             f"`{' '.join(prof['overrides']) or 'none (the full model)'}`); self CPU time per step summed over "
             f"every operator: **{total:.0f} ms** (profiler overhead included); the same step without the profiler: "
             f"{prof['wall_ms']:.0f} ms (median of {prof['steps']}, after the warm-up). Convolutions and matmuls (the "
             f"operators whose FLOPs the bench counts) take **{100 * prof['matmul_conv_share']:.0f}%** of the self "
             "time, everything else the rest.", "",
             "## Copies and dtype casts (self time of `aten::copy_`, by the operator that asked for it)", "",
             "| kind | ms/step | share of step |", "|---|---:|---:|"]
    for kind, ms in sorted(prof["copies"].items(), key=lambda x: -x[1]):
        lines.append(f"| {kind} | {ms:.1f} | {100 * ms / total:.1f}% |")
    all_copies = sum(prof["copies"].values())
    lines += [f"| **all copies** | **{all_copies:.1f}** | **{100 * all_copies / total:.1f}%** |", "",
              "Who asks for them (the nearest operator above the copy; backward nodes are autograd's):", "",
              "| kind | asked for by | ms/step |", "|---|---|---:|"]
    lines += [f"| {kind.split(' (')[0]} | `{caller}` | {ms:.1f} |" for kind, caller, ms in prof["copy_callers"][:12]]
    lines += ["",
              f"## Top {top} operators by self time", "", "| operator | self ms/step | share | calls/step |",
              "|---|---:|---:|---:|"]
    for name, ms, calls in prof["ops"][:top]:
        lines.append(f"| `{name}` | {ms:.1f} | {100 * ms / total:.1f}% | {calls:.0f} |")
    return "\n".join(lines) + "\n"
