"""The real train.yaml composes with every option, and a fast_dev_run trains through it on a fixture dataset."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from nvs.models.reference import REFERENCE_MODELS
from nvs.run.build import build_module, parameter_count
from nvs.run.config_check import check_config
from tests.conftest import CONF_DIR, compose_train, fixture_batch
from tests.run_helpers import cli_in_process, train_in_process

REPO = Path(__file__).resolve().parents[1]


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (Path(CONF_DIR) / group).glob("*.yaml"))


# Trainable parameters of each network at 64^2 (the experiments' size; the data configs add none: depth heads and
# cameras have no weights). A change here is a change of the network: update the pin on purpose.
PARAMS_64 = {"nvs": 11_719_223, "chen": 7_192_537, "sun": 55_737_007, "tatarchenko": 13_012_995}


@pytest.mark.parametrize("experiment", _options("experiment"))
def test_every_experiment_composes_and_builds(experiment, tmp_path):
    cfg = compose_train([f"experiment={experiment}", f"paths.root_dir={tmp_path}"])
    check_config("train", cfg)  # the typed schema takes every experiment
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    module = build_module(cfg)
    prefix = experiment.split("_")[0]
    assert cfg.data.size == 64 and cfg.model.name == (prefix if prefix in PARAMS_64 else "nvs")
    assert parameter_count(module.net) == PARAMS_64[cfg.model.name]


def _package(path: Path) -> tuple[str | None, dict]:
    """(config path the option file writes to, its own keys without the defaults list) of conf/<group>/<option>."""
    own = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    own.pop("defaults", None)
    glob = "# @package _global_" in path.read_text()
    return (None if glob else ".".join(path.relative_to(CONF_DIR).parent.parts)), own


def _contains(whole, part, where: str) -> list[str]:
    """Where ``part`` (a nested dict) differs from ``whole``: one 'key: expected != got' line per leaf."""
    if isinstance(part, dict):
        if not isinstance(whole, dict):
            return [f"{where}: expected a mapping, got {whole!r}"]
        return [line for k, v in part.items() for line in _contains(whole.get(k, "<missing>"), v, f"{where}.{k}")]
    return [] if whole == part else [f"{where}: {part!r} != {whole!r}"]


@pytest.mark.parametrize("group", ["data", "model/skips", "model/depth", "optim", "scheduler", "trainer", "debug"])
def test_every_group_option_composes_to_its_own_values(group, tmp_path):
    """Selecting an option puts every value of its file into the composed config, and the result resolves."""
    for option in _options(group):
        cfg = compose_train([f"{group}={option}", f"paths.root_dir={tmp_path}"])
        package, own = _package(Path(CONF_DIR) / group / f"{option}.yaml")
        assert own, f"{group}/{option} sets nothing"
        node = cfg if package is None else OmegaConf.select(cfg, package)
        diff = _contains(OmegaConf.to_container(node, resolve=False), own, f"{group}={option}")
        assert not diff, "\n".join(diff)
        check_config("train", cfg)  # and the typed schema takes it
        cfg.paths.output_dir = str(tmp_path)
        OmegaConf.resolve(cfg)


def _skip_sizes(encoder, size: int) -> list[int]:
    with torch.no_grad():
        _, feats = encoder(torch.zeros(1, 3, size, size))
    return [feats[k].shape[-1] for k in ("conv0", "conv2", "conv3", "conv4")]


@pytest.mark.parametrize("data", _options("data"))
def test_every_data_size_halves_exactly_through_the_encoder(data):
    """The decoder doubles conv4's map back four times: the skips must be exactly S, S/4, S/8, S/16."""
    from nvs.models.encoder import Encoder

    size = compose_train([f"data={data}"]).data.size
    assert _skip_sizes(Encoder(size), size) == [size, size // 4, size // 8, size // 16]


def test_a_size_the_rule_rejects_does_not_halve_exactly():
    """72 is not a multiple of 16: its conv4 map (4x4: the stride-2 convs round 9 down) doubles back to 64, not 72."""
    from nvs.models.encoder import Encoder

    assert _skip_sizes(Encoder(64), 72) == [72, 18, 9, 4] and 4 * 16 != 72


@pytest.mark.parametrize("size", [48, 72, 100])
def test_sizes_the_network_cannot_take_are_one_clear_error(size, tmp_path):
    """Four halvings down to the latent and back: a size not divisible by 16, or below 64, fails at build time."""
    from nvs.core.errors import UserError

    cfg = compose_train([f"data.size={size}", f"paths.root_dir={tmp_path}", "loss=[recon]"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    with pytest.raises(UserError, match=rf"config 'model': .*image_size={size} must be a multiple of 16 and at least 64"):
        build_module(cfg)


@pytest.mark.parametrize("model", [m for m in _options("model") if m not in REFERENCE_MODELS])
def test_bare_model_option_builds_with_its_own_losses(model, tmp_path):
    """`python -m nvs.train model=<name>` works without naming an experiment: each model brings its loss list."""
    cfg = compose_train([f"model={model}", f"paths.root_dir={tmp_path}"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    module = build_module(cfg)
    loss = module.training_step(fixture_batch(), 0)
    assert torch.isfinite(loss)


@pytest.mark.parametrize("size", [80, 96])
def test_sizes_divisible_by_16_that_are_not_powers_of_two(size, tmp_path):
    cfg = compose_train([f"data.size={size}", f"paths.root_dir={tmp_path}", "loss=[recon]"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    out = build_module(cfg).net(fixture_batch(S=size))
    assert out["rgb"].shape[-1] == size and [s.shape[-1] for s in out["rgb_scales"]] == [size // 8, size // 4,
                                                                                          size // 2, size]


@pytest.mark.parametrize("skips", ["warped", "plain", "none", "wo_conv0"])
def test_model_options_forward_backward(skips, tmp_path):
    cfg = compose_train([f"model/skips={skips}", "loss=[recon,depth_consistency,edge_smooth,warp]",
                         f"paths.root_dir={tmp_path}"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    module = build_module(cfg)
    batch = fixture_batch()
    loss = module.training_step(batch, 0)
    loss.backward()
    grads = [p.grad for p in module.net.parameters() if p.grad is not None]
    assert torch.isfinite(loss) and grads and all(torch.isfinite(g).all() for g in grads)


def _train(objects_root, tmp_path, *extra):
    cmd = [sys.executable, "-m", "nvs.train", f"data.root={objects_root}", f"paths.log_dir={tmp_path}",
           "trainer.enable_progress_bar=false", *extra]
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)


def test_fast_dev_run_through_real_train_yaml(objects_root, tmp_path, monkeypatch):
    # the entry point in this process (the command line's own start: test_short_run_writes_artifacts)
    code, err = cli_in_process("train", [f"data.root={objects_root}", f"paths.log_dir={tmp_path}",
                                         "trainer.enable_progress_bar=false", "debug=fast_dev_run"], monkeypatch)
    assert code == 0, err[-3000:]
    metrics = list(tmp_path.rglob("metrics.json"))
    assert len(metrics) == 1
    m = json.loads(metrics[0].read_text())
    assert m["params"] == PARAMS_64["nvs"] and m["seed"] == 0 and m["git_sha"]


def test_short_run_writes_artifacts(objects_root, tmp_path):
    res = _train(objects_root, tmp_path, "trainer.max_steps=4", "trainer.val_check_interval=2",
                 "data.loader.batch_size=2", "loss=[recon]", "trainer.log_every_n_steps=1")
    assert res.returncode == 0, res.stderr[-3000:]
    run_dir = next(tmp_path.rglob("metrics.json")).parent
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["steps"] == 4 and 0 < m["test"]["l1"] < 2 and m["test"]["n_pairs"] == 4
    # precision=auto (the default): the mode this machine measured fastest, recorded and said in one line
    choice = m["precision_choice"]
    assert choice["requested"] == "auto" and m["precision"] == choice["precision"]
    assert choice["mode"] == min(choice["probe_ms"], key=choice["probe_ms"].get)
    assert f"precision: {choice['mode']} ({choice['precision']}" in res.stdout + res.stderr
    assert (run_dir / "checkpoints" / "last.ckpt").is_file()
    assert any(p.name.startswith("best-") for p in (run_dir / "checkpoints").iterdir())
    assert (run_dir / ".hydra" / "config.yaml").is_file()
    assert (run_dir / "csv" / "metrics.csv").is_file()
    rows = (run_dir / "test_per_image.csv").read_text().splitlines()
    assert rows[0].startswith("id_src,id_tgt,l1") and len(rows) == 5
    assert "depth_l1" in rows[0]


def test_unknown_override_key_is_one_clear_error(objects_root, tmp_path):
    res = _train(objects_root, tmp_path, "model.no_such_key=3")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.strip() == ("error: config 'model.no_such_key': not an argument of nvs.models.net.NVSNet "
                                  "(on the command line: model.no_such_key=3)")
    res = _train(objects_root, tmp_path, "model=bogus")
    assert res.returncode == 2 and res.stderr.startswith("error: ") and "Available options in 'model'" in res.stderr
    assert "nvs" in res.stderr.split("Available options in 'model':")[1].split()


def _evaluate(tmp_path, *args):
    cmd = [sys.executable, "-m", "nvs.evaluate", f"paths.log_dir={tmp_path}", *args]
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)


def test_evaluate_checkpoint_and_reference_models(objects_root, tmp_path, monkeypatch):
    train_in_process(objects_root, tmp_path / "t", "trainer.max_steps=2", "trainer.val_check_interval=2",
                     "data.loader.batch_size=2", "loss=[recon]", "test=false")
    ckpt = next((tmp_path / "t").rglob("last.ckpt"))
    out = tmp_path / "e"
    res = _evaluate(tmp_path, f"ckpt_path={ckpt}", f"out_dir={out}", "data=chairs", f"data.root={objects_root}")
    assert res.returncode == 0, res.stderr[-3000:]
    m = json.loads((out / "metrics.json").read_text())
    assert m["test"]["n_pairs"] == 4 and "depth_sc_inv" in m["test"]
    assert len((out / "test_per_image.csv").read_text().splitlines()) == 5
    # The rest through the same entry point in this process (the command line's start is tested above).
    def evaluate(*args):
        return cli_in_process("evaluate", [f"paths.log_dir={tmp_path}", *args], monkeypatch)

    # The floor: copying the source, evaluated without a checkpoint.
    code, err = evaluate("model=copy_source", "data=chairs", f"data.root={objects_root}", f"out_dir={out}/c")
    assert code == 0, err[-3000:]
    assert json.loads((out / "c" / "metrics.json").read_text())["params"] == 0
    # A checkpoint asked to be another model option: one clear error, no traceback.
    code, err = evaluate(f"ckpt_path={ckpt}", "model=copy_source", f"out_dir={out}/x")
    assert code == 2 and "holds model 'nvs'" in err and "Traceback" not in err, err[-3000:]
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(b"not a checkpoint")
    code, err = evaluate(f"ckpt_path={bad}", f"out_dir={out}/y")
    assert code == 2 and "bad.ckpt: not a readable checkpoint" in err and "Traceback" not in err, err[-3000:]
    assert not (out / "x").exists() and not (out / "y").exists()  # a refused evaluation writes nothing


def test_onecycle_schedule_warms_up_then_anneals_over_max_steps(tmp_path):
    from nvs.run.build import build_module

    cfg = compose_train(["scheduler=onecycle", "trainer.max_steps=20", "loss=[recon]", "data.size=64",
                         f"paths.root_dir={tmp_path}"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    conf = build_module(cfg).configure_optimizers()
    opt, sched = conf["optimizer"], conf["lr_scheduler"]["scheduler"]
    assert conf["lr_scheduler"]["interval"] == "step"
    lrs = []
    for _ in range(20):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    peak = lrs.index(max(lrs))
    assert 0 < peak < 5 and max(lrs) == pytest.approx(3e-4) and lrs[-1] < 0.05 * max(lrs)
    assert opt.param_groups[0]["betas"][0] == 0.5  # the optimiser's (fidelity.adam_beta1, the code's), not cycled


def test_conv0_norm_option_keeps_colour_levels_in_the_full_resolution_skip():
    from nvs.models.encoder import Encoder

    # reflect padding: with the code's zero padding the border pixels do see the shift, through the padding
    paper, plain = Encoder(64, conv0_padding="reflect"), Encoder(64, conv0_norm="none", conv0_padding="reflect")
    assert any(isinstance(m, torch.nn.InstanceNorm2d) for m in paper.conv0.modules())
    assert not any(isinstance(m, torch.nn.InstanceNorm2d) for m in plain.conv0.modules())
    assert any(isinstance(m, torch.nn.InstanceNorm2d) for m in plain.conv2.modules())  # only conv0 changes
    plain.load_state_dict(paper.state_dict())  # no norm parameters either way: weights are interchangeable
    x = torch.rand(1, 3, 64, 64) * 2 - 1
    # instance-normalised features do not see a global brightness shift; the plain conv0 does
    with torch.no_grad():
        assert (paper.conv0(x) - paper.conv0(x * 0.5 + 0.3)).abs().max() < 1e-2
        shift = (plain.conv0(x) - plain.conv0(x * 0.5 + 0.3)).abs().mean()
        assert shift > 1e-2


def test_demo_trains_the_authors_network(tmp_path):
    cfg = compose_train(["experiment=demo"])
    code = dict(compose_train().fidelity)
    assert cfg.model.name == "nvs" and dict(cfg.fidelity) == {**code, "vgg_size": None}  # budget choice 1
    assert list(cfg.loss) == ["recon", "vgg", "depth_consistency", "edge_smooth", "warp"]
    # budget choice 2: one cycle to 5e-4 over exactly the run's steps (the paper: constant 1e-4)
    assert cfg.scheduler.max_lr == 5e-4 and cfg.scheduler.total_steps == cfg.trainer.max_steps == 900


def test_the_demos_budget_is_the_whole_demo_so_a_slow_render_leaves_less_training():
    from nvs.demo import DEMO_MINUTES, EVAL_MINUTES, train_minutes

    for machine in ("native", "emulated"):
        assert train_minutes(machine, 0) == pytest.approx(DEMO_MINUTES[machine] - EVAL_MINUTES[machine])
        assert train_minutes(machine, 150) == pytest.approx(train_minutes(machine, 0) - 2.5)
        assert train_minutes(machine, 10_000) == 0.0  # never negative: the demo then trains its MIN_STEPS
    # with make setup's ~2.6 min on a fresh machine, each class stays within its goal (12 and 15 min)
    assert DEMO_MINUTES["native"] + 2.6 <= 12 and DEMO_MINUTES["emulated"] + 2.6 <= 15


def _module(tmp_path, *overrides):
    cfg = compose_train([f"paths.root_dir={tmp_path}", "data.size=64", *overrides])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    return build_module(cfg)


def test_compile_failure_falls_back_to_eager_with_one_warning(tmp_path, monkeypatch):
    """compile=true: a compiler that fails costs one logged line; the step's loss is the eager one."""
    eager = _module(tmp_path, "loss=[recon,warp]")
    calls = []

    def broken_compile(fn, *args, **kwargs):
        def run(*a, **k):
            calls.append(1)
            raise RuntimeError("backend exploded\nsecond line")
        return run

    monkeypatch.setattr(torch, "compile", broken_compile)
    torch.manual_seed(0)
    compiled = _module(tmp_path, "loss=[recon,warp]", "compile=true")
    compiled.load_state_dict(eager.state_dict())
    batch = fixture_batch()
    with pytest.warns(UserWarning, match=r"compile=true: torch.compile failed \(RuntimeError: backend exploded\); "
                                         r"training continues eager"):
        first = compiled.training_step(dict(batch), 0)
    second = compiled.training_step(dict(batch), 1)  # no second attempt, no second warning
    assert calls == [1]
    assert torch.equal(first, eager.training_step(dict(batch), 0)) and torch.equal(first, second)


def test_compile_with_a_critic_stays_eager_and_says_so(tmp_path, monkeypatch):
    monkeypatch.setattr(torch, "compile", lambda fn, *a, **k: pytest.fail("a critic's step must not be compiled"))
    with pytest.warns(UserWarning, match=r"compile=true: the training step stays eager \(loss term\(s\) adversarial"):
        module = _module(tmp_path, "experiment=sun_chairs", "compile=true")
    assert module._compiled is None


@pytest.mark.slow
def test_compiled_step_computes_the_eager_loss(tmp_path):
    eager = _module(tmp_path, "loss=[recon,warp]", "data.size=64")
    compiled = _module(tmp_path, "loss=[recon,warp]", "compile=true")
    compiled.load_state_dict(eager.state_dict())
    batch = fixture_batch()
    a, b = eager.training_step(dict(batch), 0), compiled.training_step(dict(batch), 0)
    assert compiled._compiled is not None and torch.allclose(a, b, rtol=1e-4, atol=1e-6)


def test_the_configured_adam_is_fused_and_steps_like_the_per_parameter_loop(tmp_path):
    """optim=adam builds torch's fused Adam; five steps on the same gradients match the per-parameter loop."""
    from hydra.utils import instantiate

    cfg = compose_train([f"paths.root_dir={tmp_path}"])
    factory = instantiate(cfg.optim)
    torch.manual_seed(0)
    ref = [torch.nn.Parameter(torch.randn(33, 17)), torch.nn.Parameter(torch.randn(5))]
    fused = [torch.nn.Parameter(p.detach().clone()) for p in ref]
    start = [p.detach().clone() for p in ref]
    opt_fused = factory(fused)
    assert opt_fused.defaults["fused"] is True and opt_fused.defaults["betas"] == (0.5, 0.999)
    opt_loop = torch.optim.Adam(ref, lr=opt_fused.defaults["lr"], betas=(0.5, 0.999), foreach=False)
    for step in range(5):
        grads = [torch.randn_like(p) * (step + 1) for p in ref]
        for p, q, g in zip(ref, fused, grads):
            p.grad, q.grad = g.clone(), g.clone()
        opt_loop.step()
        opt_fused.step()
    for p, q, p0 in zip(ref, fused, start):
        assert (p - p0).abs().mean() > 1e-4  # the steps moved the parameters (5 steps of lr 1e-4)
        assert torch.allclose(p, q, rtol=0, atol=1e-7)


def test_a_run_shorter_than_val_check_interval_still_tests_a_validation_checkpoint(objects_root, tmp_path):
    """max_steps=3 under the default val_check_interval=500: the run validates at its last step and tests that
    checkpoint; without any validation, metrics.json says the final weights were tested."""
    m = train_in_process(objects_root, tmp_path / "a", "trainer.max_steps=3", "data.loader.batch_size=2",
                         "loss=[recon]")
    assert m["checkpoint"].endswith("best-3.ckpt") and m["tested_weights"] == "best validation checkpoint"
    m = train_in_process(objects_root, tmp_path / "b", "trainer.max_steps=2", "data.loader.batch_size=2",
                         "loss=[recon]", "trainer.limit_val_batches=0")
    assert m["checkpoint"] is None and m["tested_weights"] == "final weights (step 2)"
