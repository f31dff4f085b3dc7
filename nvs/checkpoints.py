"""How training writes checkpoints: atomically, failing loudly, and with ``last`` sharing ``best``'s storage.

- :class:`AtomicCheckpointIO` (a Lightning CheckpointIO plugin, set by ``nvs.train``): ``torch.save`` to memory,
  then :func:`nvs.atomic.write_bytes` (temp file, fsync, rename). Lightning's own save ignores a PermissionError
  (the run then trains to the end and finds no checkpoint); here any OSError stops training with one line.
- :class:`ModelCheckpoint` (conf/callbacks/default.yaml): ``last.ckpt`` written at the same step as the best
  checkpoint is a hard link to it (one copy on disk, ~120 MB saved per run). A later write of either file replaces
  it by rename, so the other keeps its bytes; a deleted old best leaves ``last`` intact.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.callbacks import ModelCheckpoint as _LightningModelCheckpoint
from lightning.pytorch.plugins.io import TorchCheckpointIO

from nvs.atomic import write_bytes
from nvs.errors import UserError


class CheckpointWriteError(UserError):
    """A checkpoint could not be written (permissions, disk full): training stops."""


class AtomicCheckpointIO(TorchCheckpointIO):
    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options=None) -> None:
        buf = io.BytesIO()
        torch.save(checkpoint, buf)
        try:
            write_bytes(path, buf.getvalue())
        except OSError as err:
            raise CheckpointWriteError(f"cannot write checkpoint {path}: {err.strerror or err}; training stopped "
                                       "(free space or fix the permissions, then resume with the same command)") \
                from None


def link_or_copy(src: str | Path, dst: str | Path) -> None:
    """Make ``dst`` the same file as ``src`` (hard link; a copy across file systems), replacing ``dst`` atomically."""
    src, dst = Path(src), Path(dst)
    tmp = dst.with_name(f".{dst.name}.link.tmp")
    tmp.unlink(missing_ok=True)
    try:
        os.link(src, tmp)
    except OSError:
        write_bytes(tmp, src.read_bytes())
    os.replace(tmp, dst)


class ModelCheckpoint(_LightningModelCheckpoint):
    """Lightning's ModelCheckpoint; ``last`` at the step of the best checkpoint is a hard link to it."""

    def _save_checkpoint(self, trainer, filepath: str) -> None:
        same_step = self._last_global_step_saved == trainer.global_step and self._last_checkpoint_saved
        last = Path(filepath).name.startswith(self.CHECKPOINT_NAME_LAST)
        if not (same_step and last and Path(self._last_checkpoint_saved).is_file()):
            return super()._save_checkpoint(trainer, filepath)
        if trainer.is_global_zero:
            try:
                link_or_copy(self._last_checkpoint_saved, filepath)
            except OSError as err:
                raise CheckpointWriteError(f"cannot write checkpoint {filepath}: {err.strerror or err}; training "
                                           "stopped") from None
        trainer.strategy.barrier()
        self._last_global_step_saved = trainer.global_step
        self._last_checkpoint_saved = filepath
