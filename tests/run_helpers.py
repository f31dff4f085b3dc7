"""Training runs and command lines inside the test process: what a test of the run itself (its checkpoints,
metrics.json) or of a command's answer (exit code, error line, what it leaves behind) needs, without the ~5 s of CPU a
new Python spends importing torch and Lightning. Starting a command as its own process (``python -m``, signals, a
second process) is tested through real subprocesses elsewhere."""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import sys
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


def cli_in_process(module: str, argv: list[str], monkeypatch) -> tuple[int, str]:
    """``python -m nvs.<module> *argv`` in this process -> (exit code, stderr): the command's ``main_cli`` (or its
    Hydra ``main``) with ``sys.argv`` set, stdout discarded. A traceback that would reach the terminal (a bug, exit 1)
    is in the returned stderr, as it would be on the command line."""
    mod = importlib.import_module(f"nvs.{module}")
    entry = getattr(mod, "main_cli", None) or mod.main
    monkeypatch.setenv("HYDRA_MAIN_MODULE", "__main__")  # Hydra finds conf/ from the file, as under `python -m`
    monkeypatch.setattr(sys, "argv", [f"nvs/{module.replace('.', '/')}.py", *argv])
    err = io.StringIO()
    code = 0
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            entry()
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    return code, err.getvalue()
