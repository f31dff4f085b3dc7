"""The speed goals (issue: fast on the CPUs people have), each read off one bench report: met, or by how much not and
what bounds it.

What bounds a goal is computed from the report's own numbers: the FLOPs of the step (``torch.utils.flop_counter``),
its time, and the machine's measured peak of the row's mode. A goal that needs more than the peak allows is bounded by
the arithmetic of this machine; one within it is bounded by how far the step runs below the peak. Where a profile of
the same step is at hand (``python -m nvs.bench profile=[64] profile_mode=fp32``, which writes
``profile_<device>_<size>[_<model>][_<mode>].json``), the time the step spends outside convolutions and matmuls is
read from it.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from nvs.bench.measure import mode_peak
from nvs.bench.run import REFERENCE, versus_reference
from nvs.bench.viewer_goal import viewer_goal_lines

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


def share_bound(row: dict, batch: int, peak: float, goal: float, profile: dict | None) -> str:
    """Why a training step runs at less than ``goal`` of ``peak``: the text after "not met".

    Without a profile: the time the goal allows against the time measured. With one (its ``matmul_conv_share``: the
    share of the step's self time in convolutions and matmuls): the share the step would reach were those at the peak
    and the rest unchanged; below the goal, the rest bounds it, else the convolutions' own rate at these shapes.
    """
    ms, flop = row["train_ms"], row["train_gflop_per_sample"] * batch
    allowed = flop / (goal * peak) * 1000
    short = 100 * (goal - flop / (ms / 1000) / peak)
    points = f"{short:.1f}" if short < 1 else f"{short:.0f}"  # a step just short of the goal is not "short by 0"
    text = (f"short by {points} percentage point{'s' if points != '1' else ''}: the goal allows {allowed:.0f} ms for "
            f"the step's {flop:.0f} GFLOP, it took {ms:.0f} ms")
    if not profile:
        return (f"{text}; no profile of this step beside the report (`python -m nvs.bench profile=[{row['size']}] "
                f"profile_model={row['model']} profile_mode={row['mode']}` itemises the rest)")
    conv = profile["matmul_conv_share"]
    other_ms, conv_ms = ms * (1 - conv), ms * conv
    at_peak = flop / peak * 1000
    best = at_peak / (at_peak + other_ms)
    text += (f"; in its profile (`{profile.get('file', 'profile')}`), convolutions and matmuls take "
             f"{100 * conv:.0f}% of the step's time and the rest (norms, element-wise ops, losses, the optimiser) "
             f"{100 * (1 - conv):.0f}%")
    if best < goal:
        return (f"{text}: with the convolutions at the peak the step would reach {100 * best:.0f}%, so the rest "
                "bounds it")
    rate = flop / (conv_ms / 1000)
    return (f"{text}: the convolutions themselves run at {rate:.0f} GFLOP/s, {100 * rate / peak:.0f}% of the probe's "
            f"peak, on this network's shapes (channel counts and sizes other than the probe's)")


def ratio_bound(ours_ms: float, ours_gflop: float, theirs_ms: float, theirs_gflop: float, peak: float,
                their_peak: float, goal: float) -> str:
    """Why nvs is less than ``goal``× faster than the authors' code on one task: the text after "not met".

    The speed-up is the FLOP ratio times the ratio of the two achieved rates (each of its own mode's peak: ``peak``
    for nvs's, ``their_peak`` for the authors' fp32 NCHW); nvs at 100% of its peak is the most this machine allows.
    """
    ratio = theirs_ms / ours_ms
    at_peak = ours_gflop / peak * 1000
    most = theirs_ms / at_peak
    flops = (f"{theirs_gflop / ours_gflop:.2f}× fewer FLOPs" if theirs_gflop > 1.01 * ours_gflop else
             "the same FLOPs" if theirs_gflop > 0.99 * ours_gflop else f"{ours_gflop / theirs_gflop:.2f}× more FLOPs")
    text = (f"short by {goal / ratio:.2f}×: nvs does {flops} and runs at "
            f"{100 * ours_gflop / (ours_ms / 1000) / peak:.0f}% of its mode's peak, the authors' code at "
            f"{100 * theirs_gflop / (theirs_ms / 1000) / their_peak:.0f}% of its own; at 100% nvs would take "
            f"{at_peak:.0f} ms, {most:.2f}× the authors'")
    if most < goal:
        return f"{text}: the goal is beyond this machine's peak, so its arithmetic bounds it"
    return f"{text}: within this machine's peak, so nvs's rate bounds it (the goal needs {100 * goal / most:.0f}%)"


def goal_lines(report: dict) -> list[str]:
    """Markdown bullet lines, one per goal and size that this report measured."""
    peaks = report.get("peak") or {}
    profiles = report.get("profiles") or {}
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
                line = (f"- {size}², {model} {task}: the default (auto → {auto}) is {ratio:.2f}× the fastest mode "
                        f"({best}); goal ≤ {WITHIN_FASTEST:.2f}×: {_mark(ratio <= WITHIN_FASTEST)}")
                if ratio > WITHIN_FASTEST:
                    line += (f", short by {ratio / WITHIN_FASTEST:.2f}×: the probe that chose {auto} "
                             f"({(block.get('auto') or {}).get('reason', 'no reason recorded')}) ranks the modes "
                             f"otherwise than this {task} at {size}²")
                lines.append(line)
        peak_cl = peaks.get("fp32_conv_cl_gflops")
        if size == 64 and peak_cl:
            for mode in ("fp32", "cl"):
                row = rows.get(mode, {})
                ach = row.get("train_achieved_gflops")
                if ach:
                    share = ach / peak_cl
                    ok = share >= FP32_64_OF_CL_PEAK
                    line = (f"- 64², {model} {mode} training step: {ach:.0f} GFLOP/s = {100 * share:.0f}% of the "
                            f"fp32 channels_last conv peak ({peak_cl:.0f}); goal ≥ {100 * FP32_64_OF_CL_PEAK:.0f}%: "
                            f"{_mark(ok)}")
                    if not ok:
                        line += ", " + share_bound({**row, "size": size}, block["train_batch"], peak_cl,
                                                   FP32_64_OF_CL_PEAK, profiles.get(f"{size}/{model}/{mode}"))
                    lines.append(line)
        if size == 128 and auto in rows:
            row = rows[auto]
            ach, peak = row.get("train_achieved_gflops"), mode_peak(peaks, auto)
            if ach and peak:
                share = ach / peak
                line = (f"- 128², {model} {auto} training step: {100 * share:.0f}% of its mode's conv peak; "
                        f"goal ≥ {100 * STEP_128_OF_PEAK:.0f}%: {_mark(share >= STEP_128_OF_PEAK)}")
                if share < STEP_128_OF_PEAK:
                    line += ", " + share_bound({**row, "size": size}, block["train_batch"], peak, STEP_128_OF_PEAK,
                                               profiles.get(f"{size}/{model}/{auto}"))
                lines.append(line)
        if f"{REFERENCE}/fp32" in block["rows"]:
            lines += _versus_authors(block, peaks)
    lines += viewer_goal_lines(report.get("viewer") or [], peaks)
    return (["## Goals", "", *lines, ""]) if lines else []


def _versus_authors(block: dict, peaks: dict) -> list[str]:
    out = []
    ref = block["rows"][f"{REFERENCE}/fp32"]
    their_peak = mode_peak(peaks, "fp32")
    for mode, r in versus_reference(block["rows"], "full").items():
        row = block["rows"][f"full/{mode}"]
        train, view = r.get("train_speedup"), r.get("novel_view_speedup")
        peak = mode_peak(peaks, mode)
        share = row.get("eval_achieved_gflops", 0) / peak if peak else None
        if train:
            line = (f"- {block['size']}², full {mode} against the authors' code: training step {train:.2f}× faster; "
                    f"goal ≥ {TRAIN_VS_AUTHORS:g}×: {_mark(train >= TRAIN_VS_AUTHORS)}")
            if train < TRAIN_VS_AUTHORS and peak and their_peak and row.get("train_gflop_per_sample") and ref.get(
                    "train_gflop_per_sample"):
                batch = block["train_batch"]
                line += ", " + ratio_bound(row["train_ms"], row["train_gflop_per_sample"] * batch, ref["train_ms"],
                                           ref["train_gflop_per_sample"] * batch, peak, their_peak,
                                           TRAIN_VS_AUTHORS)
            out.append(line)
        if view:
            bound = f"; it runs at {100 * share:.0f}% of its mode's conv peak" if share else ""
            line = (f"- {block['size']}², full {mode} novel view {view:.2f}× the authors'{bound}; goal ≥ "
                    f"{VIEW_VS_AUTHORS:g}×: {_mark(view >= VIEW_VS_AUTHORS)}")
            flops = row.get("eval_gflop_per_image") and ref.get("eval_gflop_per_image")
            if view < VIEW_VS_AUTHORS and peak and their_peak and flops:
                line += ", " + ratio_bound(row["eval_ms_per_image"], row["eval_gflop_per_image"],
                                           ref["eval_ms_per_image"], ref["eval_gflop_per_image"], peak,
                                           their_peak, VIEW_VS_AUTHORS)
            out.append(line)
    return out


def profile_shares(out_dir: str, slug: str) -> dict[str, dict]:
    """{"size/model/mode": {"matmul_conv_share", "file"}} of the profiles beside a report (what bounds a goal)."""
    shares = {}
    for path in sorted(Path(out_dir).glob(f"profile_{slug}_*.json")):
        try:
            prof = json.loads(path.read_text())
            shares[f"{prof['size']}/{prof['model']}/{prof['mode']}"] = {
                "matmul_conv_share": float(prof["matmul_conv_share"]), "file": path.name}
        except (OSError, ValueError, KeyError, TypeError):
            print(f"{path}: not a profile this bench wrote; ignored", file=sys.stderr)
    return shares
