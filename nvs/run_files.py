"""Artifacts every run leaves: metrics.json and the per-image CSV, written atomically."""

from __future__ import annotations

import io
from pathlib import Path

import pandas as pd

from nvs.atomic import write_json, write_text


def write_per_image(path: str | Path, rows: list[dict]) -> None:
    buf = io.StringIO()
    pd.DataFrame(rows).to_csv(buf, index=False, float_format="%.6g")
    write_text(path, buf.getvalue())


def write_metrics(path: str | Path, payload: dict) -> None:
    write_json(path, payload)


def summary_line(test: dict) -> str:
    """One printed line of the mean test metrics."""
    return "test: " + ", ".join(f"{k}={v:.4f}" for k, v in test.items() if isinstance(v, float))
