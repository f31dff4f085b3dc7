"""Nothing lost silently (issue 19): bad data found before the first step, outputs checked writable, signals save and
say how to resume, one line (exit 2) per user error wherever it is raised, multiruns that keep going.

The command-line probes run ``nvs.train`` / ``nvs.evaluate`` in this process (Hydra's own ``main``, argv patched):
the same code path as ``python -m``, without a second interpreter start per probe.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import sys
import zipfile
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf, open_dict

from nvs.core.errors import DataError, Interrupted, UserError, user_message
from nvs.run.artifacts import check_creatable, remove_unstarted_run
from nvs.run.checkpoints import AtomicCheckpointIO, CheckpointWriteError
from nvs.run.cli import exits_cleanly
from nvs.run.overrides import trainer_arguments
from nvs.train import check_composes
from tests.conftest import compose_train
from tests.run_helpers import cli_in_process

REPO = Path(__file__).resolve().parents[1]


def _cli(module: str, argv: list[str], monkeypatch) -> tuple[int, str]:
    """``python -m nvs.<module> *argv`` in this process -> (exit code, stderr)."""
    return cli_in_process(module, argv, monkeypatch)


def _error_lines(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ln.startswith("error:")]


def _copy(root: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "data"
    shutil.copytree(root, dst)
    return dst


TRAIN = ["trainer.max_steps=2", "trainer.val_check_interval=2", "data.loader.batch_size=2", "loss=[recon]",
         "trainer.enable_progress_bar=false", "trainer.precision=32-true"]
# A small network where a probe trains (the behaviour under test is the model's; the run's time is not)
SMALL = ["model=tatarchenko", "loss=[recon_final]"]


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:200])


def _bad_depth(path: Path) -> None:
    np.save(path, np.zeros((64, 32), np.float32))


# (name, change to a copy of the fixture data, extra overrides, what the one error line must say)
PROBES = [
    ("empty test list", lambda r: (r / "eval_chair_40.txt").write_text(""), [],
     ["eval_chair_40.txt: no pairs: the split is empty"]),
    ("unknown model in the test list", lambda r: open(r / "eval_chair_40.txt", "a").write("zz_0_0 m3_20_0\n"), [],
     ["eval_chair_40.txt:5: pair 'zz_0_0 m3_20_0': image file is missing", "zz_0_0.png"]),
    ("missing test image", lambda r: (r / "images" / "m3_40_0.png").unlink(), [],
     ["eval_chair_40.txt:2: pair 'm3_40_0 m3_60_10': image file is missing"]),
    ("bad depth of a test frame", lambda r: _bad_depth(r / "depth" / "m3_40_0.npy"), [],
     ["eval_chair_40.txt:2:", "depth must be a square 2-D array, got shape (64, 32)", "m3_40_0.npy"]),
    ("unknown model in id_train.txt", lambda r: (r / "id_train.txt").write_text("m0\nbogus\nm1\n"), [],
     ["id_train.txt:2: model 'bogus': image file is missing", "bogus_0_0.png"]),
    ("truncated training image", lambda r: _truncate(r / "images" / "m1_20_10.png"), ["data.loader.num_workers=1"],
     ["id_train.txt:", "model 'm1': cannot read image", "m1_20_10.png"]),
    ("batch size 0", lambda r: None, ["data.loader.batch_size=0"],
     ["data.loader.batch_size=0: expected a positive integer"]),
    ("misspelt trainer key", lambda r: None, ["trainer.max_step=3"],
     ["config 'trainer.max_step': not an argument of lightning.pytorch.Trainer; did you mean trainer.max_steps? "
      "(on the command line: trainer.max_step=3)"]),
    ("misspelt trainer key, appended as Hydra suggests", lambda r: None, ["+trainer.max_step=3"],
     ["config 'trainer.max_step': not an argument of lightning.pytorch.Trainer; did you mean trainer.max_steps? "
      "(on the command line: +trainer.max_step=3)"]),
]


@pytest.mark.parametrize("name, change, extra, needles", PROBES, ids=[p[0] for p in PROBES])
def test_probe_is_one_line_exit_2_before_any_step_and_leaves_no_run_dir(objects_root, tmp_path, monkeypatch, name,
                                                                        change, extra, needles):
    root = _copy(objects_root, tmp_path)
    change(root)
    run_dir = tmp_path / "run"
    code, stderr = _cli("train", [f"data.root={root}", f"hydra.run.dir={run_dir}", *TRAIN, *extra], monkeypatch)
    lines = _error_lines(stderr)
    assert code == 2 and "Traceback" not in stderr and len(lines) == 1, stderr[-3000:]
    assert all(n in lines[0] for n in needles), lines[0]
    assert not run_dir.exists(), sorted(p.name for p in run_dir.iterdir())


def test_unwritable_checkpoint_folder_is_found_at_start(objects_root, tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "checkpoints").write_text("a file where the checkpoints go")
    code, stderr = _cli("train", [f"data.root={objects_root}", f"hydra.run.dir={run_dir}", *TRAIN], monkeypatch)
    assert code == 2 and _error_lines(stderr) == [
        f"error: {run_dir / 'checkpoints'}: output location is not writable (a file is in the way); choose another "
        "(hydra.run.dir=..., paths.log_dir=...)"], stderr[-3000:]
    assert (run_dir / "checkpoints").is_file() and not (run_dir / ".hydra").exists()  # ours removed, theirs kept


def test_a_run_directory_that_cannot_be_created_is_one_line(objects_root, tmp_path, monkeypatch):
    (tmp_path / "file").write_text("")
    code, stderr = _cli("train", [f"data.root={objects_root}", f"hydra.run.dir={tmp_path / 'file' / 'run'}"],
                        monkeypatch)
    assert code == 2 and _error_lines(stderr) == [
        f"error: {tmp_path / 'file' / 'run'}: cannot create the run directory ({tmp_path / 'file'} is a file); "
        "choose another (hydra.run.dir=..., paths.log_dir=...)"], stderr
    code, stderr = _cli("evaluate", ["model=copy_source", "data=chairs", f"hydra.run.dir={tmp_path / 'file' / 'e'}"],
                        monkeypatch)
    assert code == 2 and "cannot create the run directory" in stderr


def test_check_creatable_accepts_a_new_folder(tmp_path):
    check_creatable(tmp_path / "a" / "b")
    assert not (tmp_path / "a").exists()  # creates nothing


def test_a_failed_checkpoint_write_is_a_user_error(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(CheckpointWriteError, match=r"cannot write checkpoint .*file/last.ckpt: .*training stopped"):
        AtomicCheckpointIO().save_checkpoint({"w": torch.zeros(3)}, tmp_path / "file" / "last.ckpt")
    AtomicCheckpointIO().save_checkpoint({"w": torch.zeros(3)}, tmp_path / "ok.ckpt")
    assert torch.load(tmp_path / "ok.ckpt")["w"].shape == (3,)


def test_remove_unstarted_run_keeps_what_it_did_not_write(tmp_path):
    d = tmp_path / "run"
    (d / ".hydra").mkdir(parents=True)
    (d / "train.log").write_text("")
    (d / "notes.txt").write_text("mine")
    assert not remove_unstarted_run(d, "train")
    assert sorted(p.name for p in d.iterdir()) == ["notes.txt"]
    (d / "checkpoints").mkdir()
    (d / "checkpoints" / "last.ckpt").write_text("")
    (d / ".hydra").mkdir()
    assert not remove_unstarted_run(d, "train") and (d / ".hydra").is_dir()  # a run to resume: untouched
    (d / "notes.txt").unlink()
    shutil.rmtree(d / "checkpoints")
    assert remove_unstarted_run(d, "train") and not d.exists()


# -- errors raised elsewhere: DataLoader workers, Lightning, the non-finite guard -----------------------------------
def test_an_image_error_inside_a_dataloader_worker_is_one_line(objects_root, tmp_path):
    from nvs.data.datamodule import Camera, LoaderSettings, NVSDataModule
    from nvs.data.shapenet import ObjectsFormat

    root = _copy(objects_root, tmp_path)
    dm = NVSDataModule(ObjectsFormat(root, "chair"), Camera(480, 480, 128, 128, 256, (0, 0, 2)), 64,
                       LoaderSettings(batch_size=2, eval_batch_size=4, num_workers=1, cache=False))
    dm.validate()
    _truncate(root / "images" / "m3_0_0.png")  # after the check: what a disk error mid-run looks like
    with pytest.raises(Exception) as err:
        next(iter(dm.test_dataloader()))
    assert not isinstance(err.value, UserError)  # torch re-raises it as another type, with the worker's traceback
    assert "Traceback" in str(err.value)
    assert user_message(err.value) == f"{root / 'images' / 'm3_0_0.png'}: cannot read image (OSError: image file is " \
                                      "truncated)"

    @exits_cleanly
    def main():
        raise err.value

    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr), pytest.raises(SystemExit) as exit_:
        main()
    assert exit_.value.code == 2 and stderr.getvalue().count("\n") == 1


def test_data_errors_survive_pickling():
    import pickle

    err = pickle.loads(pickle.dumps(DataError("a/b.txt", "bad", 3)))
    assert isinstance(err, DataError) and str(err) == "a/b.txt:3: bad" and err.line == 3


def test_lightning_misconfiguration_is_a_user_error():
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    assert user_message(MisconfigurationException("No supported gpu backend found!\nmore")) == \
        "Lightning: No supported gpu backend found!"
    assert user_message(ValueError("a bug")) is None


def test_nonfinite_loss_is_one_line_naming_the_real_key(tmp_path):
    from nvs.run.build import build_module

    cfg = compose_train(["model=copy_source", "loss=[recon_final]", f"paths.root_dir={tmp_path}"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    module = build_module(cfg)
    module.log = lambda *a, **k: None
    from tests.conftest import fixture_batch

    batch = fixture_batch()
    batch["tgt"] = batch["tgt"] * float("nan")
    with pytest.raises(UserError) as err:
        module.training_step(batch, 0)
    assert "Set nonfinite=skip to drop such steps" in str(err.value) and "module.nonfinite" not in str(err.value)
    assert "nonfinite" in OmegaConf.to_container(cfg)  # the key it names exists, at the top level


def test_a_checkpoint_with_flipped_bytes_is_one_clear_error(tmp_path):
    from nvs.run.checkpoint_files import check_complete

    path = tmp_path / "last.ckpt"
    torch.save({"state_dict": {"w": torch.arange(5000.0)}, "global_step": 2}, path)
    check_complete(path)
    with zipfile.ZipFile(path) as zf:
        info = next(i for i in zf.infolist() if i.filename.endswith("data.pkl"))
    data = bytearray(path.read_bytes())
    h = info.header_offset  # the member's bytes follow its local header (name and padding of their own lengths)
    start = h + 30 + int.from_bytes(data[h + 26:h + 28], "little") + int.from_bytes(data[h + 28:h + 30], "little")
    data[start + 5: start + 9] = b"\xff\xfe\xfd\xfc"
    path.write_bytes(bytes(data))
    assert zipfile.is_zipfile(path)  # the zip itself is intact
    with pytest.raises(UserError, match=r"last.ckpt: corrupt checkpoint \(member .*data.pkl fails its checksum\)"):
        check_complete(path)


# -- the trainer group takes every Lightning Trainer argument ------------------------------------------------------
def test_every_trainer_argument_is_accepted_without_plus():
    assert trainer_arguments(["trainer.fast_dev_run=true", "trainer.max_steps=3", "data.root=x"]) == [
        "++trainer.fast_dev_run=true", "trainer.max_steps=3", "data.root=x"]
    # a misspelt one is left to fail composing, where the trainer's schema names the closest argument
    assert trainer_arguments(["trainer.limit_val_batchs=1"]) == ["trainer.limit_val_batchs=1"]
    with pytest.raises(UserError, match=r"config 'trainer.limit_val_batchs': not an argument of "
                                        r"lightning.pytorch.Trainer; did you mean trainer.limit_val_batches\?"):
        check_composes(["trainer.limit_val_batchs=1"])


def test_trainer_fast_dev_run_on_the_command_line(objects_root, tmp_path, monkeypatch):
    code, stderr = _cli("train", [f"data.root={objects_root}", f"hydra.run.dir={tmp_path / 'run'}", *TRAIN, *SMALL,
                                  "trainer.fast_dev_run=true"], monkeypatch)
    assert code == 0, stderr[-3000:]
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["steps"] == 1


# -- multirun keeps going ----------------------------------------------------------------------------------------------
def test_multirun_goes_on_after_a_failed_job_and_reports_it(objects_root, tmp_path, monkeypatch):
    empty = _copy(objects_root, tmp_path)
    (empty / "eval_chair_40.txt").write_text("")
    sweep = tmp_path / "sweep"
    code, stderr = _cli("train", ["-m", f"data.root={tmp_path / 'none'},{empty}", f"hydra.sweep.dir={sweep}",
                                  *TRAIN], monkeypatch)
    assert code == 2 and "Traceback" not in stderr, stderr[-3000:]
    report = stderr[stderr.index("multirun: 2 job(s) failed"):].splitlines()
    assert report[1].startswith(f"  job 0 (data.root={tmp_path / 'none'} ") and "does not exist" in report[1]
    assert report[2].startswith(f"  job 1 (data.root={empty} ") and "no pairs: the split is empty" in report[2]
    records = [json.loads(ln) for ln in (sweep / "multirun_failures.jsonl").read_text().splitlines()]
    assert [r["job"] for r in records] == [0, 1] and all(r["user_error"] for r in records)


# -- evaluation of another root ------------------------------------------------------------------------------------------
def test_evaluate_takes_data_root_alone(objects_root, tmp_path, monkeypatch):
    from nvs.run.build import build_module

    cfg = compose_train([*SMALL, f"paths.root_dir={tmp_path}", f"data.root={tmp_path}/moved_away"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    module = build_module(cfg)
    ckpt = tmp_path / "model.ckpt"
    torch.save({"state_dict": module.state_dict(), "nvs_config": module.run_config, "global_step": 0}, ckpt)
    out = tmp_path / "eval"
    code, stderr = _cli("evaluate", [f"ckpt_path={ckpt}", f"data.root={objects_root}", f"out_dir={out}",
                                     f"hydra.run.dir={tmp_path / 'h'}"], monkeypatch)
    assert code == 0, stderr[-3000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["test"]["n_pairs"] == 4 and metrics["data"] == "chairs"


# -- signals -------------------------------------------------------------------------------------------------------------
class SignalAt(L.Callback):
    """Sends ``signum`` to this process at the end of training step ``step`` (what `kill` does, at a known step)."""

    def __init__(self, step: int, signum: int):
        self.step, self.signum = step, signum

    def on_train_batch_end(self, trainer, *args):
        if trainer.global_step == self.step:
            os.kill(os.getpid(), self.signum)


@pytest.mark.parametrize("signum", [signal.SIGTERM, pytest.param(signal.SIGINT, marks=pytest.mark.slow)])
def test_a_signal_saves_last_ckpt_and_says_how_to_resume(objects_root, tmp_path, signum):
    from nvs.run.training import run

    def cfg(kill: bool):
        c = compose_train([f"data.root={objects_root}", f"paths.root_dir={tmp_path}", *TRAIN, *SMALL,
                           "trainer.max_steps=3", "trainer.val_check_interval=3"])
        c.paths.output_dir = str(tmp_path / "run")
        if kill:
            with open_dict(c.callbacks):
                c.callbacks.kill = {"_target_": "tests.test_reliability.SignalAt", "step": 1, "signum": int(signum)}
        OmegaConf.resolve(c)
        return c

    before = signal.getsignal(signum)
    with pytest.raises(Interrupted) as stop:
        run(cfg(kill=True), tmp_path / "run")
    assert signal.getsignal(signum) is before  # the run's handler is gone with it
    last = tmp_path / "run" / "checkpoints" / "last.ckpt"
    name = signal.Signals(signum).name
    assert stop.value.signum == signum
    assert stop.value.message.startswith(f"interrupted by {name} at step 1: saved {last}; resume with: python -m "
                                         "nvs.train ")
    assert stop.value.message.endswith(f"hydra.run.dir={tmp_path / 'run'}")
    assert torch.load(last, map_location="cpu", weights_only=False)["global_step"] == 1

    @exits_cleanly
    def main():
        raise stop.value

    with contextlib.redirect_stderr(io.StringIO()), pytest.raises(SystemExit) as exit_:
        main()
    assert exit_.value.code == 128 + signum

    result = run(cfg(kill=False), tmp_path / "run")  # ckpt_path=auto: the resume
    assert result["steps"] == 3 and result["test"]["n_pairs"] == 4
    ckpts = tmp_path / "run" / "checkpoints"
    # best and last are the same step: one file on disk
    assert os.path.samefile(ckpts / "last.ckpt", ckpts / "best-3.ckpt")


def test_signal_outside_training_interrupts_at_once(tmp_path):
    from nvs.run.standard_callbacks import Interruption

    stop = Interruption(tmp_path / "last.ckpt", "python -m nvs.train x=1")
    with pytest.raises(Interrupted) as err:
        stop._handler(signal.SIGTERM, None)
    assert err.value.message == "interrupted by SIGTERM before any checkpoint was written: nothing to resume"


# -- KITTI pose rows and implausible poses ---------------------------------------------------------------------------
def _poses(tmp_path, line: str, n: int = 3):
    from tests.conftest import make_scenes_root

    root = make_scenes_root(tmp_path / "d", n_seq=1, n_frames=n)
    lines = (root / "poses.txt").read_text().splitlines()
    lines[1] = line
    (root / "poses.txt").write_text("\n".join(lines) + "\n")
    return root


@pytest.mark.parametrize("line, message", [
    ("0 0 0 1 0 1 0 0 0 0 1 2", "poses.txt:2: 12 numbers: a KITTI odometry 3x4 [R|t] row without its frame id; "
                                "put the id first"),
    ("00_000001 1e300 0 0 0 0 1", "poses.txt:2: rx = 1e+300 is beyond a full turn (2 pi); angles are radians"),
    ("00_000001 0 90 0 0 0 1", "poses.txt:2: ry = 90 is beyond a full turn"),
    ("00_000001 0 0 0 0 0 1e300", "poses.txt:2: translation [0.0, 0.0, 1e+300] is implausible"),
    ("00_000001 2 0 0 0 0 1 0 0 0 0 1 0", "poses.txt:2: the 3x4 pose's left 3x3 block is not a rotation"),
])
def test_kitti_rows_and_implausible_poses(tmp_path, line, message):
    from nvs.data.kitti import ScenesFormat

    with pytest.raises(DataError) as err:
        ScenesFormat(_poses(tmp_path, line))
    assert message in str(err.value)


def test_a_kitti_3x4_row_after_its_id_is_read_as_that_matrix(tmp_path):
    from scipy.spatial.transform import Rotation

    from nvs.data.kitti import ScenesFormat

    R = Rotation.from_euler("xyz", [0.1, -0.2, 0.3]).as_matrix()
    t = np.array([1.0, 2.0, 3.0])
    row = " ".join(f"{v:.12f}" for v in np.hstack([R, t[:, None]]).ravel())
    a = ScenesFormat(_poses(tmp_path / "a", f"00_000001 {row}")).poses["00_000001"]
    b = ScenesFormat(_poses(tmp_path / "b", "00_000001 0.1 -0.2 0.3 1 2 3")).poses["00_000001"]
    np.testing.assert_allclose(a[0], b[0], atol=1e-9)
    np.testing.assert_allclose(a[1], b[1])


# -- the sweep's results directory ---------------------------------------------------------------------------------------
def test_sweep_with_an_unwritable_results_directory_is_one_line(tmp_path, capsys):
    from nvs import sweep

    (tmp_path / "file").write_text("")
    with pytest.raises(SystemExit) as exit_:
        sweep.main([str(REPO / "sweeps" / "precision.yaml"), "--runs", str(tmp_path / "runs"),
                    "--results", str(tmp_path / "file" / "results")])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "Traceback" not in err
    assert err.strip().splitlines()[-1] == (f"error: {tmp_path / 'file' / 'results'}: output location is not writable "
                                            "(a file is in the way); choose another (hydra.run.dir=..., "
                                            "paths.log_dir=...)")
    assert not (tmp_path / "runs").exists()



@pytest.mark.slow
def test_sigterm_through_the_command_line_exits_143_and_the_printed_command_resumes(objects_root, tmp_path):
    import shlex
    import subprocess

    run_dir = tmp_path / "run"
    args = [f"data.root={objects_root}", f"hydra.run.dir={run_dir}", *TRAIN, *SMALL, "trainer.max_steps=3",
            "trainer.val_check_interval=3"]
    kill = ["+callbacks.kill._target_=tests.test_reliability.SignalAt", "+callbacks.kill.step=1",
            "+callbacks.kill.signum=15"]
    res = subprocess.run([sys.executable, "-m", "nvs.train", *args, *kill], cwd=REPO, capture_output=True, text=True,
                         timeout=900)
    line = res.stderr.strip().splitlines()[-1]
    assert res.returncode == 143 and "Traceback" not in res.stderr, res.stderr[-3000:]
    assert line.startswith(f"interrupted by SIGTERM at step 1: saved {run_dir / 'checkpoints' / 'last.ckpt'}; "
                           "resume with: python -m nvs.train ")
    command = shlex.split(line.split("resume with: ", 1)[1])
    assert command[:3] == ["python", "-m", "nvs.train"] and f"hydra.run.dir={run_dir}" in command
    resumed = subprocess.run([sys.executable, *command[1:]], cwd=REPO, capture_output=True, text=True, timeout=900)
    # the printed command still holds the test's kill callback: it fires again only at step 1, which is past
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert json.loads((run_dir / "metrics.json").read_text())["steps"] == 3
