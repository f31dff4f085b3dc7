"""Training runs inside the test process: what a test of the run itself (its checkpoints, metrics.json) needs, without
the seconds a new Python spends importing torch and Lightning. The command line's own behaviour (Hydra's run
directory, its output, exit codes) is tested through ``python -m nvs.train`` elsewhere."""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import OmegaConf

from tests.conftest import compose_train


def train_in_process(objects_root, out: Path, *overrides: str) -> dict:
    """Train the default model on the fixture objects into ``out`` as ``python -m nvs.train`` would (without its
    progress bar); returns the run's metrics.json."""
    from nvs.run.training import run

    cfg = compose_train([f"data.root={objects_root}", f"paths.log_dir={out}", "trainer.enable_progress_bar=false",
                         *overrides])
    cfg.paths.output_dir = str(out)
    OmegaConf.resolve(cfg)
    run(cfg, out)
    return json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").is_file() else {}
