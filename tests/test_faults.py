"""Faults and bad input: a killed run resumes, results files are never half-written, wrong shapes, wrong override types
and mismatched checkpoints stop with one clear message."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from nvs.core import atomic
from nvs.core.errors import UserError
from nvs.core.geometry import inverse_warp, pose_matrix, scale_intrinsics
from nvs.run.artifacts import write_metrics, write_per_image
from nvs.run.build import build_module
from nvs.run.config_check import check_config
from nvs.run.run_checks import model_mismatch
from tests.conftest import CONF_DIR, compose_train
from tests.run_helpers import cli_in_process

REPO = Path(__file__).resolve().parents[1]


def _python(*args, cwd=REPO, timeout=600):
    return subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=timeout)


def _one_clear_error(code: int, err: str, *needles) -> bool:
    """Exit 2, no traceback, every needle in stderr (a command run in this process: ``cli_in_process``)."""
    return code == 2 and "Traceback" not in err and all(n in err for n in needles)


def _is_one_clear_error(res, *needles) -> bool:
    """The same for a finished subprocess."""
    return _one_clear_error(res.returncode, res.stderr, *needles)


# -- kill and resume ------------------------------------------------------------------------------------------------
MAX_STEPS = 6


def _train_cmd(objects_root, run_dir):
    # Validation (and so last.ckpt, which waits for the monitored val/l1) every 2 steps.
    return ["-m", "nvs.train", f"data.root={objects_root}", f"hydra.run.dir={run_dir}",
            f"trainer.max_steps={MAX_STEPS}", "trainer.val_check_interval=2", "data.loader.batch_size=2",
            "loss=[recon]", "optim.lr=1e-3", "trainer.enable_progress_bar=false"]


@pytest.mark.slow
def test_killed_run_resumes_and_matches_an_uninterrupted_one(objects_root, tmp_path):
    killed = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, *_train_cmd(objects_root, killed)], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    last = killed / "checkpoints" / "last.ckpt"
    deadline = time.monotonic() + 300
    while not last.is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)  # mid-run, no chance to clean up
    proc.wait()
    assert last.is_file(), "the run ended before its first checkpoint"
    step_at_kill = torch.load(last, map_location="cpu", weights_only=False)["global_step"]
    assert 0 < step_at_kill < MAX_STEPS
    assert not (killed / "metrics.json").exists()

    resumed = _python(*_train_cmd(objects_root, killed))  # the same command again: ckpt_path=auto
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"Restored all states from the checkpoint at {last}" in resumed.stdout  # Lightning's line, via Hydra's log
    full = _python(*_train_cmd(objects_root, tmp_path / "full"))
    assert full.returncode == 0, full.stderr[-3000:]

    a = json.loads((killed / "metrics.json").read_text())
    b = json.loads((tmp_path / "full" / "metrics.json").read_text())
    assert a["steps"] == b["steps"] == MAX_STEPS
    # Samples are counted across the segments: the resumed process trained only the remaining steps.
    assert a["train_samples_per_s"] * a["train_wall_s"] == pytest.approx(2 * MAX_STEPS)
    # The resumed loader continues the epoch with the batches the uninterrupted run trains next (nvs.data.sampling),
    # and items draw from their own seeds: the two runs train on the same data and end with the same metrics.
    for key in ("l1", "ssim_paper", "psnr"):
        assert a["test"][key] == pytest.approx(b["test"][key], rel=1e-4), key
    assert a["test"]["n_pairs"] == b["test"]["n_pairs"] == 4


def test_resume_from_a_truncated_checkpoint_is_one_clear_error(objects_root, tmp_path, monkeypatch):
    """What a kill during a non-atomic checkpoint write leaves (run directory on another filesystem than $TMPDIR)."""
    last = tmp_path / "run" / "checkpoints" / "last.ckpt"
    last.parent.mkdir(parents=True)
    whole = tmp_path / "whole.ckpt"
    torch.save({"state_dict": {"w": torch.zeros(10_000)}, "global_step": 2}, whole)
    last.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    code, err = cli_in_process("train", _train_cmd(objects_root, tmp_path / "run")[2:], monkeypatch)
    assert _one_clear_error(code, err, "last.ckpt"), err[-2000:]
    assert last.stat().st_size == whole.stat().st_size // 2  # the refused resume leaves the file as it found it


# -- atomic writes --------------------------------------------------------------------------------------------------
def _leftovers(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if p.name.endswith(".tmp"))


class _OsWith:
    """The os module with some functions replaced, for nvs.core.atomic only (the real os stays untouched)."""

    def __init__(self, **replaced):
        self.replaced = replaced

    def __getattr__(self, name):
        return self.replaced.get(name) or getattr(os, name)


def _failing(*args, **kwargs):
    raise OSError("disk full")


@pytest.mark.parametrize("fail_at", ["write", "fsync", "replace"])
def test_failed_write_keeps_the_old_file_and_no_temp(tmp_path, monkeypatch, fail_at):
    path = tmp_path / "metrics.json"
    write_metrics(path, {"l1": 0.5})
    old = path.read_bytes()

    if fail_at == "write":
        real_fdopen = os.fdopen

        class HalfWriter:
            """Writes half of the data, then the process is 'interrupted' (a BaseException, like Ctrl-C)."""

            def __init__(self, fd, mode):
                self.f = real_fdopen(fd, mode)

            def __enter__(self):
                return self

            def __exit__(self, *exc):
                self.f.close()

            def write(self, data):
                self.f.write(data[: len(data) // 2])
                self.f.flush()
                raise KeyboardInterrupt

        monkeypatch.setattr(atomic, "os", _OsWith(fdopen=HalfWriter))
        with pytest.raises(KeyboardInterrupt):
            write_metrics(path, {"l1": 0.25, "big": list(range(10_000))})
    else:
        monkeypatch.setattr(atomic, "os", _OsWith(**{fail_at: _failing}))
        with pytest.raises(OSError, match="disk full"):
            write_metrics(path, {"l1": 0.25})
    assert path.read_bytes() == old
    assert _leftovers(tmp_path) == []


def test_failed_csv_write_keeps_the_old_table(tmp_path, monkeypatch):
    path = tmp_path / "test_per_image.csv"
    write_per_image(path, [{"id_src": "a", "id_tgt": "b", "l1": 0.1}])
    old = path.read_text()
    monkeypatch.setattr(atomic, "os", _OsWith(replace=_failing))
    with pytest.raises(OSError):
        write_per_image(path, [{"id_src": "a", "id_tgt": "b", "l1": 0.2}] * 1000)
    assert path.read_text() == old and _leftovers(tmp_path) == []


WRITER = """
import sys
from nvs.run.artifacts import write_metrics
path, i = sys.argv[1], 0
print("ready", flush=True)
while True:
    i += 1
    write_metrics(path, {"i": i, "rows": [i] * 200_000})  # ~1.4 MB per write
"""


def test_sigkill_during_writes_never_leaves_a_truncated_file(tmp_path):
    path = tmp_path / "metrics.json"
    write_metrics(path, {"i": 0, "rows": [0] * 200_000})
    for delay in (0.3, 0.55, 0.8):
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], cwd=REPO, stdout=subprocess.PIPE,
                                text=True)
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(delay)
        proc.kill()
        proc.wait()
        proc.stdout.close()
        data = json.loads(path.read_text())  # a whole file: the old or the new one, never a prefix
        assert data["rows"] == [data["i"]] * 200_000
        # A killed writer cannot remove its temp file, but it is hidden and never named like a results file.
        assert [p.name for p in tmp_path.iterdir() if not p.name.startswith(".")] == ["metrics.json"]


def test_stress_report_is_written_atomically(tmp_path, monkeypatch):
    from nvs import stress

    out = tmp_path / "stress.md"
    out.write_text("old report\n")
    monkeypatch.setattr(atomic, "os", _OsWith(replace=_failing))
    with pytest.raises(OSError):
        stress.main(["--sections", "geometry", "--out", str(out)])
    assert out.read_text() == "old report\n" and _leftovers(tmp_path) == []


# -- wrong shapes ---------------------------------------------------------------------------------------------------
def _warp_args(B=2, S=4):
    K = torch.tensor([[3.0, 0, 1.5], [0, 3.0, 1.5], [0, 0, 1]]).expand(B, 3, 3).clone()
    return torch.rand(B, 3, S, S), torch.ones(B, 1, S, S), K, pose_matrix(torch.eye(3).expand(B, 3, 3),
                                                                          torch.zeros(B, 3))


@pytest.mark.parametrize("which, bad, match", [
    ("K", lambda K: K[0], r"K must have shape \(2,3,3\), got \(3, 3\)"),
    ("K", lambda K: K[:1], r"K must have shape \(2,3,3\), got \(1, 3, 3\)"),
    ("K", lambda K: torch.eye(4).expand(2, 4, 4), r"K must have shape \(2,3,3\), got \(2, 4, 4\)"),
    ("K", lambda K: K[..., :2], r"K must have shape \(2,3,3\), got \(2, 3, 2\)"),
    ("T", lambda T: T[:, :3], r"T_tgt_src must have shape \(2,4,4\), got \(2, 3, 4\)"),
    ("depth", lambda d: d[:, 0], r"depth_tgt must be \(B,1,H,W\)"),
    ("depth", lambda d: d[..., :3], r"disagree in batch or size"),
])
def test_wrong_shapes_name_the_argument(which, bad, match):
    src, depth, K, T = _warp_args()
    args = {"src": src, "depth_tgt": depth, "K": K, "T_tgt_src": T}
    key = {"K": "K", "T": "T_tgt_src", "depth": "depth_tgt"}[which]
    args[key] = bad(args[key])
    with pytest.raises(ValueError, match=match):
        inverse_warp(**args)


def test_scale_intrinsics_rejects_a_wrong_K():
    with pytest.raises(ValueError, match=r"K must have shape \(...,3,3\), got \(4, 4\)"):
        scale_intrinsics(torch.eye(4), 0.5)


# -- wrong type in a CLI override -----------------------------------------------------------------------------------
def _resolved(overrides, tmp_path):
    cfg = compose_train([*overrides, f"paths.root_dir={tmp_path}"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    return cfg


def _check(overrides):
    check_config("train", compose_train(overrides), overrides)


@pytest.mark.parametrize("override, message", [
    ("trainer.max_steps=abc", "config 'trainer.max_steps': expected an integer, got 'abc' "
                              "(on the command line: trainer.max_steps=abc)"),
    ("data.loader.batch_size=x", "config 'data.loader.batch_size': expected an integer, got 'x'"),
    ("test=yes", "config 'test': expected true or false, got 'yes'"),
    ("data.camera.fx=wide", "config 'data.camera.fx': expected a number, got 'wide'"),
    ("loss.recon.scale_weights=[1,x]", "config 'loss.recon.scale_weights[1]': expected a number, got 'x'"),
    ("model.n_points=[1]", "config 'model.n_points': expected an integer, got [1]"),
    ("data.camera=1", "config 'data.camera': expected a mapping {...}, got 1"),
    # Lightning's max_steps is an int (-1: no limit); None fails inside its fit loop
    ("trainer.max_steps=null", "config 'trainer.max_steps': expected an integer, got null"),
    ("trainer.max_steps='12'", "config 'trainer.max_steps': expected an integer, got '12'"),
])
def test_wrong_override_type_names_the_key(override, message):
    with pytest.raises(UserError) as err:
        _check([override])
    assert message in str(err.value)
    assert str(err.value).endswith(f"(on the command line: {override})")


@pytest.mark.parametrize("overrides", [
    ["trainer.val_check_interval=0.5"],  # a number for a number: Lightning takes a fraction of an epoch
    ["trainer.precision=16"],  # a scalar for a string
    ["experiment=sun_chairs", "model.lstm_blocks=1"],  # the experiment's own defaults count
    ["model=chen", "model.n_points=100"],
    ["+callbacks.model_checkpoint.every_n_train_steps=2", "~test", "hydra.run.dir=/x"],
    ["data=drive", "data.depth_head.max_disparity=20"],
])
def test_well_typed_overrides_pass(overrides):
    _check(overrides)


@pytest.mark.parametrize("overrides", [["model.n_points=0"], ["model.n_points=-5"], ["model=chen", "model.n_points=0"]])
def test_a_latent_of_no_points_is_one_clear_error_at_build(overrides, tmp_path):
    """Well typed but builds nothing: n_points=0 crashed at the first forward, -5 deep inside torch."""
    with pytest.raises(UserError, match=r"n_points=-?\d+: expected a positive integer"):
        build_module(_resolved(overrides, tmp_path))


def test_every_mismatch_is_listed_in_one_message():
    with pytest.raises(UserError, match=r"config 'data.size': .*; config 'trainer.max_steps'"):
        _check(["trainer.max_steps=a", "data.size=b", "data=drive"])


@pytest.mark.parametrize("module, override", [("nvs.train", "trainer.max_steps=abc"),
                                              ("nvs.train", "data.loader.batch_size=x"),
                                              ("nvs.evaluate", "seed=abc")])
def test_wrong_override_type_on_the_command_line(objects_root, tmp_path, module, override):
    extra = ["model=copy_source", "data=chairs"] if module == "nvs.evaluate" else []
    res = _python("-m", module, f"data.root={objects_root}", f"hydra.run.dir={tmp_path}", *extra, override)
    assert _is_one_clear_error(res, f"config '{override.split('=')[0]}'"), res.stderr[-2000:]


# -- a checkpoint from another model option -------------------------------------------------------------------------
def _checkpoint(tmp_path, overrides) -> Path:
    """A checkpoint as nvs.train leaves it (weights without loss networks, resolved run config), without training."""
    module = build_module(_resolved(overrides, tmp_path))
    state = {k: v for k, v in module.state_dict().items() if not k.startswith("losses.")}
    path = tmp_path / "model.ckpt"
    torch.save({"state_dict": state, "nvs_config": module.run_config, "global_step": 0}, path)
    return path


def test_model_mismatch_names_the_differing_key(tmp_path):
    held = OmegaConf.to_container(_resolved(["model/skips=warped"], tmp_path).model)
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        def asked(*ov):
            return OmegaConf.to_container(compose("evaluate", overrides=list(ov)).model, resolve=False)

        assert model_mismatch(asked("model=nvs"), held) is None
        assert model_mismatch(asked("model=nvs", "model/skips=none"), held) == (
            "model.skips._target_: the checkpoint has 'nvs.models.skips.WarpedSkips', "
            "the command asks for 'nvs.models.skips.NoSkips'")
        assert model_mismatch(asked("model=nvs", "model/skips=wo_conv0"), held).startswith("model.skips.levels:")
        assert model_mismatch(asked("model=nvs", "model.n_points=100"), held).startswith("model.n_points:")


def _evaluate_in_process(monkeypatch, *args) -> tuple[int, str]:
    """``python -m nvs.evaluate *args``'s exit code and stderr, through its entry point in this process."""
    return cli_in_process("evaluate", list(args), monkeypatch)


def test_checkpoint_of_another_skip_option_is_one_clear_error(objects_root, tmp_path, monkeypatch):
    ckpt = _checkpoint(tmp_path, ["model/skips=warped", "loss=[recon]"])
    code, err = _evaluate_in_process(monkeypatch, f"ckpt_path={ckpt}", "model=nvs", "model/skips=none", "data=chairs",
                                     f"data.root={objects_root}", f"out_dir={tmp_path / 'e'}",
                                     f"hydra.run.dir={tmp_path / 'h'}")
    assert _one_clear_error(code, err, "model.skips", "WarpedSkips"), err[-2000:]
    assert not (tmp_path / "e").exists() and not (tmp_path / "h").exists()  # nothing left behind


def test_checkpoint_weights_of_another_shape_are_one_clear_error(objects_root, tmp_path, monkeypatch):
    """A checkpoint whose config names one skip option but whose weights come from another (edited, or stale code)."""
    ckpt = _checkpoint(tmp_path, ["model/skips=plain", "loss=[recon]"])
    data = torch.load(ckpt, weights_only=False)
    data["nvs_config"]["model"]["skips"] = {"_target_": "nvs.models.skips.NoSkips"}
    torch.save(data, ckpt)
    code, err = _evaluate_in_process(monkeypatch, f"ckpt_path={ckpt}", "data=chairs", f"data.root={objects_root}",
                                     f"out_dir={tmp_path / 'e'}", f"hydra.run.dir={tmp_path / 'h'}")
    assert _one_clear_error(code, err, "model.ckpt", "pixel_decoder"), err[-2000:]
