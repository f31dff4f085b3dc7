"""Report section 5: the same short training run twice with one seed (bitwise equal?) and once with another."""

from __future__ import annotations

import math
from pathlib import Path

from omegaconf import OmegaConf

from nvs.data.synthetic import write_objects_root
from nvs.run.compose import compose

DETERMINISM_STEPS = 4


def determinism_run(data_root: Path, out_dir: Path, seed: int, steps: int = DETERMINISM_STEPS) -> dict:
    """A short training run (train, validate, test) on the fixture dataset -> its test metrics.

    The library call ``nvs.run.training.run`` that ``python -m nvs.train`` makes, in this process, on the real
    train.yaml with these overrides.
    """
    from nvs.run.training import run

    overrides = [f"data.root={data_root}", f"seed={seed}", f"trainer.max_steps={steps}",
                 f"trainer.val_check_interval={steps // 2}", "data.loader.batch_size=2", "loss=[recon,warp]",
                 "trainer.enable_progress_bar=false", "trainer.log_every_n_steps=1", f"paths.root_dir={out_dir}"]
    cfg = compose("train", overrides)
    cfg.paths.output_dir = str(out_dir)
    OmegaConf.resolve(cfg)
    out_dir.mkdir(parents=True, exist_ok=True)
    return run(cfg, out_dir)["test"]


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
