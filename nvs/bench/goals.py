"""The speed goals (issue: fast on the CPUs people have), each read off one bench report: met, or by how much not."""

from __future__ import annotations

from nvs.bench.measure import MODE_PEAK
from nvs.bench.run import REFERENCE, versus_reference

# (what, goal) -- the thresholds the report checks
WITHIN_FASTEST = 1.10
FP32_64_OF_CL_PEAK = 0.60
STEP_128_OF_PEAK = 0.70
TRAIN_VS_AUTHORS = 4.0
VIEW_VS_AUTHORS = 2.5
FULL_MODELS = ("full_vgg_native", "full")  # the demo's network first, then the code's VGG resize


def _rows(block: dict, model: str) -> dict[str, dict]:
    return {r["mode"]: r for r in block["rows"].values() if r["model"] == model and "error" not in r}


def _full(block: dict) -> str | None:
    return next((m for m in FULL_MODELS if _rows(block, m)), None)


def _mark(ok: bool) -> str:
    return "**met**" if ok else "**not met**"


def goal_lines(report: dict) -> list[str]:
    """Markdown bullet lines, one per goal and size that this report measured."""
    peaks = report.get("peak") or {}
    lines: list[str] = []
    for block in report["sizes"]:
        size, auto = block["size"], (block.get("auto") or {}).get("mode")
        model = _full(block)
        if model is None:
            continue
        rows = _rows(block, model)
        for task, key in (("training step", "train_ms"), ("novel view", "eval_ms_per_image")):
            timed = {m: r[key] for m, r in rows.items() if r.get(key) and m != "compile"}
            if auto in timed:
                best = min(timed, key=timed.get)
                ratio = timed[auto] / timed[best]
                lines.append(f"- {size}², {model} {task}: the default (auto → {auto}) is {ratio:.2f}× the fastest "
                             f"mode ({best}); goal ≤ {WITHIN_FASTEST:.2f}×: {_mark(ratio <= WITHIN_FASTEST)}")
        peak_cl = peaks.get("fp32_conv_cl_gflops")
        if size == 64 and peak_cl:
            for mode in ("fp32", "cl"):
                ach = rows.get(mode, {}).get("train_achieved_gflops")
                if ach:
                    share = ach / peak_cl
                    lines.append(f"- 64², {model} {mode} training step: {ach:.0f} GFLOP/s = {100 * share:.0f}% of "
                                 f"the fp32 channels_last conv peak ({peak_cl:.0f}); goal ≥ "
                                 f"{100 * FP32_64_OF_CL_PEAK:.0f}%: {_mark(share >= FP32_64_OF_CL_PEAK)}")
        if size == 128 and auto in rows:
            ach = rows[auto].get("train_achieved_gflops")
            peak = peaks.get(MODE_PEAK.get(auto, "") + "_gflops")
            if ach and peak:
                share = ach / peak
                lines.append(f"- 128², {model} {auto} training step: {100 * share:.0f}% of its mode's conv peak; "
                             f"goal ≥ {100 * STEP_128_OF_PEAK:.0f}%: {_mark(share >= STEP_128_OF_PEAK)}")
        if f"{REFERENCE}/fp32" in block["rows"]:
            lines += _versus_authors(block, peaks)
    return (["## Goals", "", *lines, ""]) if lines else []


def _versus_authors(block: dict, peaks: dict) -> list[str]:
    out = []
    ratios = versus_reference(block["rows"], "full")
    for mode, r in ratios.items():
        row = block["rows"][f"full/{mode}"]
        train, view = r.get("train_speedup"), r.get("novel_view_speedup")
        peak = peaks.get(MODE_PEAK.get(mode, "") + "_gflops")
        share = row.get("eval_achieved_gflops", 0) / peak if peak else None
        if train:
            out.append(f"- {block['size']}², full {mode} against the authors' code: training step {train:.2f}× "
                       f"faster; goal ≥ {TRAIN_VS_AUTHORS:g}×: {_mark(train >= TRAIN_VS_AUTHORS)}")
        if view:
            bound = f"; it runs at {100 * share:.0f}% of its mode's conv peak" if share else ""
            out.append(f"- {block['size']}², full {mode} novel view {view:.2f}× the authors'{bound}; goal ≥ "
                       f"{VIEW_VS_AUTHORS:g}×: {_mark(view >= VIEW_VS_AUTHORS)}")
    return out
