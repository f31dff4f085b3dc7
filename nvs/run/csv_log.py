"""The CSV logger's ``csv/metrics.csv``: a resumed run continues it (Lightning's deletes it and starts afresh), and a
write the disk refuses leaves it whole.

The curve figures and the committed job files read that file: after a resume it holds every step once, the rows of
the segments before the checkpoint kept and the later ones appended; a disk that fills while rows are appended cuts
the partial rows off again and stops the run with one line naming the file.
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter

from nvs.core.atomic import WriteFailed, write_text


def continue_from(logger: CSVLogger, step: int | None) -> None:
    """Give ``logger`` nvs's writer. Resuming from a checkpoint at global step ``step``: keep the rows it wrote before
    it (Lightning labels the training rows of global step s as s - 1; validation and test rows carry s itself, the
    module logs ``step``), drop the later ones (those steps are trained again), append the new ones. ``step=None``:
    a fresh run (Lightning's start: an old metrics.csv in the folder is removed).

    Lightning's logger deletes metrics.csv when its writer starts in a non-empty folder: it gets this writer first.
    """
    if logger._experiment is None:
        logger._fs.makedirs(logger.root_dir, exist_ok=True)
        logger._experiment = _CurveWriter(logger.log_dir, None if step is None else int(step))


class _CurveWriter(ExperimentWriter):
    def __init__(self, log_dir: str, keep_before: int | None):
        self._keep_before = keep_before
        super().__init__(log_dir)

    def save(self) -> None:
        """Lightning's save (the new rows appended); when the file system refuses, the file is cut back to what it
        held before (no partial row is ever read as a number) and one WriteFailed names it."""
        path = Path(self.metrics_file_path)
        size = path.stat().st_size if path.is_file() else None
        try:
            super().save()
        except OSError as err:
            if size is None:
                path.unlink(missing_ok=True)
            elif path.is_file() and path.stat().st_size > size:
                os.truncate(path, size)  # (frees space: works on a full disk)
            if isinstance(err, WriteFailed):
                raise
            raise WriteFailed(path, err) from None

    def _rewrite_with_new_header(self, fieldnames: list[str]) -> None:
        # a new column rewrites the whole file: atomically, so that a full disk cannot leave it half-written
        with open(self.metrics_file_path, newline="") as f:
            rows = list(csv.DictReader(f))
        self._write(Path(self.metrics_file_path), fieldnames, rows)

    @staticmethod
    def _write(path: Path, keys: list[str], rows: list[dict]) -> None:
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
        write_text(path, buf.getvalue())

    def _check_log_dir_exists(self) -> None:
        path = Path(self.metrics_file_path)
        if self._keep_before is None:
            return super()._check_log_dir_exists()
        if not path.is_file():
            return
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            rows = [r for r in reader if _step(r) < self._keep_before
                    or (_step(r) == self._keep_before and _evaluation(r))]
            keys = sorted(reader.fieldnames or [])
        # Lightning appends rows in the sorted order of the keys it knows: the kept file is written in that order.
        self._write(path, keys, rows)
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
