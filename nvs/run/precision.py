"""``precision=auto``: the execution mode (dtype and memory layout) chosen by a timed probe of this machine.

On a CPU the probe times the network's typical convolutions (one 3x3 conv per level at 64^2, forward and backward)
in three modes -- ``fp32`` (NCHW), ``cl`` (fp32 channels_last) and ``bf16_cl`` (bf16 autocast, channels_last) -- and
picks the fastest, timing the modes in interleaved rounds. bf16 is only fast where the CPU has native bf16
instructions (AVX512-BF16, AMX); elsewhere oneDNN emulates it at ~10x the fp32 cost, which is why a fixed bf16
default cannot serve every machine. The result is cached per machine (CPU model, family/model/stepping, bf16
flags, threads) and torch version, so it costs ~0.5-1 s once; a probe taken on a busy machine is taken again by the
first run that finds it quiet. A resumed run keeps the mode its checkpoint records (:func:`kept_through_resume`).
On CUDA, auto picks bf16 autocast where the device supports it (fp32 otherwise) without probing.

An explicit precision is honoured; bf16 on a CPU that the probe measures slower than fp32 gets one warning line.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from nvs.core.atomic import cache_dir

AUTO = "auto"
# mode -> (Lightning precision, channels_last)
MODES: dict[str, tuple[str, bool]] = {"fp32": ("32-true", False), "cl": ("32-true", True),
                                      "bf16_cl": ("bf16-mixed", True)}
LIGHTNING_PRECISIONS = ("64-true", "32-true", "bf16-mixed", "bf16-true", "16-mixed", "16-true",
                        "64", "32", "16", "bf16")
_ALIASES = {"32": "32-true", "64": "64-true", "16": "16-mixed", "bf16": "bf16-mixed"}
# (channels, spatial size) of the probe's convolutions: one 3x3 conv per level of the network at 64^2 (conv0 at full
# resolution, then halving the size and doubling the channels), at half the training batch. Version 1 timed three
# smaller convs (batch 4, 32-128 channels at 32^2-8^2, ~5 ms a mode) one mode after the other: on a Zen 4 with native
# bf16 one such probe measured fp32 fastest (bf16_cl 1.28x) where the 64^2 training step runs 1.54x faster in
# bf16_cl, and the cache kept that pick. These shapes (~25 ms a mode) put bf16_cl at 0.59-0.62x fp32 there, against
# 0.65x for the training step and 0.79x for the novel view (readings of nvs.bench and three probes, 2026-12-04).
_PROBE_CONVS = ((32, 64), (64, 32), (128, 16), (256, 8))
_PROBE_BATCH = 4
_PROBE_ROUNDS = 5
# After this many rounds a mode this much slower than the fastest is not timed again (an emulated bf16: ~10x).
_DROP_AFTER_ROUNDS, _DROP_SLOWDOWN = 2, 4.0
# An explicit bf16 at least this much slower than the fastest mode is worth a warning.
WARN_SLOWDOWN = 1.5
PROBE_VERSION = 2
# A probe taken while the 1-minute load average was at least this many runnable processes per core this process may
# use measured the machine busy (under `make test`'s three workers on 2 cores: cl 149 ms, fp32 336 ms, where the quiet
# machine times them within 10% of each other). It is kept, and the first probe() that finds the machine quiet times
# the modes again and replaces it.
BUSY_LOAD_PER_CORE = 0.75


@dataclass(frozen=True)
class Choice:
    """What runs: the Lightning precision and layout, the mode's name, and why (one line)."""

    requested: str
    precision: str
    channels_last: bool
    mode: str
    reason: str
    probe_ms: dict[str, float] | None = None

    @property
    def autocast_dtype(self) -> torch.dtype | None:
        return torch.bfloat16 if self.precision.startswith("bf16") else (
            torch.float16 if self.precision.startswith("16") else None)

    def record(self) -> dict:
        """The ``metrics.json`` field."""
        return asdict(self)

    def line(self) -> str:
        return f"precision: {self.mode} ({self.precision}, {'channels_last' if self.channels_last else 'NCHW'}): " \
               f"{self.reason}"


def normalise(precision) -> str:
    """A Lightning precision in its long form (``32`` -> ``32-true``), or ``auto``; anything else is a ValueError."""
    text = str(precision)
    if text == AUTO:
        return AUTO
    if text not in LIGHTNING_PRECISIONS:
        raise ValueError(f"{precision!r}: expected auto or one of {', '.join(LIGHTNING_PRECISIONS)}")
    return _ALIASES.get(text, text)


def _cpuinfo() -> dict[str, str]:
    fields: dict[str, str] = {}
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            key = key.strip()
            if not key:
                break  # the first processor's block is enough
            fields.setdefault(key, value.strip())
    return fields


def native_bf16_flags() -> list[str]:
    """The CPU flags that give native bf16 arithmetic (``avx512_bf16``, ``amx_bf16``) this CPU has."""
    flags = set(_cpuinfo().get("flags", "").split())
    return sorted(flags & {"avx512_bf16", "amx_bf16"})


def machine_key() -> str:
    """What the probe's result depends on: CPU model and its family/model/stepping (two CPUs may share a model name),
    the bf16 flags, the thread count and torch's version."""
    info = _cpuinfo()
    cpu = info.get("model name") or platform.processor() or platform.machine()
    fms = "/".join(info.get(k, "?") for k in ("cpu family", "model", "stepping"))
    flags = ",".join(native_bf16_flags()) or "no-bf16"
    return f"{cpu} [{fms}] {flags} {torch.get_num_threads()}t torch-{torch.__version__} v{PROBE_VERSION}"


def cache_path() -> Path:
    """``precision.json`` in :func:`nvs.core.atomic.cache_dir`."""
    return cache_dir() / "precision.json"


def _time_modes(convs: list[torch.nn.Module], inputs: list[torch.Tensor], rounds: int) -> dict[str, float]:
    """ms of forward + backward of every probe conv, per mode: the fastest of ``rounds`` rounds that each time every
    mode once (interleaved, so a burst of load from elsewhere falls on all modes, and the minimum is the run that the
    load spared). A mode over ``_DROP_SLOWDOWN`` x the fastest after ``_DROP_AFTER_ROUNDS`` rounds is not timed again:
    more rounds would not change the pick."""
    prepared = {}
    for mode, (_, channels_last) in MODES.items():
        fmt = torch.channels_last if channels_last else torch.contiguous_format
        prepared[mode] = ([c.to(memory_format=fmt) for c in convs],
                          [x.contiguous(memory_format=fmt).requires_grad_(True) for x in inputs])

    def once(mode: str) -> float:
        mode_convs, xs = prepared[mode]
        dtype = torch.bfloat16 if mode.startswith("bf16") else None
        t0 = time.perf_counter()
        with torch.autocast("cpu", dtype=dtype) if dtype else contextlib.nullcontext():
            outs = [torch.relu(c(x)) for c, x in zip(mode_convs, xs)]
        sum(o.float().mean() for o in outs).backward()
        return 1000 * (time.perf_counter() - t0)

    for mode in MODES:  # warm-up: oneDNN builds its kernels for these shapes and layouts
        once(mode)
    best = {mode: float("inf") for mode in MODES}
    timed = list(MODES)
    for done in range(1, rounds + 1):
        for mode in timed:
            best[mode] = min(best[mode], once(mode))
        if done == _DROP_AFTER_ROUNDS:
            timed = [m for m in MODES if best[m] <= _DROP_SLOWDOWN * min(best.values())]
    return best


# The load average under which the probe that probe() last returned was taken (for the choice's line).
_LAST_PROBE_LOAD: list[float | None] = [None]


def load_average() -> float | None:
    """The 1-minute load average (None where the system does not tell)."""
    return round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def busy(load: float | None) -> bool:
    """Whether a 1-minute load average ``load`` says the machine was busy (:data:`BUSY_LOAD_PER_CORE`)."""
    return load is not None and load >= BUSY_LOAD_PER_CORE * _cores()


def probe(refresh: bool = False) -> dict[str, float]:
    """ms of the probe in every CPU mode on this machine, {mode: ms}; cached per :func:`machine_key`. A kept probe
    that was taken on a busy machine is taken again once the machine is quiet (:data:`BUSY_LOAD_PER_CORE`)."""
    key, path = machine_key(), cache_path()
    cache: dict = {}
    with contextlib.suppress(OSError, ValueError):
        cache = json.loads(path.read_text())
    kept = cache.get(key) if isinstance(cache, dict) else None
    if not refresh and isinstance(kept, dict) and set(kept.get("ms", {})) == set(MODES):
        if not (busy(kept.get("load_avg_1min")) and not busy(load_average())):
            _LAST_PROBE_LOAD[0] = kept.get("load_avg_1min")
            return dict(kept["ms"])
    if not isinstance(cache, dict):
        cache = {}
    gen = torch.Generator().manual_seed(0)
    convs = [torch.nn.Conv2d(c, c, 3, padding=1) for c, _ in _PROBE_CONVS]
    inputs = [torch.randn(_PROBE_BATCH, c, s, s, generator=gen) for c, s in _PROBE_CONVS]
    ms = _time_modes(convs, inputs, _PROBE_ROUNDS)
    cache[key] = {"ms": ms, "date": time.strftime("%Y-%m-%dT%H:%M:%S"), "rounds": _PROBE_ROUNDS,
                  "load_avg_1min": load_average()}
    _LAST_PROBE_LOAD[0] = cache[key]["load_avg_1min"]
    with contextlib.suppress(OSError):  # a cache that cannot be written only costs the probe next time
        from nvs.core.atomic import write_json

        write_json(path, cache)
    return ms


def _on_cuda(accelerator: str | None) -> bool:
    return str(accelerator or "auto") in ("auto", "gpu", "cuda") and torch.cuda.is_available()


def choose(requested="auto", channels_last="auto", accelerator: str | None = "auto", warn=None) -> Choice:
    """The mode a run uses. ``requested``: ``auto`` or a Lightning precision; ``channels_last``: ``auto`` or a bool
    (auto: the layout the probe measures faster for that precision). ``warn`` receives the emulated-bf16 warning
    (default: one line on stderr)."""
    requested = normalise(requested)
    layout = None if str(channels_last) == AUTO else bool(channels_last)
    if _on_cuda(accelerator):
        if requested == AUTO:
            bf16 = torch.cuda.is_bf16_supported()
            precision, why = ("bf16-mixed", "CUDA device supports bf16") if bf16 else \
                ("32-true", "CUDA device without bf16")
        else:
            precision, why = requested, "requested"
        cl = precision.startswith("bf16") if layout is None else layout
        return Choice(requested, precision, cl, _mode_name(precision, cl), why)
    if requested not in (AUTO, "32-true", "bf16-mixed") and layout is not None:
        return Choice(requested, requested, layout, _mode_name(requested, layout), "requested")
    _LAST_PROBE_LOAD[0] = None
    ms = probe()
    fastest = min(ms, key=ms.get)
    if requested == AUTO and layout is None:
        precision, cl = MODES[fastest]
        others = ", ".join(f"{m} {ms[m] / ms[fastest]:.2f}x" for m in ms if m != fastest)
        load = _LAST_PROBE_LOAD[0]
        note = f"; probed on a busy machine (load {load}): timed again once it is quiet" if busy(load) else ""
        return Choice(AUTO, precision, cl, fastest, f"fastest in this machine's probe ({others}){note}", ms)
    if requested == AUTO:  # a layout was given: the faster dtype in it
        candidates = [m for m in MODES if MODES[m][1] == layout] or list(MODES)
        mode = min(candidates, key=ms.get)
        precision = MODES[mode][0]
        return Choice(AUTO, precision, layout, _mode_name(precision, layout),
                      f"fastest in this machine's probe with channels_last={layout}", ms)
    candidates = [m for m in MODES if MODES[m][0] == requested]
    if layout is None:
        mode = min(candidates, key=ms.get) if candidates else None
        cl = MODES[mode][1] if mode else requested.startswith("bf16")
    else:
        cl = layout
        mode = next((m for m in candidates if MODES[m][1] == cl), None)
    reason = "requested"
    if requested.startswith("bf16"):
        bf16_ms = ms.get(mode or "bf16_cl", ms["bf16_cl"])
        slowdown = bf16_ms / ms[fastest]
        if slowdown >= WARN_SLOWDOWN:
            flags = native_bf16_flags()
            reason = f"requested; measured {slowdown:.1f}x slower than {fastest}"
            message = (f"warning: precision {requested} on a CPU that "
                       f"{'has ' + '/'.join(flags) + ' but ' if flags else 'emulates bf16 (no avx512_bf16/amx_bf16): '}"
                       f"measured {slowdown:.1f}x slower than {fastest} in this machine's probe; "
                       f"precision=auto would pick {fastest}")
            (warn or (lambda text: print(text, file=sys.stderr, flush=True)))(message)
    return Choice(requested, requested, cl, _mode_name(requested, cl), reason, ms)


def kept_through_resume(choice: Choice, held: dict | None) -> Choice:
    """``choice`` for a run that resumes a checkpoint recording ``held`` (its first segment's ``Choice.record()``):
    under ``auto`` the recorded mode, so that one run never trains in two modes (a re-probe, another thread count or
    a busy probe may pick another now); an explicit precision, or no record, keeps ``choice``."""
    if choice.requested != AUTO or not held or held.get("requested") != AUTO or held.get("mode") not in MODES:
        return choice
    if held["mode"] == choice.mode:
        return choice
    precision, cl = MODES[held["mode"]]
    return Choice(AUTO, precision, cl, held["mode"], f"the mode of the run it resumes, kept for its remaining steps "
                  f"(this machine's probe now picks {choice.mode})", choice.probe_ms)


def _mode_name(precision: str, channels_last: bool) -> str:
    for mode, (p, cl) in {**MODES, "bf16": ("bf16-mixed", False)}.items():
        if (p, cl) == (precision, channels_last):
            return mode
    return f"{precision}{'_cl' if channels_last else ''}"
