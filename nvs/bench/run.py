"""One image size: build every contender, time them interleaved, then count FLOPs and peak memory one by one."""

from __future__ import annotations

import gc

import torch

from nvs.bench.contenders import Batches, Contender, make_batches, nvs_contender, reference_contender
import nvs.bench.measure as measure
from nvs.bench.reference import SIZE as REFERENCE_SIZE

REFERENCE = "authors_code"  # the row name of the authors' code


def _error(err: Exception) -> str:
    return f"{err.__class__.__name__}: {str(err).splitlines()[0][:160] if str(err) else ''}"


def build(models: dict[str, list[str]], modes: list[str], batches: Batches, device: torch.device, root_dir: str,
          size: int, reference: str | None, log=print) -> tuple[dict[str, Contender], dict[str, dict]]:
    """-> ({"model/mode": contender}, {"model/mode": row with params or error}); the authors' code as REFERENCE."""
    contenders, rows = {}, {}
    for model, overrides in models.items():
        for mode in modes:
            key = f"{model}/{mode}"
            rows[key] = {"model": model, "mode": mode}
            try:
                contenders[key] = nvs_contender(list(overrides), mode, batches, device, root_dir, size)
                rows[key]["params"] = contenders[key].params
            except Exception as err:  # noqa: BLE001 - a failing option is reported in the table, not fatal
                rows[key]["error"] = _error(err)
                log(f"{size}² {key}: {rows[key]['error']}")
    if reference and size == REFERENCE_SIZE:
        key = f"{REFERENCE}/fp32"
        contenders[key] = reference_contender(reference, batches, device)
        rows[key] = {"model": REFERENCE, "mode": "fp32", "params": contenders[key].params}
    return contenders, rows


def bench_size(models: dict[str, list[str]], modes: list[str], size: int, train_batch: int, eval_batch: int,
               throughput_batch: int | None, warmup: int, repeats: int, device: torch.device, root_dir: str,
               reference: str | None = None, log=print) -> dict:
    """Every model option in every mode (and the authors' code at 256² when ``reference`` is a path) at one size."""
    batches = make_batches(size, train_batch, eval_batch, throughput_batch, device)
    contenders, rows = build(models, modes, batches, device, root_dir, size, reference, log)
    log(f"{size}²: timing {len(contenders)} contenders, train batch {train_batch}, interleaved")
    timings = {
        "train": measure.interleaved({k: c.train for k, c in contenders.items()}, device, warmup, repeats),
        "eval": measure.interleaved({k: c.eval for k, c in contenders.items()}, device, warmup + 1,
                                    max(repeats, 5)),
        "eval_path": measure.interleaved({k: c.extra["eval_path"] for k, c in contenders.items()
                                          if "eval_path" in c.extra}, device, warmup, max(repeats, 5)),
    }
    if throughput_batch:
        timings["throughput"] = measure.interleaved({k: c.throughput for k, c in contenders.items()}, device, 1,
                                                    max(repeats // 2, 1))
    for key, contender in contenders.items():
        row = rows[key]
        for what, table in timings.items():
            if key in table:
                row[what] = table[key]
        if "error" in row["train"]:
            row["error"] = row["train"]["error"]
            continue
        row["train_ms"] = row["train"]["median_ms"]
        row["train_samples_per_s"] = 1000 * train_batch / row["train"]["median_ms"]
        if "median_ms" in row["eval"]:
            row["eval_ms_per_image"] = row["eval"]["median_ms"] / eval_batch
        if "median_ms" in row.get("eval_path", {}):
            row["eval_path_ms_per_image"] = row["eval_path"]["median_ms"] / eval_batch
        if "median_ms" in row.get("throughput", {}):
            row["throughput_images_per_s"] = 1000 * throughput_batch / row["throughput"]["median_ms"]
        if not contender.compiled:  # the counter sees eager ops only; a compiled row reuses its eager count
            row["train_gflop_per_sample"] = measure.flops(contender.train) / 1e9 / train_batch
            row["eval_gflop_per_image"] = measure.flops(contender.eval) / 1e9 / eval_batch
        row["train_peak_mb"] = measure.peak_mb(contender.train, device, contender.state())
        row["eval_peak_mb"] = measure.peak_mb(contender.eval, device, contender.state())
        log(f"{size}² {key}: train {row['train']['median_ms']:.0f} ms/step, "
            f"eval {row.get('eval_ms_per_image', float('nan')):.1f} ms/img, train peak {row['train_peak_mb']:.0f} MB")
    del contenders
    gc.collect()
    _derive(rows, train_batch)
    return {"size": size, "train_batch": train_batch, "eval_batch": eval_batch, "throughput_batch": throughput_batch,
            "rows": rows}


def _derive(rows: dict[str, dict], train_batch: int) -> None:
    """FLOPs shared across modes, speedups over the same model's fp32 row, achieved GFLOP/s."""
    for row in rows.values():
        if "error" in row:
            continue
        same = [r for r in rows.values() if r["model"] == row["model"] and "error" not in r]
        for k in ("train_gflop_per_sample", "eval_gflop_per_image"):
            if k not in row:
                counted = [r[k] for r in same if k in r]
                if counted:
                    row[k] = counted[0]
        base = rows.get(f"{row['model']}/fp32")
        if base and "error" not in base:
            row["train_speedup"] = base["train"]["median_ms"] / row["train"]["median_ms"]
            if "eval_ms_per_image" in row and "eval_ms_per_image" in base:
                row["eval_speedup"] = base["eval_ms_per_image"] / row["eval_ms_per_image"]
        if "train_gflop_per_sample" in row:
            row["train_achieved_gflops"] = row["train_gflop_per_sample"] * train_batch / (
                row["train"]["median_ms"] / 1e3)
        if row.get("eval_gflop_per_image") and row.get("eval_ms_per_image"):
            row["eval_achieved_gflops"] = row["eval_gflop_per_image"] / (row["eval_ms_per_image"] / 1e3)


def slow_modes(block: dict, factor: float | None) -> dict[str, float]:
    """The modes whose training step is at least ``factor`` times the fastest mode's for every model of a size's
    block (an emulated bf16: ~10x), each with its smallest such ratio; {} without a factor."""
    if not factor:
        return {}
    ratios: dict[str, list[float]] = {}
    for model in dict.fromkeys(r["model"] for r in block["rows"].values() if r["model"] != REFERENCE):
        timed = {r["mode"]: r["train_ms"] for r in block["rows"].values() if r["model"] == model and "train_ms" in r}
        if len(timed) < 2:
            continue
        best = min(timed.values())
        for mode, ms in timed.items():
            ratios.setdefault(mode, []).append(ms / best)
    return {m: min(v) for m, v in ratios.items() if min(v) >= factor}


def versus_reference(rows: dict[str, dict], model: str = "full") -> dict[str, dict]:
    """The authors' code over each mode of ``model``: time, FLOPs and peak-memory ratios (> 1: nvs is ahead)."""
    ref = rows.get(f"{REFERENCE}/fp32")
    if not ref or "error" in ref:
        return {}
    out = {}
    for key, row in rows.items():
        if row["model"] != model or "error" in row:
            continue
        r = {"train_speedup": ref["train"]["median_ms"] / row["train"]["median_ms"]}
        if "eval_ms_per_image" in row and "eval_ms_per_image" in ref:
            r["novel_view_speedup"] = ref["eval_ms_per_image"] / row["eval_ms_per_image"]
            if "eval_path_ms_per_image" in ref:
                r["eval_path_speedup"] = ref["eval_path_ms_per_image"] / row["eval_ms_per_image"]
        for k in ("train_gflop_per_sample", "eval_gflop_per_image", "train_peak_mb", "eval_peak_mb"):
            if row.get(k) and ref.get(k):
                r[f"{k}_ratio"] = ref[k] / row[k]
        out[row["mode"]] = r
    return out
