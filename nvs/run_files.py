"""Artifacts every run leaves (metrics.json and the per-image CSV, written atomically), and its output folder:
checked writable at start, removed when the run fails before its first step."""

from __future__ import annotations

import io
import os
import shutil
import tempfile
from pathlib import Path

import pandas as pd

from nvs.atomic import write_json, write_text
from nvs.errors import UserError


def write_per_image(path: str | Path, rows: list[dict]) -> None:
    buf = io.StringIO()
    pd.DataFrame(rows).to_csv(buf, index=False, float_format="%.6g")
    write_text(path, buf.getvalue())


def write_metrics(path: str | Path, payload: dict) -> None:
    write_json(path, payload)


def summary_line(test: dict) -> str:
    """One printed line of the mean test metrics."""
    return "test: " + ", ".join(f"{k}={v:.4f}" for k, v in test.items() if isinstance(v, float))


def is_global_zero() -> bool:
    """Rank 0 of a distributed run (or a plain run): the one process that writes and removes run files."""
    from lightning.pytorch.utilities.rank_zero import rank_zero_only

    return getattr(rank_zero_only, "rank", 0) == 0


def check_writable(directory: str | Path) -> None:
    """Create ``directory`` if needed and write a probe file in it; UserError (one line) if the system refuses."""
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-probe.", dir=directory)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise UserError(f"{directory}: output location is not writable ({err.strerror or err}); choose another "
                        "(hydra.run.dir=..., paths.log_dir=...)") from None


# What a run writes before its first step: Hydra's config copy and log, the CSV logger, the checkpoint folder.
_UNSTARTED = (".hydra", "csv", "checkpoints")


def remove_unstarted_run(out_dir: str | Path, job_name: str) -> bool:
    """Remove what a run that failed before its first step wrote into ``out_dir``, then the folder if that empties
    it. A folder holding a checkpoint or a metrics.json (a run to resume, or finished) is left alone, and so is
    anything the run did not write. Returns whether the folder is gone."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir() or (out_dir / "metrics.json").exists() or any(out_dir.glob("checkpoints/*.ckpt")):
        return False
    for name in _UNSTARTED:
        path = out_dir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
    (out_dir / f"{job_name}.log").unlink(missing_ok=True)
    try:
        out_dir.rmdir()
    except OSError:
        return False
    return True
