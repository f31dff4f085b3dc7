"""python -m nvs.bench: run time, memory and FLOPs of every model option in every execution mode.

Writes results/bench/<device>.json and .md. Medians and spreads over repeated runs after warm-up, synchronised on
GPU; peak memory is the process's peak RSS on CPU (reset before each measurement) or max allocated on GPU.
"""

from __future__ import annotations

import contextlib
import platform
import statistics
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import hydra
import torch
from hydra import compose
from omegaconf import DictConfig, OmegaConf
from torch.utils.flop_counter import FlopCounterMode

from nvs.atomic import write_json, write_text
from nvs.build import build_module, device_name, git_sha, parameter_count
from nvs.errors import exits_cleanly
from nvs.geometry import pose_matrix, scale_intrinsics

MODES = {
    # name: (channels_last, autocast dtype or None, compile)
    "fp32": (False, None, False),
    "cl": (True, None, False),
    "bf16": (False, torch.bfloat16, False),
    "bf16_cl": (True, torch.bfloat16, False),
    "compile": (True, torch.bfloat16, True),
}


def synthetic_batch(B: int, S: int, device: torch.device, seed: int = 0) -> dict:
    """An object-centric batch of the data contract: 20 degrees of azimuth about (0,0,2), depth in [1.5,2.5]."""
    g = torch.Generator().manual_seed(seed)
    K = scale_intrinsics(torch.tensor([[480.0, 0, 128], [0, 480.0, 128], [0, 0, 1]]), S / 256)
    a = torch.deg2rad(torch.tensor(20.0))
    R = torch.tensor([[torch.cos(a), 0, torch.sin(a)], [0, 1, 0], [-torch.sin(a), 0, torch.cos(a)]])
    c = torch.tensor([0.0, 0.0, 2.0])
    T = pose_matrix(R[None], (c - R @ c)[None])[0]
    batch = {
        "src": torch.rand(B, 3, S, S, generator=g),
        "tgt": torch.rand(B, 3, S, S, generator=g),
        "K": K.expand(B, 3, 3).clone(),
        "T_tgt_src": T.expand(B, 4, 4).clone(),
        "pivot": c.expand(B, 3).clone(),
        "depth_tgt": 1.5 + torch.rand(B, 1, S, S, generator=g),
    }
    return {k: v.to(device) for k, v in batch.items()}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    else:
        with contextlib.suppress(OSError):
            Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM (peak RSS) of this process


def _peak_mb(device: torch.device) -> float | None:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def _time(fn, device, warmup: int, repeats: int) -> dict:
    for _ in range(warmup):
        fn()
    _sync(device)
    _reset_peak(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(1000 * (time.perf_counter() - t0))
    return {"median_ms": statistics.median(times), "min_ms": min(times), "max_ms": max(times),
            "peak_mem_mb": _peak_mb(device)}


def _flops(fn) -> int:
    with FlopCounterMode(display=False) as counter:
        fn()
    return int(counter.get_total_flops())


def machine_peak(device: torch.device) -> dict:
    """Achievable bf16 GFLOP/s: a large matmul and a 3x3 64-channel channels_last convolution."""
    out = {}
    a = torch.randn(2048, 2048, device=device, dtype=torch.bfloat16)
    r = _time(lambda: a @ a, device, 2, 5)
    out["bf16_matmul_gflops"] = 2 * 2048**3 / r["median_ms"] / 1e6
    conv = torch.nn.Conv2d(64, 64, 3, padding=1).to(device, memory_format=torch.channels_last)
    x = torch.randn(8, 64, 128, 128, device=device).contiguous(memory_format=torch.channels_last)

    def run_conv():
        with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16):
            conv(x)

    r = _time(run_conv, device, 2, 5)
    out["bf16_conv3x3_gflops"] = 2 * 8 * 64 * 64 * 9 * 128 * 128 / r["median_ms"] / 1e6
    return out


def bench_one(cfg_train: DictConfig, mode: str, device: torch.device, bcfg: DictConfig) -> dict:
    """Train step, eval latency, throughput, memory and FLOPs of one model option in one mode."""
    channels_last, dtype, compiled = MODES[mode]
    cfg_train.channels_last = channels_last
    module = build_module(cfg_train).to(device)
    net = module.net
    if compiled:
        module.net = torch.compile(net)
    opt = module.configure_optimizers()
    if isinstance(opt, (list, tuple)):
        opt = opt[0]
    S = int(cfg_train.data.size)
    train_batch = synthetic_batch(bcfg.train_batch, S, device)
    autocast = (lambda: torch.autocast(device.type, dtype=dtype)) if dtype else contextlib.nullcontext

    def train_step():
        module.train()
        with autocast():
            out = module(dict(train_batch), module.train_needs)
            total = sum(term.weight * term(out, train_batch) for term in module.losses.values())
        total.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)

    def eval_fn(batch):
        def run():
            module.eval()
            with torch.no_grad(), autocast():
                module(dict(batch))
        return run

    res = {"mode": mode, "params": parameter_count(net)}
    res["train"] = _time(train_step, device, bcfg.warmup, bcfg.repeats)
    eval_batch = synthetic_batch(bcfg.eval_batch, S, device, seed=1)
    res["eval"] = _time(eval_fn(eval_batch), device, bcfg.warmup + 1, max(bcfg.repeats, 5))
    res["eval"]["ms_per_image"] = res["eval"]["median_ms"] / bcfg.eval_batch
    thr_batch = synthetic_batch(bcfg.throughput_batch, S, device, seed=2)
    thr = _time(eval_fn(thr_batch), device, 1, max(bcfg.repeats // 2, 1))
    res["throughput_images_per_s"] = 1000 * bcfg.throughput_batch / thr["median_ms"]
    res["throughput_peak_mem_mb"] = thr["peak_mem_mb"]
    if not compiled:
        res["train_gflop_per_sample"] = _flops(train_step) / 1e9 / bcfg.train_batch
        res["eval_gflop_per_image"] = _flops(eval_fn(eval_batch)) / 1e9 / bcfg.eval_batch
    return res


def _add_ratios(rows: dict) -> None:
    for model, modes in rows.items():
        base = modes.get("fp32")
        flops = {k: modes[m].get(k) for m in modes for k in ("train_gflop_per_sample", "eval_gflop_per_image")
                 if modes[m].get(k)}
        for r in modes.values():
            if "error" in r:
                continue
            for k, v in flops.items():
                r.setdefault(k, v)  # FLOPs do not depend on the mode; compiled runs reuse the eager count
            if base and "error" not in base:
                r["train_step_speedup"] = base["train"]["median_ms"] / r["train"]["median_ms"]
                r["eval_speedup"] = base["eval"]["ms_per_image"] / r["eval"]["ms_per_image"]
            if r.get("train_gflop_per_sample"):
                batch = r["train_batch"]
                r["train_achieved_gflops"] = r["train_gflop_per_sample"] * batch / (r["train"]["median_ms"] / 1e3)


def _markdown(report: dict) -> str:
    h = report["header"]
    lines = [f"# Benchmark on {h['device']}", "",
             f"- command: `{h['command']}`", f"- git SHA: {h['git_sha']}", f"- date: {h['date']}",
             f"- torch {h['torch']}, {h['threads']} threads; image {h['image_size']}², train batch {h['train_batch']}, "
             f"eval batch {h['eval_batch']}, throughput batch {h['throughput_batch']}; "
             f"median of {h['repeats']} after {h['warmup']} warm-up"]
    if report.get("peak"):
        p = report["peak"]
        lines.append(f"- measured peak: bf16 matmul {p['bf16_matmul_gflops']:.0f} GFLOP/s, "
                     f"bf16 channels_last 3x3 conv {p['bf16_conv3x3_gflops']:.0f} GFLOP/s")
    lines += ["", "| model | mode | params | train ms/step (min–max) | speedup | eval ms/img | eval speedup | "
              "img/s @bs32 | peak MB (train) | GFLOP/sample train | achieved GFLOP/s | % of conv peak |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    peak = (report.get("peak") or {}).get("bf16_conv3x3_gflops")
    for model, modes in report["models"].items():
        for mode, r in modes.items():
            if "error" in r:
                lines.append(f"| {model} | {mode} | failed: {r['error']} |" + " |" * 9)
                continue
            t = r["train"]
            ach = r.get("train_achieved_gflops")
            lines.append(
                f"| {model} | {mode} | {r['params'] / 1e6:.2f} M | {t['median_ms']:.0f} ({t['min_ms']:.0f}–{t['max_ms']:.0f})"
                f" | {r.get('train_step_speedup', float('nan')):.2f}× | {r['eval']['ms_per_image']:.1f}"
                f" | {r.get('eval_speedup', float('nan')):.2f}× | {r['throughput_images_per_s']:.1f}"
                f" | {t['peak_mem_mb'] or 0:.0f} | {r.get('train_gflop_per_sample', float('nan')):.1f}"
                f" | {ach or float('nan'):.0f} | {100 * ach / peak if (ach and peak) else float('nan'):.0f}% |")
    lines += accuracy_section(Path(report["header"].get("precision_csv") or "results/precision.csv"))
    return "\n".join(lines) + "\n"


def accuracy_section(csv_path: Path, tolerance: float = 0.02) -> list[str]:
    """Markdown lines comparing test L1 of the fp32 and fast rows of the precision study (sweeps/precision.yaml).

    The rows are matched by name (``precision_fp32_*`` against ``precision_fast_*``); without the study's CSV the
    section says how to produce it.
    """
    head = ["", "## Accuracy of the fast mode", ""]
    if not csv_path.is_file():
        return head + [f"No `{csv_path}` yet: run `python -m nvs.sweep sweeps/precision.yaml`."]
    import pandas as pd

    df = pd.read_csv(csv_path)
    done = df[df["status"] == "done"]
    fp32 = done[done["row"].str.startswith("precision_fp32")]
    fast = done[done["row"].str.startswith("precision_fast")]
    if fp32.empty or fast.empty:
        return head + [f"`{csv_path}` has no finished fp32 and fast rows yet."]
    l1_fp32, l1_fast = float(fp32["l1"].mean()), float(fast["l1"].mean())
    rel = (l1_fast - l1_fp32) / l1_fp32
    verdict = "within" if abs(rel) <= tolerance else "NOT within"
    steps = ", ".join(sorted({str(int(x)) for x in done["steps"].dropna()}))
    return head + [
        f"Same chair schedule and seeds ({len(fp32)} run(s) each, {steps} steps, from `{csv_path}`):", "",
        "| mode | test L1 | SSIM (paper) | train wall s |", "|---|---:|---:|---:|",
        f"| fp32 NCHW | {l1_fp32:.4f} | {fp32['ssim_paper'].mean():.4f} | {fp32['train_wall_s'].mean():.0f} |",
        f"| bf16 + channels_last | {l1_fast:.4f} | {fast['ssim_paper'].mean():.4f} | "
        f"{fast['train_wall_s'].mean():.0f} |", "",
        f"Relative L1 difference {100 * rel:+.1f}%: {verdict} the {100 * tolerance:.0f}% goal."]


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in name.lower()).strip("-")[:60]


@hydra.main(version_base="1.3", config_path="../conf", config_name="bench")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    for m in cfg.modes:
        if m not in MODES:
            raise SystemExit(f"error: unknown mode {m!r}; choose from {list(MODES)}")
    report = {"header": {
        "command": "python -m nvs.bench " + " ".join(sys.argv[1:]),
        "git_sha": git_sha(), "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "device": device_name(device), "torch": torch.__version__, "threads": torch.get_num_threads(),
        "python": platform.python_version(), "image_size": cfg.image_size, "train_batch": cfg.train_batch,
        "eval_batch": cfg.eval_batch, "throughput_batch": cfg.throughput_batch, "repeats": cfg.repeats,
        "warmup": cfg.warmup}, "models": {}}
    if cfg.measure_peak:
        report["peak"] = machine_peak(device)
        print(f"peak: {report['peak']}", flush=True)
    chosen = list(cfg.only) if cfg.only else list(cfg.models)
    unknown = [m for m in chosen if m not in cfg.models]
    if unknown:
        raise SystemExit(f"error: only={unknown}: not in bench.yaml models {list(cfg.models)}")
    for model in chosen:
        overrides = cfg.models[model]
        report["models"][model] = {}
        for mode in cfg.modes:
            tcfg = compose(config_name="train", overrides=list(overrides) + [
                f"data.size={cfg.image_size}", f"paths.root_dir={cfg.paths.root_dir}", "paths.output_dir=/tmp"])
            OmegaConf.resolve(tcfg)
            try:
                r = bench_one(tcfg, mode, device, cfg)
            except Exception as err:  # noqa: BLE001 - a failing option is reported in the table, not fatal
                r = {"mode": mode, "error": f"{err.__class__.__name__}: {str(err).splitlines()[0][:120]}"}
            r["train_batch"] = cfg.train_batch
            report["models"][model][mode] = r
            msg = r.get("error") or f"train {r['train']['median_ms']:.0f} ms, eval {r['eval']['ms_per_image']:.1f} ms/img"
            print(f"{model:>14} {mode:>8}: {msg}", flush=True)
        _add_ratios({model: report["models"][model]})
        out = Path(cfg.out_dir)
        name = _slug(device_name(device).split("(")[0])
        write_json(out / f"{name}.json", report)
        write_text(out / f"{name}.md", _markdown(report))
    print(f"wrote {out / name}.json and .md")


if __name__ == "__main__":
    main()
