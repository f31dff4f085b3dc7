"""Timing, FLOPs and peak memory of callables, interleaved so that machine noise falls on every contender alike.

Times are medians of repeats after warm-up, synchronised on GPU. FLOPs are torch's counter
(``torch.utils.flop_counter.FlopCounterMode``: matmuls and convolutions, forward and backward). Peak memory on GPU
is ``max_memory_allocated``; on CPU it is the rise of the process's peak RSS over one call, measured after
``malloc_trim`` has handed freed heap pages back, plus the state that persists between calls (parameters, buffers,
optimiser state), so two contenders in one process are measured alike.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import statistics
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _status_kb(key: str) -> float | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return float(line.split()[1])
    except OSError:
        pass
    return None


def _trim_heap() -> None:
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def state_bytes(modules: Iterable[torch.nn.Module], optimizers: Iterable[torch.optim.Optimizer] = ()) -> int:
    """Bytes of what lives between steps: parameters, buffers and optimiser state (each tensor once)."""
    seen, total = set(), 0
    tensors = [t for m in modules for t in (*m.parameters(), *m.buffers())]
    tensors += [v for opt in optimizers for s in opt.state.values() for v in s.values() if torch.is_tensor(v)]
    for t in tensors:
        if t.data_ptr() not in seen:
            seen.add(t.data_ptr())
            total += t.numel() * t.element_size()
    return total


def peak_mb(fn: Callable[[], object], device: torch.device, persistent_bytes: int = 0) -> float | None:
    """Peak memory (MB) of one call of ``fn``: what it allocates at most, plus ``persistent_bytes``."""
    if device.type == "cuda":
        sync(device)
        torch.cuda.reset_peak_memory_stats(device)
        fn()
        sync(device)
        return torch.cuda.max_memory_allocated(device) / 2**20
    _trim_heap()
    before = _status_kb("VmRSS")
    try:
        Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM (peak RSS) to the current RSS
    except OSError:
        return None
    fn()
    peak = _status_kb("VmHWM")
    if before is None or peak is None:
        return None
    return (peak - before) / 1024 + persistent_bytes / 2**20


def flops(fn: Callable[[], object]) -> int:
    with FlopCounterMode(display=False) as counter:
        fn()
    return int(counter.get_total_flops())


def interleaved(fns: dict[str, Callable[[], object]], device: torch.device, warmup: int, repeats: int
                ) -> dict[str, dict]:
    """Times every callable ``repeats`` times, one call of each in turn (after ``warmup`` calls of each).

    -> {name: {median_ms, min_ms, max_ms}}. A callable that raises is reported as {"error": ...} and dropped.
    """
    times: dict[str, list[float]] = {name: [] for name in fns}
    errors: dict[str, str] = {}
    for _ in range(warmup):
        for name, fn in fns.items():
            if name not in errors:
                try:
                    fn()
                except Exception as err:  # noqa: BLE001 - a failing contender is reported, the rest go on
                    errors[name] = f"{err.__class__.__name__}: {str(err).splitlines()[0][:160] if str(err) else ''}"
    for _ in range(repeats):
        for name, fn in fns.items():
            if name in errors:
                continue
            sync(device)
            t0 = time.perf_counter()
            try:
                fn()
            except Exception as err:  # noqa: BLE001
                errors[name] = f"{err.__class__.__name__}: {str(err).splitlines()[0][:160] if str(err) else ''}"
                continue
            sync(device)
            times[name].append(1000 * (time.perf_counter() - t0))
    out = {}
    for name in fns:
        if name in errors:
            out[name] = {"error": errors[name]}
        else:
            t = times[name]
            out[name] = {"median_ms": statistics.median(t), "min_ms": min(t), "max_ms": max(t), "n": len(t)}
    return out


# Peak kinds: (dtype, what); "conv" is a 3x3 64-channel convolution at 128² batch 8, forward (the network's typical
# layer), in NCHW or channels_last; "matmul" a 2048² matmul.
PEAK_KINDS = {"fp32_matmul": (None, "matmul"), "fp32_conv": (None, "conv"), "fp32_conv_cl": (None, "conv_cl"),
              "bf16_matmul": (torch.bfloat16, "matmul"), "bf16_conv_cl": (torch.bfloat16, "conv_cl")}
# Which peak a bench mode is measured against (its own arithmetic and layout).
MODE_PEAK = {"fp32": "fp32_conv", "cl": "fp32_conv_cl", "bf16": "bf16_conv_cl", "bf16_cl": "bf16_conv_cl",
             "compile": "bf16_conv_cl"}


def mode_peak(peaks: dict, mode: str) -> float | None:
    """The measured conv peak (GFLOP/s) a row of ``mode`` is compared with, if the report measured it."""
    return peaks.get(MODE_PEAK.get(mode, "") + "_gflops")


_N, _C, _S = 8, 64, 128
SLOW_PEAK_CALL_MS = 2000.0
_PEAK_FLOP = {"matmul": 2 * 2048**3, "conv": 2 * _N * _C * _C * 9 * _S * _S}  # one call of each kind


def machine_peak(device: torch.device, repeats: int = 7, kinds=None) -> dict:
    """Achievable GFLOP/s of every ``PEAK_KINDS`` entry (or of ``kinds``), timed interleaved (medians):
    {kind + "_gflops": value}."""
    a = torch.randn(2048, 2048, device=device)
    x = torch.randn(_N, _C, _S, _S, device=device)
    conv = torch.nn.Conv2d(_C, _C, 3, padding=1).to(device)
    conv_cl = torch.nn.Conv2d(_C, _C, 3, padding=1).to(device, memory_format=torch.channels_last)
    x_cl = x.contiguous(memory_format=torch.channels_last)
    mats = {None: a, torch.bfloat16: a.to(torch.bfloat16)}
    flop = {**_PEAK_FLOP, "conv_cl": _PEAK_FLOP["conv"]}

    def kernel(dtype, what):
        def run():
            with torch.no_grad(), torch.autocast(device.type, dtype=dtype or torch.bfloat16, enabled=dtype is not None):
                if what == "matmul":
                    mats[dtype] @ mats[dtype]
                else:
                    (conv_cl if what == "conv_cl" else conv)(x_cl if what == "conv_cl" else x)
        return run

    kernels = {k: kernel(*v) for k, v in PEAK_KINDS.items() if kinds is None or k in kinds}
    first = interleaved(kernels, device, 0, 1)  # one call each: the warm-up, timed
    # A kind whose one call takes seconds (a 2048² bf16 matmul where bf16 is emulated: ~50 s) keeps that timing;
    # repeating it would cost the bench minutes to measure a rate 100x below the others.
    slow = {k for k, t in first.items() if t.get("median_ms", 0) > SLOW_PEAK_CALL_MS}
    t = {**interleaved({k: f for k, f in kernels.items() if k not in slow and "error" not in first[k]}, device, 1,
                       repeats), **{k: first[k] for k in slow}}
    return {f"{k}_gflops": flop[v[1]] / t[k]["median_ms"] / 1e6 for k, v in PEAK_KINDS.items()
            if "median_ms" in t.get(k, {})}


def peak_again(device: torch.device, start: dict) -> tuple[dict, dict]:
    """The peaks timed once more at the end of a run -> (the larger of the two per kind, the end's). A shared machine
    drifts over a long bench (on the AVX2 EPYC the NCHW conv peak read 103 and then 79 GFLOP/s in two runs 11
    minutes apart), and a row timed while it was faster than at the start would read > 100% of a peak timed once.
    Kinds whose one call took seconds (emulated bf16 matmul) keep the start's value."""
    quick = [k for k, (_, what) in PEAK_KINDS.items() if f"{k}_gflops" in start  # its one call's ms at the start
             and _PEAK_FLOP["matmul" if what == "matmul" else "conv"] / start[f"{k}_gflops"] / 1e6
             <= SLOW_PEAK_CALL_MS]
    end = machine_peak(device, kinds=quick) if quick else {}
    return {k: max(v, end.get(k, v)) for k, v in start.items()}, end
