"""A finished run directory as the tools see it: its label, dataset, whether it trained, and its checkpoint.

Shared by the sweep runner (``--figures``) and ``python -m nvs.figures``; it reads files only.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from nvs.core.errors import UserError
from nvs.models.reference import REFERENCE_MODELS



@dataclass
class Run:
    dir: Path
    label: str
    data: str
    reference: bool


def read_metrics(run_dir: Path) -> dict:
    """The run's ``metrics.json``; a UserError naming it when it is missing or unreadable."""
    path = Path(run_dir) / "metrics.json"
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        raise UserError(f"{path}: missing or unreadable (is the run finished?)") from None


def run_from_dir(d: Path) -> Run:
    """A run named after its directory, its dataset and kind read from its metrics.json."""
    m = read_metrics(d)
    return Run(Path(d), Path(d).name, str(m.get("data", "")), m.get("model") in REFERENCE_MODELS)


def checkpoint_of(run_dir: Path) -> Path:
    """The run's validation-selected checkpoint (metrics.json's, else best-*.ckpt, else last.ckpt)."""
    m = read_metrics(run_dir)
    if m.get("checkpoint") and Path(m["checkpoint"]).is_file():
        return Path(m["checkpoint"])
    best = sorted((Path(run_dir) / "checkpoints").glob("best-*.ckpt"))
    if best:
        return best[-1]
    last = Path(run_dir) / "checkpoints" / "last.ckpt"
    if last.is_file():
        return last
    raise UserError(f"{run_dir}: no checkpoint to draw from")
