"""Inputs that used to pass silently or end in a traceback (issue 37): depth in the wrong unit or non-finite, a
byte-order mark, untrained runs, resumes that change the run, the convert and evaluate command lines, the sweep's
lock and its child, and the viewer's upload limits. Each is one line naming the file or key (exit 2), or works.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from nvs.core.errors import DataError, UserError
from tests.test_reliability import SMALL, TRAIN, _cli, _copy, _error_lines


# -- depth units and non-finite depth ----------------------------------------------------------------------------------
def test_integer_depth_is_refused_before_any_step_naming_the_file(objects_root, tmp_path, monkeypatch):
    root = _copy(objects_root, tmp_path)
    bad = root / "depth" / "m3_40_0.npy"
    np.save(bad, np.full((64, 64), 2000, np.uint16))  # millimetres
    run_dir = tmp_path / "run"
    code, stderr = _cli("train", [f"data.root={root}", f"hydra.run.dir={run_dir}", *TRAIN], monkeypatch)
    lines = _error_lines(stderr)
    assert code == 2 and "Traceback" not in stderr and len(lines) == 1, stderr[-3000:]
    assert "depth is uint16, expected float metres" in lines[0] and str(bad) in lines[0], lines[0]
    assert not run_dir.exists()


@pytest.mark.parametrize("value, kind", [(np.nan, "NaN"), (np.inf, "inf"), (-np.inf, "inf"), (-1.0, "negative")])
def test_non_finite_or_negative_depth_is_refused_naming_the_file(tmp_path, value, kind):
    from nvs.data.files import read_depth

    depth = np.full((64, 64), 2.0, np.float32)
    depth[3, :5] = value
    depth[0, 0] = 0.0  # the one mask rule: 0 = no data
    path = tmp_path / "d.npy"
    np.save(path, depth)
    with pytest.raises(DataError) as err:
        read_depth(path, 64)
    assert str(err.value).startswith(f"{path}: 5 depth value(s) are {kind}; depth must be finite metres >= 0")
    depth[3, :5] = 0.0
    np.save(path, depth)
    d = read_depth(path, 32)
    assert d.shape == (1, 32, 32) and float(d.max()) == 2.0


def test_a_byte_order_mark_in_poses_txt_is_accepted(scenes_root, tmp_path):
    from nvs.data.kitti import ScenesFormat

    root = _copy(scenes_root, tmp_path)
    poses = root / "poses.txt"
    poses.write_bytes(b"\xef\xbb\xbf" + poses.read_bytes())
    fmt = ScenesFormat(root)
    assert "00_000000" in fmt.poses and fmt.pairs("train", 0.1, 0)  # the first id is the first frame's, not "\ufeff..."


# -- nvs.convert -------------------------------------------------------------------------------------------------------
def _convert(argv, capsys) -> tuple[int, str]:
    from nvs import convert

    with pytest.raises(SystemExit) as exit_:
        convert.main(argv)
    return exit_.value.code, capsys.readouterr().err


def test_convert_out_under_a_missing_folder_is_one_line(tmp_path, capsys):
    out = tmp_path / "missing" / "deeper" / "nvs.ckpt"
    code, err = _convert([str(tmp_path), "--out", str(out)], capsys)
    assert code == 2 and err.splitlines() == [
        f"error: --out {out}: the folder {out.parent} does not exist (create it first)"], err
    assert not (tmp_path / "missing").exists()


def test_convert_of_a_pickled_module_is_one_line(tmp_path, capsys):
    torch.save(torch.nn.Linear(2, 2), tmp_path / "0_net_enc.pth")
    for net in ("dec", "depthdec"):
        torch.save({}, tmp_path / f"0_net_{net}.pth")
    code, err = _convert([str(tmp_path), "--out", str(tmp_path / "nvs.ckpt")], capsys)
    assert code == 2 and err.splitlines() == [
        f"error: {tmp_path / '0_net_enc.pth'}: not a plain state_dict: it pickles the Python object "
        "torch.nn.modules.linear.Linear (a whole network?); save net.state_dict() instead"], err
    assert "\x1b[" not in err and not (tmp_path / "nvs.ckpt").exists()


# -- nvs.evaluate --------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_ckpt(tmp_path_factory, objects_root):
    """An untrained tatarchenko checkpoint at 64^2 on the fixture objects (what evaluate reads back)."""
    from omegaconf import OmegaConf

    from nvs.run.build import build_module
    from tests.conftest import compose_train

    tmp = tmp_path_factory.mktemp("small_ckpt")
    cfg = compose_train([*SMALL, f"paths.root_dir={tmp}", f"data.root={objects_root}"])
    cfg.paths.output_dir = str(tmp)
    OmegaConf.resolve(cfg)
    module = build_module(cfg)
    path = tmp / "model.ckpt"
    torch.save({"state_dict": module.state_dict(), "nvs_config": module.run_config, "global_step": 0}, path)
    return path


@pytest.mark.parametrize("extra, message", [
    (["data.size=128"], "data.size=128: a checkpoint is evaluated at the size it was trained at; drop data.size"),
    (["+data.size=128"], "data.size=128: {ckpt} was trained at 64x64 and is evaluated at that size; drop data.size"),
    (["model=chen"], "model=chen: nvs.evaluate builds only the reference models from model= "
                     "(copy_source|gt_warp|mean_depth|gt_plane); a trained model comes from its checkpoint"),
    (["limit=0"], "limit=0: expected a positive number of test pairs (limit=null: all of them)"),
])
def test_evaluate_overrides_it_cannot_honour_are_one_line(small_ckpt, tmp_path, monkeypatch, extra, message):
    out = tmp_path / "eval"
    code, stderr = _cli("evaluate", [f"ckpt_path={small_ckpt}", f"out_dir={out}", f"hydra.run.dir={tmp_path / 'h'}",
                                     *extra], monkeypatch)
    lines = _error_lines(stderr)
    assert code == 2 and "Traceback" not in stderr and len(lines) == 1, stderr[-3000:]
    assert message.format(ckpt=small_ckpt) in lines[0], lines[0]
    assert not out.exists() and not (tmp_path / "h").exists()


# -- runs that would train nothing, or crash inside the optimiser or the Trainer ----------------------------------------
@pytest.mark.parametrize("extra, message", [
    (["optim.lr=-1"], "config 'optim.lr': expected a positive learning rate, got -1"),
    (["+optim.weight_decay=-1"], "config 'optim': Invalid weight_decay value: -1"),
    (["trainer.val_check_interval=0"], "config 'trainer.val_check_interval': expected a positive number of steps"),
    (["trainer.max_steps=0"], "config 'trainer.max_steps=0': no training step would run"),
    (["data.loader.batch_size=1000"], "data.loader.batch_size=1000: larger than the 108 training pairs; the partial "
                                      "batch is dropped, so no step would run"),
    (["trainer.limit_train_batches=0"], "no training step ran"),
])
def test_a_run_that_would_train_nothing_or_crash_is_one_line(objects_root, tmp_path, monkeypatch, extra, message):
    run_dir = tmp_path / "run"
    code, stderr = _cli("train", [f"data.root={objects_root}", f"hydra.run.dir={run_dir}", *TRAIN, *SMALL, *extra],
                        monkeypatch)
    lines = _error_lines(stderr)
    assert code == 2 and "Traceback" not in stderr and len(lines) == 1, stderr[-3000:]
    assert message in lines[0], lines[0]
    assert not run_dir.exists()  # no metrics.json of an untrained network


# -- a resume must train what it records -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def trained_run(objects_root, tmp_path_factory):
    """A 2-step tatarchenko run's directory (last.ckpt at step 2) and the arguments that made it."""
    run_dir = tmp_path_factory.mktemp("resume") / "run"
    args = [f"data.root={objects_root}", f"hydra.run.dir={run_dir}", *TRAIN, *SMALL]
    mp = pytest.MonkeyPatch()
    try:
        code, stderr = _cli("train", args, mp)
    finally:
        mp.undo()
    assert code == 0, stderr[-3000:]
    return run_dir, args


@pytest.mark.parametrize("extra, message", [
    (["optim.lr=0.5"], "cannot resume with other settings (optim.lr: the checkpoint has 0.0001, the command asks for "
                       "0.5); a resume restores the optimiser's state (its learning rate included)"),
    (["model=chen", "loss=[recon_final]"], "cannot resume with other settings (model._target_: the checkpoint has "
                                           "'nvs.models.baselines"),
    (["data.size=128", "data.loader.with_depth=false"], "cannot resume with other settings (data.size: the checkpoint has 64, the command asks for "
                        "128)"),
])
def test_a_resume_with_another_lr_model_or_size_is_refused(trained_run, monkeypatch, extra, message):
    run_dir, args = trained_run
    last = run_dir / "checkpoints" / "last.ckpt"
    before = (last.stat().st_mtime_ns, json.loads((run_dir / "metrics.json").read_text()))
    code, stderr = _cli("train", [*args, "trainer.max_steps=4", *extra], monkeypatch)
    lines = _error_lines(stderr)
    assert code == 2 and "Traceback" not in stderr and len(lines) == 1, stderr[-3000:]
    assert lines[0].startswith(f"error: {last}: ") and message in lines[0], lines[0]
    assert (last.stat().st_mtime_ns, json.loads((run_dir / "metrics.json").read_text())) == before


def test_lightnings_state_dict_error_on_resume_is_one_line():
    from nvs.run.run_checks import resume_load_error

    a, b = torch.nn.Linear(2, 3), torch.nn.Sequential(torch.nn.Linear(2, 2))
    with pytest.raises(RuntimeError) as err:
        a.load_state_dict(b.state_dict())
    out = resume_load_error(err.value, "run/checkpoints/last.ckpt")
    assert isinstance(out, UserError) and "\n" not in str(out)
    assert str(out).startswith("run/checkpoints/last.ckpt: does not fit this run's model (Missing key(s)")
    assert resume_load_error(RuntimeError("another failure"), "x.ckpt") is None


# -- paths Hydra's grammar cannot read bare ----------------------------------------------------------------------------
def _parsed(override: str):
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return OverridesParser.create().parse_overrides([override])[0].value()


@pytest.mark.parametrize("value", ["/tmp/plain/run", "/tmp/é", "/tmp/日本 語/run", "/tmp/it's", "/tmp/a,b", "/tmp/x\\",
                                   "/tmp/x\\'y"])
def test_hydra_value_reads_back_as_the_same_path(value):
    from nvs.run.overrides import hydra_value

    assert _parsed(f"k={hydra_value(value)}") == value
    assert (hydra_value(value) == value) == (value in ("/tmp/plain/run", "/tmp/x\\"))  # quoted only where needed


def test_the_printed_resume_command_runs_for_a_non_ascii_run_directory(tmp_path):
    import shlex

    from nvs.run.training import resume_command

    out = tmp_path / "runs" / "café 1"
    argv = shlex.split(resume_command(out))
    assert argv[:3] == ["python", "-m", "nvs.train"] and argv[-1].startswith("hydra.run.dir=")
    assert _parsed(argv[-1]) == str(out)


def test_sweep_runs_under_a_non_ascii_directory_give_hydra_a_readable_sweep_dir(tmp_path):
    from nvs import sweep
    from tests.test_sweep import _study

    study = _study(tmp_path)
    root = tmp_path / "résultats" / "64px_10steps"
    cmd = sweep.multirun_command(study, study.rows[0], [0, 1], root, sweep.Launch(jobs=1, threads=1))
    (sweep_dir,) = [c for c in cmd if c.startswith("hydra.sweep.dir=")]
    assert _parsed(sweep_dir) == str(root.resolve())


# -- sweeps: one sweep per job, and no orphaned training process --------------------------------------------------------
def _gone(pid: int) -> bool:
    """The process has exited (a zombie nobody reaped counts as exited)."""
    import os

    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


def _wait(predicate, timeout: float = 20.0) -> bool:
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def test_a_job_lock_excludes_a_second_sweep_and_dies_with_its_holder(tmp_path):
    import os
    import signal
    import subprocess
    import sys

    from nvs.sweep.lock import JobLocks
    from tests.test_reliability import REPO

    first, second = JobLocks(tmp_path), JobLocks(tmp_path)
    assert first.acquire("full_s0") is None
    held = second.acquire("full_s0")
    assert held is not None and held.startswith(f"pid {os.getpid()} on ")
    assert second.acquire("full_s1") is None  # other jobs are free
    first.release()
    assert second.acquire("full_s0") is None
    second.release()
    # a sweep killed with -9 leaves its lock file behind, but not its lock
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from nvs.sweep.lock import JobLocks; "
                               f"assert JobLocks(sys.argv[1]).acquire('full_s0') is None; print('held', flush=True); "
                               "time.sleep(60)", str(tmp_path)], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert first.acquire("full_s0") == f"pid {holder.pid} on " + held.split(" on ", 1)[1].split(",")[0] + \
            ", since " + json.loads(first.path("full_s0").read_text())["since"]
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=10)
        assert first.path("full_s0").exists() and first.acquire("full_s0") is None
    finally:
        holder.kill()
        first.release()


def test_a_sweep_skips_the_jobs_another_sweep_holds(tmp_path, monkeypatch, capsys):
    from nvs.sweep import __main__ as sweep_main
    from nvs.sweep.lock import JobLocks

    study = tmp_path / "ref.yaml"
    study.write_text(json.dumps({"name": "ref", "title": "t", "paper_source": "none", "seeds": [0, 1], "size": 64,
                                 "steps": 2, "rows": [{"name": "copy", "reference": "copy_source", "data": "chairs"},
                                                      {"name": "warp", "reference": "gt_warp", "data": "chairs"}]}))
    launched = []
    monkeypatch.setattr(sweep_main, "launch_row", lambda study, jobs, *a, **k: launched.extend(jobs) or jobs)
    monkeypatch.setattr(sweep_main, "check_launch", lambda *a: None)
    runs = tmp_path / "runs"
    other = JobLocks(runs / "64px_2steps")  # another sweep, running job s0
    assert other.acquire("copy_s0") is None
    try:
        code = sweep_main.run([str(study), "--runs", str(runs), "--results", str(tmp_path / "results")])
    finally:
        other.release()
    err = capsys.readouterr().err
    assert [j.dir.name for j in launched] == ["warp_s0"] and code == 1, err
    assert "[sweep] copy s0: skipped, another sweep is running it (pid " in err


def test_killing_a_sweep_with_sigkill_ends_its_training_child(tmp_path):
    import os
    import signal
    import subprocess
    import sys

    from tests.test_reliability import REPO

    pidfile = tmp_path / "child.pid"
    child = f"import os, time; open({str(pidfile)!r}, 'w').write(str(os.getpid())); time.sleep(120)"
    parent = subprocess.Popen([sys.executable, "-c", "import os, sys; from nvs.sweep.launch import run_streaming; "
                               f"run_streaming([sys.executable, '-c', {child!r}], dict(os.environ))"], cwd=REPO)
    try:
        assert _wait(lambda: pidfile.exists() and pidfile.read_text().strip()), "the child never started"
        pid = int(pidfile.read_text())
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=10)
        assert _wait(lambda: _gone(pid), timeout=10), "the child outlived its sweep"
    finally:
        parent.kill()
        if pidfile.exists() and not _gone(int(pidfile.read_text())):
            os.kill(int(pidfile.read_text()), signal.SIGKILL)


# -- the viewer's uploads ------------------------------------------------------------------------------------------------
def _big_png(side: int) -> bytes:
    """A valid 1-bit PNG of side^2 pixels, all black, in a few kB (what a decompression bomb looks like)."""
    import struct
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    row = b"\x00" * (1 + (side + 7) // 8)  # filter byte + packed bits
    compressor = zlib.compressobj(9)
    idat = b"".join(compressor.compress(row) for _ in range(side)) + compressor.flush()
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 1, 0, 0, 0, 0))
            + chunk(b"IDAT", idat) + chunk(b"IEND", b""))


def test_an_upload_whose_header_declares_too_many_pixels_is_refused_before_decoding():
    from nvs.viewer.images import MAX_UPLOAD_PIXELS, decode_upload

    data = _big_png(8000)  # 64 megapixels in a few kB; decoding would take ~200 MB as RGB
    assert len(data) < 200_000 and 8000 * 8000 > MAX_UPLOAD_PIXELS
    with pytest.raises(UserError, match=r"photo.png: image too large \(8000x8000 pixels; the viewer takes at most 50 "
                                        r"megapixels\)"):
        decode_upload(data, 64, "photo.png")
    assert decode_upload(_big_png(100), 64).shape == (3, 64, 64)


def test_a_malformed_multipart_body_is_a_400_with_one_line(tmp_path):
    import asyncio

    from aiohttp.test_utils import TestClient, TestServer

    from nvs.viewer.server import build_app
    from tests.test_viewer import _net, _session

    app = build_app(_session(_net(tmp_path, "model=tatarchenko")), {"model": "tatarchenko"})

    async def probe():
        async with TestClient(TestServer(app)) as client:
            bad = await client.post("/api/upload", data=b"--xyz\r\nnot a part header at all",
                                    headers={"Content-Type": "multipart/form-data; boundary=xyz"})
            missing = await client.post("/api/upload", data=b"garbage",
                                        headers={"Content-Type": "multipart/form-data"})
            return [(r.status, await r.json()) for r in (bad, missing)]

    for status, body in asyncio.run(probe()):
        assert status == 400 and body["error"].startswith("malformed upload: not a multipart form"), (status, body)
        assert "\n" not in body["error"] and "Traceback" not in body["error"]
