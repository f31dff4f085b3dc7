"""Report section 5: the same short training run twice with one seed (bitwise equal?) and once with another."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

from nvs.synthetic import write_objects_root

DETERMINISM_STEPS = 4
CHECKOUT = Path(__file__).resolve().parents[2]  # the nvs that runs this report runs the training command too


def determinism_run(data_root: Path, out_dir: Path, seed: int, steps: int = DETERMINISM_STEPS) -> dict:
    """A short ``python -m nvs.train`` run (train, validate, test) on the fixture dataset -> its test metrics.

    The training command itself, in a child process: the report measures what users run, and a tool does not import
    another tool's CLI module.
    """
    overrides = [f"data.root={data_root}", f"seed={seed}", f"trainer.max_steps={steps}",
                 f"trainer.val_check_interval={steps // 2}", "data.loader.batch_size=2", "loss=[recon,warp]",
                 "trainer.enable_progress_bar=false", "trainer.log_every_n_steps=1",
                 f"paths.root_dir={out_dir}", f"hydra.run.dir={out_dir}"]
    res = subprocess.run([sys.executable, "-m", "nvs.train", *overrides], capture_output=True, text=True,
                         cwd=CHECKOUT)
    if res.returncode != 0:
        raise RuntimeError(f"python -m nvs.train {' '.join(overrides)} failed ({res.returncode}):\n"
                           f"{res.stderr[-2000:]}")
    return json.loads((out_dir / "metrics.json").read_text())["test"]


def determinism_section(work: str) -> list[list]:
    root = write_objects_root(Path(work) / "chairs_64")
    a = determinism_run(root, Path(work) / "det_a", seed=0)
    b = determinism_run(root, Path(work) / "det_b", seed=0)
    c = determinism_run(root, Path(work) / "det_c", seed=1)
    keys = [k for k in a if k != "n_pairs"]
    same = [k for k in keys if a[k] == b[k] or (math.isnan(a[k]) and math.isnan(b[k]))]
    differ = [k for k in keys if a[k] != c[k]]
    return [["seed 0 vs seed 0", f"{len(same)}/{len(keys)} bitwise equal", f"l1 {a['l1']:.6f} vs {b['l1']:.6f}"],
            ["seed 0 vs seed 1 (control)", f"{len(differ)}/{len(keys)} differ", f"l1 {a['l1']:.6f} vs {c['l1']:.6f}"]]
