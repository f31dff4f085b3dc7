"""Artifacts every run leaves (metrics.json and the per-image CSV, written atomically), and its output folder:
checked writable at start, removed when the run fails before its first step."""

from __future__ import annotations

import io
import os
import shutil
import sys
import tempfile
from pathlib import Path

import pandas as pd

from nvs.core.atomic import json_text, write_files, write_json, write_text
from nvs.core.errors import UserError

METRICS, PER_IMAGE = "metrics.json", "test_per_image.csv"


def _per_image_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    pd.DataFrame(rows).to_csv(buf, index=False, float_format="%.6g")
    return buf.getvalue()


def write_per_image(path: str | Path, rows: list[dict]) -> None:
    write_text(path, _per_image_csv(rows))


def write_metrics(path: str | Path, payload: dict) -> None:
    write_json(path, payload)


def write_run_results(out_dir: str | Path, payload: dict, rows: list[dict] | None = None) -> None:
    """``metrics.json`` and (given ``rows``) ``test_per_image.csv`` in ``out_dir``: both or neither. A disk that fills
    (or a kill) leaves the previous pair as it was; metrics.json, which marks a run as finished, is renamed last."""
    files = {} if rows is None else {Path(out_dir) / PER_IMAGE: _per_image_csv(rows).encode()}
    files[Path(out_dir) / METRICS] = json_text(payload).encode()
    write_files(files)


def run_record(module, run, choice, training: dict | None = None) -> dict:
    """The head of ``metrics.json``, one schema for ``nvs.train`` and ``nvs.evaluate``: the model, data, size and
    seed, a trained run's ``training`` keys (steps, wall time, throughput, overrides), then the network's size and
    where and how it ran. ``run``: the run's config; ``choice``: its ``nvs.run.precision.Choice``."""
    from nvs.core.provenance import device_name, git_sha
    from nvs.run.build import parameter_count

    return {"model": module.model_name, "data": run.data.get("name"), "image_size": run.data.size,
            "seed": int(run.seed), **(training or {}), "params": parameter_count(module.net),
            "device": device_name(module.device), "precision": str(choice.precision),
            "precision_choice": choice.record(), "git_sha": git_sha()}


def test_record(module, test_s: float, checkpoint: str | None, tested_weights: str) -> dict:
    """The test part of ``metrics.json``: time per image (the whole test loop, and the forward alone), which weights
    were tested, and the mean of every per-image metric."""
    return {"eval_ms_per_image": 1000 * test_s / max(len(module.test_rows), 1),
            "eval_forward_ms_per_image": module.test_forward_ms_per_image(), "checkpoint": checkpoint,
            "tested_weights": tested_weights, "test": module.test_summary()}


def summary_line(test: dict) -> str:
    """One printed line of the mean test metrics."""
    return "test: " + ", ".join(f"{k}={v:.4f}" for k, v in test.items() if isinstance(v, float))


def is_global_zero() -> bool:
    """Rank 0 of a distributed run (or a plain run): the one process that writes and removes run files.

    Lightning's own record once it is loaded; before that (a command that stops at its config) the rank a launcher
    gives in the environment, read as Lightning reads it, so that an early error costs no Lightning import."""
    if "lightning" not in sys.modules:
        rank = next((os.environ[k] for k in ("RANK", "LOCAL_RANK", "SLURM_PROCID", "JSM_NAMESPACE_RANK")
                     if k in os.environ), "0")
        return rank.strip() in ("", "0")
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
        why = "a file is in the way" if _blocker(directory) else (err.strerror or str(err))
        raise UserError(f"{directory}: output location is not writable ({why}); choose another "
                        "(hydra.run.dir=..., paths.log_dir=...)") from None


def _blocker(directory: Path) -> Path | None:
    """The file (not folder) at ``directory`` or at one of its parents, if any."""
    for p in (directory, *directory.parents):
        if p.exists():
            return None if p.is_dir() else p
    return None


def check_creatable(directory: str | Path) -> None:
    """UserError if ``directory`` cannot be created: a file in the way, or its nearest existing parent is not
    writable. Creates nothing (for the run directory, before Hydra makes it)."""
    directory = Path(directory).absolute()
    blocker = _blocker(directory)
    parent = next((p for p in (directory, *directory.parents) if p.exists()), None)
    if blocker is not None or (parent is not None and not os.access(parent, os.W_OK | os.X_OK)):
        why = f"{blocker} is a file" if blocker is not None else f"{parent} is not writable"
        raise UserError(f"{directory}: cannot create the run directory ({why}); choose another "
                        "(hydra.run.dir=..., paths.log_dir=...)")


def run_dir_of(argv: list[str], task: str) -> Path:
    """The folder Hydra will create for ``argv`` (its parent for the default, time-stamped one)."""
    multirun = any(a in ("-m", "--multirun") for a in argv)
    key = "hydra.sweep.dir=" if multirun else "hydra.run.dir="
    values = {a.split("=", 1)[0].lstrip("+"): a.split("=", 1)[1].strip("'\"") for a in argv if "=" in a}
    if key[:-1] in values and "${" not in values[key[:-1]]:
        return Path(values[key[:-1]])
    if "paths.log_dir" in values and "${" not in values["paths.log_dir"]:
        return Path(values["paths.log_dir"]) / task
    root = values.get("paths.root_dir") or os.environ.get("NVS_ROOT") or "."
    return Path(root) / "runs" / task


# What a run writes before its first step: Hydra's config copy and log, the CSV logger, the checkpoint folder.
_UNSTARTED = (".hydra", "csv", "checkpoints")


def existing_files(out_dir: str | Path) -> frozenset[str]:
    """Every file and folder under ``out_dir`` (relative POSIX paths): what a failed run must leave in place."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        return frozenset()
    return frozenset(p.relative_to(out_dir).as_posix() for p in out_dir.rglob("*"))


def remove_unstarted_run(out_dir: str | Path, job_name: str, existing: frozenset[str] = frozenset()) -> bool:
    """Remove what a run that failed before its first step wrote into ``out_dir``, then the folder if that empties
    it. A folder holding a checkpoint or a metrics.json (a run to resume, or finished) is left alone, and so is
    anything the run did not write: every path in ``existing`` (what was there before it started) and everything
    outside the run's own folders. Hydra's ``.hydra/`` and job log are the run's. Returns whether the folder is gone."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir() or (out_dir / "metrics.json").exists() or any(out_dir.glob("checkpoints/*.ckpt")):
        return False
    for name in _UNSTARTED:
        path = out_dir / name
        if not path.is_dir() or path.is_symlink():
            continue
        if name == ".hydra":
            shutil.rmtree(path, ignore_errors=True)
            continue
        for p in sorted(path.rglob("*"), key=lambda q: len(q.parts), reverse=True) + [path]:  # deepest first
            if p.relative_to(out_dir).as_posix() in existing:
                continue
            try:
                if p.is_dir() and not p.is_symlink():
                    p.rmdir()
                else:
                    p.unlink()
            except OSError:  # a folder still holding what was there before
                pass
    (out_dir / f"{job_name}.log").unlink(missing_ok=True)
    try:
        out_dir.rmdir()
    except OSError:
        return False
    return True
