"""docs/extending.md's worked example, run as the page writes it: a method, its loss and a dataset converter that
live outside nvs/ (docs/extending), trained for a few steps and evaluated through the real entry point."""

from __future__ import annotations

import csv
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "extending.md"
EXAMPLE = REPO / "docs" / "extending"


def _doc_commands() -> dict[str, list[str]]:
    """The page's two commands (converter, training), split into argv after their PYTHONPATH prefix."""
    block = re.search(r"## 4\. Train, evaluate, view\n\n```bash\n(.*?)```", DOC.read_text(), re.S).group(1)
    lines = [ln for ln in block.splitlines() if ln.strip()]
    assert all(ln.startswith("PYTHONPATH=docs/extending python -m ") for ln in lines), lines
    argv = [shlex.split(ln.split(" ", 1)[1]) for ln in lines]
    return {a[2]: a for a in argv}  # by module: mynvs.turntable, nvs.train


def _turntable(root: Path, objects: int = 4, size: int = 64) -> Path:
    rng = np.random.default_rng(0)
    for i in range(objects):
        (root / f"obj{i}").mkdir(parents=True)
        for az in range(0, 360, 20):
            for el in (0, 10, 20):
                img = np.full((size, size, 3), 255, np.uint8)
                x, y = rng.integers(8, size // 2, 2)
                img[y:y + 20, x:x + 24] = rng.integers(0, 200, 3)
                Image.fromarray(img).save(root / f"obj{i}" / f"az{az}_el{el}.png")
    return root


def test_the_extending_example_converts_trains_and_evaluates_outside_nvs(tmp_path):
    commands = _doc_commands()
    env = {**os.environ, "PYTHONPATH": str(EXAMPLE)}

    # the dataset: the page's converter on a turntable folder
    convert = commands["mynvs.turntable"]
    data = tmp_path / "turntable_64"
    res = subprocess.run([sys.executable, *convert[1:3], str(_turntable(tmp_path / "tt")), str(data)], cwd=REPO,
                         env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert (data / "id_train.txt").read_text().split() == ["obj0", "obj1"]
    pairs = (data / "eval_chair_40.txt").read_text().splitlines()
    assert len(pairs) == 18 * 3 and pairs[0] == "obj3_0_0 obj3_20_0"

    # the method and its loss: the page's training command, shortened, with test on
    train = commands["nvs.train"]
    assert "model=warp_refine" in train and "data=turntable" in train
    argv = [a for a in train[1:] if not a.startswith("trainer.max_steps=")]
    res = subprocess.run([sys.executable, *argv, f"data.root={data}", f"paths.log_dir={tmp_path / 'runs'}",
                          "trainer.max_steps=3", "trainer.val_check_interval=3", "trainer.log_every_n_steps=1",
                          "data.loader.batch_size=2", "data.loader.limit_test_pairs=4", "trainer.enable_progress_bar=false"],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    run_dir = next((tmp_path / "runs").rglob("metrics.json")).parent
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["model"] == "warp_refine" and m["data"] == "turntable" and m["steps"] == 3
    stated = re.search(r"([\d,]+) parameters at `channels: 16`, the `params`", DOC.read_text()).group(1)
    assert m["params"] == int(stated.replace(",", "")) and m["test"]["n_pairs"] == 4 and 0 < m["test"]["l1"] < 1
    config = (run_dir / ".hydra" / "config.yaml").read_text()
    assert "_target_: mynvs.net.WarpRefine" in config and "_target_: mynvs.losses.DepthTV" in config
    with open(run_dir / "csv" / "metrics.csv") as f:
        header = next(csv.reader(f))
    assert {"train/loss/recon", "train/loss/depth_tv", "train/loss/total"} <= set(header)


def test_the_page_shows_the_turntable_layout_the_converter_reads():
    sys.path.insert(0, str(EXAMPLE))
    try:
        from mynvs.turntable import NAME
    finally:
        sys.path.remove(str(EXAMPLE))
    block = re.search(r"```\n(my_turntable/\n.*?)```", DOC.read_text(), re.S).group(1)
    images = [ln.strip() for ln in block.splitlines() if ln.strip().endswith(".png")]
    assert len(images) >= 4 and all(NAME.search(name) for name in images), images
    assert {"chair_a/", "chair_b/", "chair_c/"} <= {ln.strip() for ln in block.splitlines()}  # the 3 splits' minimum


def test_a_network_without_n_scales_and_too_few_scales_is_one_line_at_step_one(objects_root, tmp_path):
    """A model config without a loss override keeps recon's four scale weights; a one-scale network that does not
    declare ``n_scales`` is refused with one line and exit 2 at its first step, and leaves no run folder."""
    (tmp_path / "noscales.py").write_text(
        "from mynvs.net import WarpRefine\n\n\nclass NoScales(WarpRefine):\n    n_scales = None\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(EXAMPLE), str(tmp_path), str(REPO)])}
    runs = tmp_path / "runs"
    res = subprocess.run([sys.executable, "-m", "nvs.train", "--config-dir", str(EXAMPLE / "conf"), "model=warp_refine",
                          "model._target_=noscales.NoScales", "loss=[recon]", f"data.root={objects_root}",
                          f"paths.log_dir={runs}", "trainer.max_steps=2", "data.loader.batch_size=2",
                          "trainer.enable_progress_bar=false", "trainer.precision=32-true"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 2, res.stderr[-3000:]
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert errors == ["error: loss.recon.scale_weights has 4 weights but the model predicts 1 scale(s); use "
                      "loss=[recon_final,...] or loss.recon.scale_weights=[1.0]"], res.stderr[-3000:]
    assert "Traceback" not in res.stderr and not list(runs.rglob("*.ckpt"))
    assert not (runs / "train").exists() or not any((runs / "train").iterdir())
