"""The bench report as Markdown: one table per image size, the authors' code beside nvs, the fast mode's accuracy."""

from __future__ import annotations

from pathlib import Path

from nvs.bench.run import REFERENCE, versus_reference
from nvs.provenance import markdown as provenance_markdown

NAN = float("nan")


def _f(value, fmt: str) -> str:
    return "–" if value is None or value != value else format(value, fmt)


def size_table(block: dict, peak: float | None) -> list[str]:
    s, b = block["size"], block["train_batch"]
    thr = block.get("throughput_batch")
    lines = [f"## {s}², train batch {b}, eval batch {block['eval_batch']}", "",
             "| model | mode | params | train ms/step (min–max) | samples/s | × fp32 | eval ms/img | × fp32 | "
             f"img/s @bs{thr or '–'} | peak MB train / eval | GFLOP/sample train | GFLOP/img eval | "
             "achieved GFLOP/s | % of conv peak |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in block["rows"].values():
        name = "authors' code" if row["model"] == REFERENCE else row["model"]
        if "error" in row:
            lines.append(f"| {name} | {row['mode']} | failed: {row['error']} |" + " |" * 11)
            continue
        t = row["train"]
        ach = row.get("train_achieved_gflops")
        lines.append(
            f"| {name} | {row['mode']} | {row['params'] / 1e6:.2f} M | {t['median_ms']:.0f} "
            f"({t['min_ms']:.0f}–{t['max_ms']:.0f}) | {row['train_samples_per_s']:.1f} | "
            f"{_f(row.get('train_speedup'), '.2f')}× | {_f(row.get('eval_ms_per_image'), '.1f')} | "
            f"{_f(row.get('eval_speedup'), '.2f')}× | {_f(row.get('throughput_images_per_s'), '.1f')} | "
            f"{_f(row.get('train_peak_mb'), '.0f')} / {_f(row.get('eval_peak_mb'), '.0f')} | "
            f"{_f(row.get('train_gflop_per_sample'), '.1f')} | {_f(row.get('eval_gflop_per_image'), '.1f')} | "
            f"{_f(ach, '.0f')} | {_f(100 * ach / peak if ach and peak else None, '.0f')}"
            f"{'%' if ach and peak else ''} |")
    return lines + [""]


def reference_table(block: dict, model: str = "full") -> list[str]:
    """The authors' code against each mode of ``model`` at the same size, batch and inputs."""
    rows, ratios = block["rows"], versus_reference(block["rows"], model)
    ref = rows.get(f"{REFERENCE}/fp32")
    if not ref:
        return []
    head = [f"## The authors' code beside nvs ({block['size']}², train batch {block['train_batch']}, "
            f"novel view batch {block['eval_batch']}; same inputs, interleaved)", ""]
    if "error" in ref:
        return head + [f"The authors' code failed: {ref['error']}", ""]
    modes = [m for m in ratios]
    lines = head + ["| | authors' code (fp32, as it runs) | " + " | ".join(f"nvs {model} {m}" for m in modes) + " |",
                    "|---|---:|" + "---:|" * len(modes)]

    def line(label, key, fmt, ratio_key=None):
        cells = [_f(ref.get(key), fmt)]
        for m in modes:
            row = rows[f"{model}/{m}"]
            r = ratios[m].get(ratio_key) if ratio_key else None
            cells.append(f"{_f(row.get(key), fmt)}" + (f" (**{r:.2f}×**)" if r else ""))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")

    line("train step, ms (authors' ÷ nvs)", "train_ms", ".0f", "train_speedup")
    line("train GFLOP per sample", "train_gflop_per_sample", ".1f", "train_gflop_per_sample_ratio")
    line("train peak MB", "train_peak_mb", ".0f", "train_peak_mb_ratio")
    line("novel view, ms/image", "eval_ms_per_image", ".1f", "novel_view_speedup")
    line("novel view GFLOP per image", "eval_gflop_per_image", ".1f", "eval_gflop_per_image_ratio")
    line("novel view peak MB", "eval_peak_mb", ".0f", "eval_peak_mb_ratio")
    lines.append(f"| their eval.py forward (the whole training forward), ms/image | "
                 f"{_f(ref.get('eval_path_ms_per_image'), '.1f')} | "
                 + " | ".join(f"(**{_f(ratios[m].get('eval_path_speedup'), '.2f')}×** nvs's novel view)"
                              for m in modes) + " |")
    return lines + ["", "The authors' train step is one iteration of their train.py (set_input, forward, "
                    "optimize_parameters: zero_grad, backward_G, Adam step); their novel view calls their encode, "
                    "transform, depthdecode, inverse_warp (×4) and decode under no_grad in eval mode; their eval.py "
                    "runs the whole training forward instead. Ratios: authors' ÷ nvs (> 1: nvs is faster, does "
                    "fewer FLOPs, needs less memory).", ""]


def markdown(report: dict) -> str:
    h = report["header"]
    lines = [f"# Benchmark on {h['device']}", "", provenance_markdown(h), ""]
    p = report.get("peak")
    if p:
        lines += [f"Measured peak: bf16 matmul {p['bf16_matmul_gflops']:.0f} GFLOP/s, bf16 channels_last 3×3 conv "
                  f"{p['bf16_conv3x3_gflops']:.0f} GFLOP/s.", ""]
    lines += ["Train: one optimiser step on a synthetic batch of the data contract (forward, `NVSModule.loss`, "
              "backward, Adam) as training runs it; eval: the novel view of the eval batch under `no_grad`. Medians "
              "over interleaved repeats (every contender of a size once per round). Peak memory: what one call "
              "allocates at most (CPU: rise of peak RSS after the heap is trimmed) plus parameters, buffers and "
              "optimiser state. FLOPs: `torch.utils.flop_counter` (convolutions and matmuls, forward and "
              "backward). Modes: fp32 NCHW eager (the paper code's arithmetic), cl = channels_last, bf16 = "
              "autocast, compile = bf16_cl with `torch.compile` of the step's forward and losses.", ""]
    conv_peak = (p or {}).get("bf16_conv3x3_gflops")
    for block in report["sizes"]:
        lines += reference_table(block)
        lines += size_table(block, conv_peak)
    lines += accuracy_section(Path(h.get("precision_csv") or "results/precision.csv"))
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
