"""precision=auto: the probe, its cache, the choice and its warning, and where the choice reaches a run."""

from __future__ import annotations

import json

import pytest
import torch

from nvs.run import precision
from nvs.run.precision import choose, normalise

# A CPU that emulates bf16 (the AVX2-only EPYC: ~10x) and one that has it natively.
EMULATED = {"fp32": 10.0, "cl": 9.0, "bf16_cl": 95.0}
NATIVE = {"fp32": 10.0, "cl": 9.5, "bf16_cl": 6.0}


@pytest.fixture
def probed(monkeypatch):
    """Replace the timed probe with fixed timings; returns a setter."""
    state = {"ms": NATIVE}
    monkeypatch.setattr(precision, "probe", lambda refresh=False: dict(state["ms"]))
    monkeypatch.setattr(precision.torch.cuda, "is_available", lambda: False)

    def use(ms):
        state["ms"] = ms
    return use


def test_auto_picks_the_fastest_mode_of_the_probe(probed):
    probed(NATIVE)
    c = choose()
    assert (c.mode, c.precision, c.channels_last) == ("bf16_cl", "bf16-mixed", True)
    assert c.autocast_dtype is torch.bfloat16 and c.requested == "auto" and c.probe_ms == NATIVE
    probed(EMULATED)
    c = choose()
    assert (c.mode, c.precision, c.channels_last) == ("cl", "32-true", True) and c.autocast_dtype is None
    assert "fastest" in c.reason and "bf16_cl 10.56x" in c.reason
    assert c.line().startswith("precision: cl (32-true, channels_last): ")


def test_an_explicit_precision_is_honoured_and_emulated_bf16_warns_once_with_the_slowdown(probed):
    probed(EMULATED)
    said = []
    c = choose("bf16-mixed", warn=said.append)
    assert (c.precision, c.channels_last, c.mode) == ("bf16-mixed", True, "bf16_cl")
    assert len(said) == 1 and "10.6x slower than cl" in said[0] and said[0].startswith("warning: ")
    assert "measured 10.6x slower" in c.reason
    said.clear()
    probed(NATIVE)
    assert choose("bf16", warn=said.append).precision == "bf16-mixed" and said == []
    # fp32 asked, layout left to the probe: the faster of NCHW and channels_last; a given layout is kept
    probed({"fp32": 8.0, "cl": 9.0, "bf16_cl": 6.0})
    assert (choose("32").precision, choose("32").channels_last) == ("32-true", False)
    assert choose("32-true", channels_last=True).channels_last is True
    assert choose("auto", channels_last=False).precision == "32-true"  # the one mode in NCHW


def test_cuda_picks_bf16_where_the_device_supports_it(monkeypatch):
    monkeypatch.setattr(precision.torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(precision, "probe", lambda refresh=False: pytest.fail("no CPU probe on CUDA"))
    monkeypatch.setattr(precision.torch.cuda, "is_bf16_supported", lambda: True)
    assert (choose().precision, choose().channels_last) == ("bf16-mixed", True)
    monkeypatch.setattr(precision.torch.cuda, "is_bf16_supported", lambda: False)
    assert choose().precision == "32-true"
    assert choose("16-mixed").precision == "16-mixed"


def test_an_unknown_precision_is_a_value_error_naming_the_choices():
    assert normalise("32") == "32-true" and normalise("bf16") == "bf16-mixed" and normalise("auto") == "auto"
    with pytest.raises(ValueError, match="expected auto or one of"):
        normalise("fp33")


def test_the_probe_runs_once_per_machine_and_is_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("NVS_CACHE_DIR", str(tmp_path))
    calls = []
    real = precision._time_modes

    def counted(*args):
        calls.append(args)
        return real(*args)

    monkeypatch.setattr(precision, "_time_modes", counted)
    first = precision.probe()
    assert set(first) == set(precision.MODES) and all(v > 0 for v in first.values())
    assert precision.probe() == first and len(calls) == 1  # from the cache
    cache = json.loads((tmp_path / "precision.json").read_text())
    entry = cache[precision.machine_key()]
    assert list(cache) == [precision.machine_key()] and entry["ms"] == first
    assert entry["rounds"] == precision._PROBE_ROUNDS and "v2" in precision.machine_key()
    precision.probe(refresh=True)
    assert len(calls) == 2


def test_a_probe_taken_on_a_busy_machine_is_taken_again_once_it_is_quiet(tmp_path, monkeypatch):
    """`make test`'s workers loading the cores skew the modes apart; the next quiet run measures them again."""
    monkeypatch.setenv("NVS_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(precision, "_cores", lambda: 2)
    monkeypatch.setattr(precision.torch.cuda, "is_available", lambda: False)
    timings = iter([{"fp32": 336.0, "cl": 149.0, "bf16_cl": 1024.0},  # busy: cl looks 2.26x faster
                    {"fp32": 39.0, "cl": 35.0, "bf16_cl": 466.0},  # quiet
                    {"fp32": 1.0, "cl": 2.0, "bf16_cl": 3.0}])  # never asked for
    calls = []
    monkeypatch.setattr(precision, "_time_modes", lambda *a: calls.append(1) or dict(next(timings)))
    load = {"now": 3.37}
    monkeypatch.setattr(precision, "load_average", lambda: load["now"])
    assert precision.busy(1.5) and not precision.busy(1.49) and not precision.busy(None)

    busy_choice = choose("auto")
    assert busy_choice.mode == "cl" and "probed on a busy machine (load 3.37)" in busy_choice.line()
    assert choose("auto").probe_ms["fp32"] == 336.0 and len(calls) == 1  # still busy: the kept probe serves
    load["now"] = 0.4
    quiet = choose("auto")
    assert len(calls) == 2 and quiet.probe_ms["fp32"] == 39.0 and "busy" not in quiet.line()
    entry = json.loads((tmp_path / "precision.json").read_text())[precision.machine_key()]
    assert entry["load_avg_1min"] == 0.4 and entry["ms"]["cl"] == 35.0  # the quiet probe replaced the busy one
    load["now"] = 5.0
    assert choose("auto").probe_ms["fp32"] == 39.0 and len(calls) == 2  # a quiet probe is kept whatever the load


def test_the_probe_interleaves_the_modes_keeps_each_ones_fastest_round_and_drops_a_far_slower_mode(monkeypatch):
    """A burst of load in one round costs that round only; an emulated bf16 (10x) is timed in two rounds only."""
    order = []
    cost = {"fp32": [9.0, 5.0, 30.0, 5.5, 6.0, 5.0], "cl": [9.0, 4.5, 30.0, 4.8, 4.6, 4.7],
            "bf16_cl": [90.0, 50.0, 300.0, 50.0, 50.0, 50.0]}
    clock = {"t": 0.0}

    def fake_perf_counter():
        return clock["t"]

    real_conv = torch.nn.Conv2d.forward

    def timed_conv(self, x):
        mode = ("bf16_cl" if torch.is_autocast_enabled("cpu") else
                "cl" if x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous() else "fp32")
        if not order or order[-1] != mode:
            order.append(mode)
            clock["t"] += cost[mode][sum(1 for m in order if m == mode) - 1] / 1000
        return real_conv(self, x)

    monkeypatch.setattr(precision.time, "perf_counter", fake_perf_counter)
    monkeypatch.setattr(torch.nn.Conv2d, "forward", timed_conv)
    convs = [torch.nn.Conv2d(4, 4, 3, padding=1)]
    inputs = [torch.randn(1, 4, 6, 6)]
    ms = precision._time_modes(convs, inputs, 5)
    assert order[:9] == ["fp32", "cl", "bf16_cl"] * 3  # the warm-up round, then two timed rounds of every mode
    assert order.count("bf16_cl") == 3 and order[9:] == ["fp32", "cl"] * 3
    assert ms == pytest.approx({"fp32": 5.0, "cl": 4.5, "bf16_cl": 50.0})


def test_the_machine_key_tells_apart_cpus_that_share_a_model_name(monkeypatch):
    zen3 = {"model name": "AMD EPYC", "cpu family": "25", "model": "1", "stepping": "1", "flags": "avx2 fma"}
    zen4 = {**zen3, "model": "17", "flags": "avx2 avx512f avx512_bf16"}
    monkeypatch.setattr(precision, "_cpuinfo", lambda: zen3)
    key3 = precision.machine_key()
    monkeypatch.setattr(precision, "_cpuinfo", lambda: zen4)
    key4 = precision.machine_key()
    assert key3 != key4 and "no-bf16" in key3 and "avx512_bf16" in key4 and torch.__version__ in key4


def test_an_unwritable_cache_only_costs_the_probe(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setenv("NVS_CACHE_DIR", str(blocker / "sub"))
    assert set(precision.probe()) == set(precision.MODES)


def test_the_sweep_refuses_a_pinned_mode_this_machine_emulates(probed):
    from nvs.core.errors import UserError
    from nvs.sweep.cost_check import check_precision

    class FakeJob:
        kind = "train"
        fingerprint = {"trainer": {"precision": "bf16-mixed", "accelerator": "auto"}, "channels_last": True}

    said = []
    probed(EMULATED)
    with pytest.raises(UserError, match=r"9\.0x|10\.6x") as err:
        check_precision([FakeJob()], 1, remote=False, accept=False, log=said.append)
    assert "--accept-precision" in str(err.value) and "native bf16" in str(err.value)
    assert "10.56x the fastest (cl)" in said[0]
    check_precision([FakeJob()], 1, remote=False, accept=True, log=said.append)  # accepted: runs, says so
    said.clear()
    probed(NATIVE)
    check_precision([FakeJob()], 1, remote=False, accept=False, log=said.append)
    assert "1.00x the fastest (bf16_cl)" in said[0]
    said.clear()
    check_precision([FakeJob()], 1, remote=True, accept=False, log=said.append)
    assert "cannot measure" in said[0]


def test_evaluate_keeps_a_reference_model_exact_and_reads_null_as_the_runs_own(probed):
    from omegaconf import OmegaConf

    from nvs.evaluate import evaluation_precision

    probed(NATIVE)
    run = OmegaConf.create({"trainer": {"precision": "32-true"}, "channels_last": False})
    reference = OmegaConf.create({"precision": "auto", "ckpt_path": None})
    assert (evaluation_precision(reference, run).precision, evaluation_precision(reference, run).channels_last) \
        == ("32-true", False)
    trained = OmegaConf.create({"precision": "auto", "ckpt_path": "x.ckpt"})
    assert evaluation_precision(trained, run).precision == "bf16-mixed"
    own = OmegaConf.create({"precision": None, "ckpt_path": "x.ckpt"})
    assert evaluation_precision(own, run).precision == "32-true"


def test_committed_reference_jobs_stay_valid_across_the_evaluate_default_change():
    from nvs.sweep.jobs import config_changes

    assert config_changes({"precision": None, "seed": 0}, {"precision": "auto", "seed": 0}) == []
    assert config_changes({"precision": "32-true"}, {"precision": "auto"}) == ["precision"]
    assert config_changes({"trainer": {"precision": None}}, {"trainer": {"precision": "auto"}}) \
        == ["trainer.precision"]
