"""A resumed run continues the CSV logger's ``csv/metrics.csv`` (Lightning's deletes it and starts afresh).

The curve figures and the committed job files read that file: after a resume it holds every step once, the rows of
the segments before the checkpoint kept and the later ones appended.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter

from nvs.core.atomic import write_text


def continue_from(logger: CSVLogger, step: int) -> None:
    """Resuming from a checkpoint at global step ``step``: keep the rows ``logger`` wrote before it (Lightning labels
    the training rows of global step s as s - 1; validation and test rows carry s itself, the module logs ``step``),
    drop the later ones (those steps are trained again), append the new ones.

    Lightning's logger deletes metrics.csv when its writer starts in a non-empty folder: it gets this writer first.
    """
    if logger._experiment is None:
        logger._fs.makedirs(logger.root_dir, exist_ok=True)
        logger._experiment = _ContinuedWriter(logger.log_dir, int(step))


class _ContinuedWriter(ExperimentWriter):
    def __init__(self, log_dir: str, keep_before: int):
        self._keep_before = keep_before
        super().__init__(log_dir)

    def _check_log_dir_exists(self) -> None:
        path = Path(self.metrics_file_path)
        if not path.is_file():
            return
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            rows = [r for r in reader if _step(r) < self._keep_before
                    or (_step(r) == self._keep_before and _evaluation(r))]
            keys = sorted(reader.fieldnames or [])
        # Lightning appends rows in the sorted order of the keys it knows: the kept file is written in that order.
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
        write_text(path, buf.getvalue())
        self.metrics_keys = keys


def _step(row: dict) -> float:
    try:
        return float(row.get("step") or 0)
    except ValueError:
        return 0.0


def _evaluation(row: dict) -> bool:
    """A row of a validation (or test): its values are all val/ or test/ metrics (the checkpoint follows them)."""
    filled = [k for k, v in row.items() if v not in ("", None) and k not in ("step", "epoch")]
    return bool(filled) and all(k.startswith(("val/", "test/")) for k in filled)
