"""The bench report as Markdown: one table per image size, the authors' code beside nvs, the fast mode's accuracy."""

from __future__ import annotations

from pathlib import Path

from nvs.bench.goals import goal_lines
from nvs.bench.measure import mode_peak
from nvs.bench.run import REFERENCE, versus_reference
from nvs.core.provenance import markdown as provenance_markdown

NAN = float("nan")


def _f(value, fmt: str) -> str:
    return "–" if value is None or value != value else format(value, fmt)


def _pct(achieved, peaks: dict, mode: str) -> str:
    peak = mode_peak(peaks, mode)
    return f"{100 * achieved / peak:.0f}%" if achieved and peak else "–"


def size_table(block: dict, peaks: dict) -> list[str]:
    s, b = block["size"], block["train_batch"]
    thr = block.get("throughput_batch")
    lines = [f"## {s}², train batch {b}, eval batch {block['eval_batch']}", "",
             "| model | mode | params | train ms/step (min–max) | samples/s | × fp32 | eval ms/img | × fp32 | "
             f"img/s @bs{thr or '–'} | peak MB train / eval | GFLOP/sample train | GFLOP/img eval | "
             "train GFLOP/s | train % of mode's peak | eval GFLOP/s | eval % of mode's peak |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in block["rows"].values():
        name = "authors' code" if row["model"] == REFERENCE else row["model"]
        if "error" in row:
            lines.append(f"| {name} | {row['mode']} | failed: {row['error']} |" + " |" * 13)
            continue
        t = row["train"]
        ach, ach_eval = row.get("train_achieved_gflops"), row.get("eval_achieved_gflops")
        lines.append(
            f"| {name} | {row['mode']} | {row['params'] / 1e6:.2f} M | {t['median_ms']:.0f} "
            f"({t['min_ms']:.0f}–{t['max_ms']:.0f}) | {row['train_samples_per_s']:.1f} | "
            f"{_f(row.get('train_speedup'), '.2f')}× | {_f(row.get('eval_ms_per_image'), '.1f')} | "
            f"{_f(row.get('eval_speedup'), '.2f')}× | {_f(row.get('throughput_images_per_s'), '.1f')} | "
            f"{_f(row.get('train_peak_mb'), '.0f')} / {_f(row.get('eval_peak_mb'), '.0f')} | "
            f"{_f(row.get('train_gflop_per_sample'), '.1f')} | {_f(row.get('eval_gflop_per_image'), '.1f')} | "
            f"{_f(ach, '.0f')} | {_pct(ach, peaks, row['mode'])} | {_f(ach_eval, '.0f')} | "
            f"{_pct(ach_eval, peaks, row['mode'])} |")
    dropped = block.get("dropped")
    if dropped:
        lines += ["", "Not timed at the larger sizes: " + ", ".join(
            f"{m} (its training step ≥ {r:.1f}× the fastest mode's here, for every model)"
            for m, r in dropped["modes"].items()) + f"; `drop_slower={dropped['factor']}`."]
    return lines + [""] + auto_lines(block)


def auto_lines(block: dict) -> list[str]:
    """How the mode ``precision=auto`` picks compares with the fastest mode measured here, per model and task."""
    auto = block.get("auto")
    if not auto:
        return []
    lines = [f"precision=auto picks **{auto['mode']}** here ({auto['reason']}). Against the fastest mode this "
             "bench measured (goal: within 10%):", ""]
    models = dict.fromkeys(r["model"] for r in block["rows"].values() if r["model"] != REFERENCE)
    for model in models:
        rows = {r["mode"]: r for r in block["rows"].values() if r["model"] == model and "error" not in r}
        parts = []
        for task, key in (("train", "train_ms"), ("novel view", "eval_ms_per_image")):
            timed = {m: r[key] for m, r in rows.items() if r.get(key) and m != "compile"}
            if auto["mode"] in timed:
                best = min(timed, key=timed.get)
                ratio = timed[auto["mode"]] / timed[best]
                parts.append(f"{task} {ratio:.2f}× the fastest ({best})" + ("" if ratio <= 1.10 else " **> 10%**"))
        if parts:
            lines.append(f"- {model}: " + ", ".join(parts))
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


def _drift(report: dict) -> str:
    """The start and end peaks, where the run timed both (the rows use the larger of each kind)."""
    start, end = report.get("peak_start") or {}, report.get("peak_end") or {}
    both = [k for k in ("fp32_conv", "fp32_conv_cl", "fp32_matmul", "bf16_conv_cl") if f"{k}_gflops" in end
            and f"{k}_gflops" in start]
    if not both:
        return ""
    return (" The larger of two timings, at the start and at the end of the run (" + ", ".join(
        f"{k} {start[k + '_gflops']:.0f} → {end[k + '_gflops']:.0f}" for k in both) + "): the machine's speed drifts.")


def markdown(report: dict, rendered: str | None = None) -> str:
    """The report as Markdown; ``rendered``: a line saying the text was rendered again from the report's JSON."""
    h = report["header"]
    lines = [f"# Benchmark on {h['device']}", "", provenance_markdown(h), ""] + ([rendered, ""] if rendered else [])
    p = report.get("peak") or {}
    if "bf16_conv3x3_gflops" in p:  # reports from before the fp32 peaks
        p = {"bf16_matmul_gflops": p["bf16_matmul_gflops"], "bf16_conv_cl_gflops": p["bf16_conv3x3_gflops"]}
    if p:
        names = {"fp32_matmul": "fp32 matmul", "fp32_conv": "fp32 3×3 conv NCHW", "fp32_conv_cl":
                 "fp32 3×3 conv channels_last", "bf16_matmul": "bf16 matmul", "bf16_conv_cl":
                 "bf16 3×3 conv channels_last"}
        lines += ["Measured peaks (GFLOP/s; a 2048² matmul, a 3×3 64-channel conv at 128², batch 8, forward): "
                  + ", ".join(f"{names[k]} {p[k + '_gflops']:.0f}" for k in names if k + "_gflops" in p)
                  + ". Each row's % is of its own mode's conv peak (fp32 → NCHW, cl → channels_last, bf16 modes → "
                  "bf16 channels_last)." + _drift(report), ""]
    lines += ["Train: one optimiser step on a synthetic batch of the data contract (forward, `NVSModule.loss`, "
              "backward, Adam) as training runs it; eval: the novel view of the eval batch under `no_grad`. Medians "
              "over interleaved repeats (every contender of a size once per round). Peak memory: what one call "
              "allocates at most (CPU: rise of peak RSS after the heap is trimmed) plus parameters, buffers and "
              "optimiser state. FLOPs: `torch.utils.flop_counter` (convolutions and matmuls, forward and "
              "backward). Modes: fp32 NCHW eager (the paper code's arithmetic), cl = channels_last, bf16 = "
              "autocast, compile = bf16_cl with `torch.compile` of the step's forward and losses.", ""]
    lines += goal_lines({**report, "peak": p})
    for block in report["sizes"]:
        lines += reference_table(block)
        lines += size_table(block, p)
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
