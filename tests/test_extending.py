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
    assert 0 < m["params"] < 100_000 and m["test"]["n_pairs"] == 4 and 0 < m["test"]["l1"] < 1
    config = (run_dir / ".hydra" / "config.yaml").read_text()
    assert "_target_: mynvs.net.WarpRefine" in config and "_target_: mynvs.losses.DepthTV" in config
    with open(run_dir / "csv" / "metrics.csv") as f:
        header = next(csv.reader(f))
    assert {"train/loss/recon", "train/loss/depth_tv", "train/loss/total"} <= set(header)
