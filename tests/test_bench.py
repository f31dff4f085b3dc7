"""The benchmark: its measuring primitives against hand-computed cases, its config checks, the authors' code path and
one end-to-end run at a tiny size. Speed itself is not asserted (benchmarks measure, tests check behaviour)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import reference_code as rc
import nvs.bench.measure as measure
from nvs.core.errors import UserError
from nvs.run.compose import compose

REPO = Path(__file__).resolve().parents[1]


def test_flop_count_of_a_convolution_is_the_hand_count():
    conv = torch.nn.Conv2d(3, 8, 3, padding=1)
    x = torch.randn(2, 3, 16, 16)
    assert measure.flops(lambda: conv(x)) == 2 * 2 * 3 * 8 * 9 * 16 * 16
    # backward: the input and weight gradients, each as many FLOPs as the forward
    assert measure.flops(lambda: conv(x.requires_grad_()).sum().backward()) == 3 * 2 * 2 * 3 * 8 * 9 * 16 * 16


def test_state_bytes_counts_parameters_and_adam_state_once():
    lin = torch.nn.Linear(100, 50)
    opt = torch.optim.Adam(lin.parameters())
    n = 100 * 50 + 50
    assert measure.state_bytes([lin, lin]) == 4 * n
    lin(torch.randn(3, 100)).sum().backward()
    opt.step()
    assert measure.state_bytes([lin], [opt]) == 4 * n * 3 + 2 * 4  # + exp_avg, exp_avg_sq, two scalar steps


def test_peak_memory_sees_a_temporary_allocation():
    def fn():
        t = torch.ones(50 * 2**20 // 4)  # 50 MB, touched
        return float(t[-1])

    peak = measure.peak_mb(fn, torch.device("cpu"))
    if peak is None:
        pytest.skip("no /proc/self/clear_refs here")
    assert 45 < peak < 120, peak
    assert 45 + 10 < measure.peak_mb(fn, torch.device("cpu"), persistent_bytes=10 * 2**20) < 130


def test_interleaved_timing_goes_round_robin_and_reports_a_failure():
    calls = []

    def failing():
        calls.append("bad")
        raise RuntimeError("broken option\nsecond line")

    fns = {"a": lambda: calls.append("a"), "b": lambda: calls.append("b"), "bad": failing}
    out = measure.interleaved(fns, torch.device("cpu"), warmup=1, repeats=3)
    assert calls == ["a", "b", "bad"] + ["a", "b"] * 3
    assert out["bad"] == {"error": "RuntimeError: broken option"}
    assert out["a"]["n"] == 3 and out["a"]["min_ms"] <= out["a"]["median_ms"] <= out["a"]["max_ms"]


def _bench_cfg(*overrides):
    return compose("bench", list(overrides))


def test_the_peaks_are_timed_again_at_the_end_and_the_larger_kept(monkeypatch):
    """A machine that drifts over a run: each kind keeps its faster timing, and a kind whose one call took seconds
    (emulated bf16 matmul) is not timed again."""
    from nvs.bench.report import markdown

    asked = []

    def fake_peak(device, repeats=7, kinds=None):
        asked.append(set(kinds))
        return {"fp32_conv_gflops": 80.0, "fp32_conv_cl_gflops": 150.0}

    monkeypatch.setattr(measure, "machine_peak", fake_peak)
    start = {"fp32_conv_gflops": 100.0, "fp32_conv_cl_gflops": 120.0, "bf16_matmul_gflops": 0.3}
    best, end = measure.peak_again(torch.device("cpu"), start)
    assert asked == [{"fp32_conv", "fp32_conv_cl"}]  # 2*2048^3 FLOP at 0.3 GFLOP/s: ~57 s a call, kept
    assert best == {"fp32_conv_gflops": 100.0, "fp32_conv_cl_gflops": 150.0, "bf16_matmul_gflops": 0.3}
    report = {"header": {"device": "cpu", "command": "x"}, "sizes": [], "peak": best, "peak_start": start,
              "peak_end": end}
    md = markdown(report)
    assert "fp32 3×3 conv channels_last 150" in md and "fp32_conv 100 → 80, fp32_conv_cl 120 → 150" in md


def test_plan_pairs_sizes_with_batches_and_names_bad_keys():
    from nvs.bench.__main__ import plan

    pairs, models = plan(_bench_cfg())
    assert pairs == [(64, 8), (128, 8), (256, 4)]  # the studies' batch at 64² and 128²
    assert list(models) == ["full", "tatarchenko", "chen", "sun"]
    assert plan(_bench_cfg("image_size=128", "train_batch=16"))[0] == [(128, 16)]
    assert plan(_bench_cfg("image_size=256"))[0] == [(256, 4)]  # one of sizes: the list's batch there
    assert plan(_bench_cfg("sizes=[64,256]", "train_batch=2"))[0] == [(64, 2), (256, 2)]
    for bad, key in ((["train_batch=[8,8]"], "'train_batch'"), (["modes=[fp32,fast]"], "'modes': unknown"),
                     (["only=[full,bogus]"], "'only'"), (["sizes=[64,0]", "train_batch=8"], "'sizes'"),
                     (["repeats=0"], "'repeats'"), (["image_size=abc"], "'image_size': expected a positive"),
                     (["image_size=96"], "image_size=96 is not one of sizes .* give train_batch=<n>")):
        with pytest.raises(UserError, match=key):
            plan(_bench_cfg(*bad))


def test_every_bench_model_option_composes():
    cfg = _bench_cfg()
    from nvs.bench.contenders import train_config

    for name, overrides in cfg.models.items():
        tcfg = train_config(list(overrides), 64, str(REPO), True)
        assert tcfg.data.size == 64, name


def test_profile_sums_copies_and_ranks_operators():
    from nvs.bench.profile import markdown, profile_step

    prof = profile_step(["experiment=tatarchenko_chairs"], "bf16_cl", 64, 2, torch.device("cpu"), str(REPO),
                        warmup=1, steps=1)
    selfs = [ms for _, ms, _ in prof["ops"]]
    assert selfs == sorted(selfs, reverse=True) and prof["total_ms"] == pytest.approx(sum(selfs))
    names = {name for name, _, _ in prof["ops"]}
    assert {"aten::convolution_backward", "aten::copy_"} <= names or "aten::mkldnn_convolution" in names
    assert prof["copies"] and all(v >= 0 for v in prof["copies"].values())
    # autocast casts the fp32 weights and inputs to bf16: conversions are among the copies
    assert any(k.startswith("dtype/layout") for k in prof["copies"])
    # the share the goals read: the counted operators' self time over the step's
    kernels = ("aten::convolution_backward", "aten::mkldnn_convolution")
    counted = sum(ms for name, ms, _ in prof["ops"] if name in kernels)
    assert counted / prof["total_ms"] <= prof["matmul_conv_share"] < 1
    text = markdown({"command": "x"}, prof)
    assert "| **all copies** |" in text and "## Top 30 operators by self time" in text


def test_bench_writes_report_with_consistent_numbers(tmp_path):
    cmd = [sys.executable, "-m", "nvs.bench", "image_size=64", "train_batch=2", "only=[tatarchenko]",
           "modes=[fp32,bf16_cl]", "repeats=1", "warmup=0", "throughput_batch=2", "measure_peak=false",
           f"out_dir={tmp_path}", f"paths.log_dir={tmp_path}/logs"]
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    report = json.loads(next(tmp_path.glob("*.json")).read_text())
    assert report["header"]["command"].startswith("python -m nvs.bench image_size=64")
    (block,) = report["sizes"]
    assert (block["size"], block["train_batch"]) == (64, 2)
    fp32, fast = block["rows"]["tatarchenko/fp32"], block["rows"]["tatarchenko/bf16_cl"]
    for row in (fp32, fast):
        assert row["train_samples_per_s"] == pytest.approx(2000 / row["train"]["median_ms"])
        assert row["train_peak_mb"] > row["params"] * 4 * 3 / 2**20  # weights + Adam's two moments at least
    # the mode changes the arithmetic, not the work: one FLOP count; backward is counted (about twice the forward,
    # less the first layer's input gradient, which nothing needs)
    assert fast["train_gflop_per_sample"] == fp32["train_gflop_per_sample"] > 2.5 * fp32["eval_gflop_per_image"]
    assert fast["train_speedup"] == pytest.approx(fp32["train"]["median_ms"] / fast["train"]["median_ms"])
    md = next(tmp_path.glob("*.md")).read_text()
    assert "## 64², train batch 2, eval batch 1" in md and "| tatarchenko | bf16_cl |" in md and "Git SHA" in md


def test_a_mode_slower_than_the_fastest_for_every_model_is_dropped_from_the_larger_sizes():
    from nvs.bench.report import size_table
    from nvs.bench.run import REFERENCE, slow_modes

    def row(model, mode, ms):
        t = {"median_ms": ms, "min_ms": ms, "max_ms": ms}
        return {"model": model, "mode": mode, "params": 1e6, "train": t, "train_ms": ms, "train_samples_per_s": 1.0}

    times = {("full", "fp32"): 2500, ("full", "cl"): 2300, ("full", "bf16_cl"): 25000,
             ("chen", "fp32"): 310, ("chen", "cl"): 280, ("chen", "bf16_cl"): 3400, (REFERENCE, "fp32"): 100}
    block = {"size": 64, "train_batch": 8, "eval_batch": 1,
             "rows": {f"{m}/{mode}": row(m, mode, ms) for (m, mode), ms in times.items()}}
    slow = slow_modes(block, 4.0)
    assert list(slow) == ["bf16_cl"] and slow["bf16_cl"] == pytest.approx(25000 / 2300)  # the smaller ratio
    assert slow_modes(block, 20.0) == {} and slow_modes(block, None) == {}
    block["rows"]["chen/bf16_cl"]["train_ms"] = 300  # fast for one model: kept (the reference row does not count)
    assert slow_modes(block, 4.0) == {}
    block["dropped"] = {"modes": {"bf16_cl": 12.1}, "factor": 4.0}
    assert "Not timed at the larger sizes: bf16_cl (its training step ≥ 12.1× the fastest mode's here, for every " \
           "model); `drop_slower=4.0`." in "\n".join(size_table(block, {}))


@pytest.mark.skipif(not rc.available(), reason=f"the authors' code is not at {rc.REFERENCE}")
def test_reference_novel_view_is_their_forward_and_their_step_trains():
    from nvs.bench.contenders import make_batches
    from nvs.bench.reference import Reference

    batches = make_batches(256, 1, 1, None, torch.device("cpu"))
    torch.manual_seed(0)
    ref = Reference(rc.REFERENCE, torch.device("cpu"))
    view = Reference.inputs(batches.eval)
    assert view["A"].min() >= -1 and view["A"].max() <= 1
    ours = ref.novel_view(view)
    ref.eval_path(view)  # their eval.py forward leaves its target view in fake_B
    assert ours.shape == (1, 3, 256, 256)
    assert torch.allclose(ours, ref.model.fake_B, atol=1e-6)
    before = ref.model.dec.finalpred.weight.detach().clone()
    ref.train_step(Reference.inputs(batches.train))
    assert not torch.equal(before, ref.model.dec.finalpred.weight)
    from nvs.bench.contenders import train_config
    from nvs.run.build import build_module, parameter_count

    # their three networks are nvs's full model at 256², parameter for parameter
    assert ref.parameter_count() == parameter_count(build_module(train_config([], 256, str(REPO), False)).net)
    assert "models" not in sys.modules or not hasattr(sys.modules["models"], "base_model")  # import undone


def test_reference_path_is_checked():
    from nvs.bench.reference import check_path

    with pytest.raises(UserError, match="not a checkout of the authors' code"):
        check_path(REPO / "nvs")
    assert _bench_cfg().reference is None  # the authors' code is timed only when asked for


def test_accuracy_section_compares_fp32_and_fast_rows(tmp_path):
    import pandas as pd

    from nvs.bench.report import accuracy_section

    path = tmp_path / "precision.csv"
    assert "run `python -m nvs.sweep sweeps/precision.yaml`" in "\n".join(accuracy_section(path))
    rows = [{"row": "precision_fp32_chairs", "status": "done", "l1": 0.200, "ssim_paper": 0.7, "train_wall_s": 300,
             "steps": 500},
            {"row": "precision_fast_chairs", "status": "done", "l1": 0.203, "ssim_paper": 0.7, "train_wall_s": 100,
             "steps": 500},
            {"row": "copy_source_chairs", "status": "done", "l1": 0.21, "ssim_paper": 0.7, "train_wall_s": None,
             "steps": None}]
    pd.DataFrame(rows).to_csv(path, index=False)
    text = "\n".join(accuracy_section(path))
    assert "+1.5%: within the 2% goal" in text and "| fp32 NCHW | 0.2000 |" in text
    rows[1]["l1"] = 0.21
    pd.DataFrame(rows).to_csv(path, index=False)
    assert "+5.0%: NOT within" in "\n".join(accuracy_section(path))
