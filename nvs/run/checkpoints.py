"""Checkpoints: how training writes them, and the one way every tool reads a run back from one.

Writing (atomically, failing loudly, ``last`` sharing ``best``'s storage):
- :class:`AtomicCheckpointIO` (a Lightning CheckpointIO plugin, set by ``nvs.train``): ``torch.save`` to memory,
  then :func:`nvs.core.atomic.write_bytes` (temp file, fsync, rename). Lightning's own save ignores a PermissionError
  (the run then trains to the end and finds no checkpoint); here any OSError stops training with one line.
- :class:`ModelCheckpoint` (conf/callbacks/default.yaml): ``last.ckpt`` every ``last_every_n_steps`` training
  steps, after every validation and at the end of training; written at the same step as the best checkpoint it is a
  hard link to it (one copy on disk, ~120 MB saved per run). A later write of either file replaces it by rename, so
  the other keeps its bytes; a deleted old best leaves ``last`` intact. Every checkpoint carries a content hash of
  its weights (:mod:`nvs.core.weights_digest`, stamped by the module).

Reading: :func:`nvs.run.checkpoint_files.read_checkpoint` is the one way a checkpoint file is opened (zip directory,
every member's CRC, the weights' content hash); resume (``resume_checkpoint``: the newest checkpoint by its recorded
step), the test after training, ``nvs.evaluate``, the viewer and ``nvs.figures`` go through it.
:func:`restore_run_config` gives the run's own config (with data from the command line when given) and the
checkpoint; :func:`restore_module` rebuilds its module with the weights, every missing, unexpected or misshapen
weight being one clear error.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.callbacks import ModelCheckpoint as _LightningModelCheckpoint
from lightning.pytorch.plugins.io import TorchCheckpointIO
from omegaconf import DictConfig, OmegaConf

from nvs.core.atomic import reason, write_bytes
from nvs.core.errors import UserError
from nvs.core.legacy import upgrade_targets
from nvs.models.reference import REFERENCE_MODELS
from nvs.module.lightning_module import NVSModule
from nvs.run.build import build_module
from nvs.run.checkpoint_files import read_checkpoint
from nvs.run.run_checks import model_mismatch


class CheckpointWriteError(UserError):
    """A checkpoint could not be written (permissions, disk full): training stops; the file it would have replaced
    is unchanged (atomic writes), so the run resumes from it."""

    def __init__(self, path, err: OSError):
        kept = "the previous one is unchanged" if Path(path).is_file() else "none was there before"
        super().__init__(f"cannot write checkpoint {path}: {reason(err)}; training stopped, {kept} (free space or "
                         "fix the permissions, then resume with the same command)")


class AtomicCheckpointIO(TorchCheckpointIO):
    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options=None) -> None:
        buf = io.BytesIO()
        torch.save(checkpoint, buf)
        try:
            write_bytes(path, buf.getvalue())
        except OSError as err:
            raise CheckpointWriteError(path, err) from None


def link_or_copy(src: str | Path, dst: str | Path) -> None:
    """Make ``dst`` the same file as ``src`` (hard link; a copy across file systems), replacing ``dst`` atomically."""
    src, dst = Path(src), Path(dst)
    tmp = dst.with_name(f".{dst.name}.link.tmp")
    tmp.unlink(missing_ok=True)
    try:
        os.link(src, tmp)
    except OSError:
        write_bytes(tmp, src.read_bytes())
    try:
        os.replace(tmp, dst)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise


class ModelCheckpoint(_LightningModelCheckpoint):
    """Lightning's ModelCheckpoint, and: ``last.ckpt`` every ``last_every_n_steps`` training steps (None: only at
    validations), after every validation and at the end of training, not only with a new best; at the best's step a
    hard link to it. A run resumed in a moved directory keeps its best and last (no ``last-v1.ckpt``)."""

    def __init__(self, *args, last_every_n_steps: int | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        if last_every_n_steps is not None and (not isinstance(last_every_n_steps, int) or last_every_n_steps < 1):
            raise UserError(f"callbacks.model_checkpoint.last_every_n_steps={last_every_n_steps}: expected a positive "
                            "integer or null")
        self.last_every_n_steps = last_every_n_steps
        self._last_step: int | None = None  # the step last.ckpt holds (written by this process)
        self._last_writes = 0

    def _save_checkpoint(self, trainer, filepath: str) -> None:
        # The rows logged so far reach the disk before the checkpoint: a kill after it loses no part of the curve.
        for logger in trainer.loggers:
            logger.save()
        same_step = self._last_global_step_saved == trainer.global_step and self._last_checkpoint_saved
        last = Path(filepath).name.startswith(self.CHECKPOINT_NAME_LAST)
        if not (same_step and last and Path(self._last_checkpoint_saved).is_file()):
            return super()._save_checkpoint(trainer, filepath)
        if trainer.is_global_zero:
            try:
                link_or_copy(self._last_checkpoint_saved, filepath)
            except OSError as err:
                raise CheckpointWriteError(filepath, err) from None
        trainer.strategy.barrier()
        self._last_global_step_saved = trainer.global_step
        self._last_checkpoint_saved = filepath

    def _save_last_checkpoint(self, trainer, monitor_candidates) -> None:
        super()._save_last_checkpoint(trainer, monitor_candidates)
        self._last_step = trainer.global_step
        self._last_writes += 1

    def _save_last_now(self, trainer, force: bool = False) -> None:
        fitting = trainer.state.fn == "fit" and not trainer.sanity_checking and not trainer.fast_dev_run
        if not (self.save_last and fitting and trainer.global_step > 0) or (self._last_step == trainer.global_step
                                                                            and not force):
            return
        best_step = self._last_global_step_saved  # Lightning skips a best at a step it saved: last does not count
        self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
        self._last_global_step_saved = best_step

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
        n = self.last_every_n_steps
        # A validation due after this step saves last itself, after it (a checkpoint saved before it would resume
        # past the validation without running it).
        if n and trainer.global_step % n == 0 and not validation_follows(trainer):
            self._save_last_now(trainer)

    def on_validation_end(self, trainer, pl_module) -> None:
        writes = self._last_writes
        super().on_validation_end(trainer, pl_module)
        if self._last_writes == writes:  # no new best (or last written before this validation): last now
            self._save_last_now(trainer, force=True)

    def on_train_end(self, trainer, pl_module) -> None:
        super().on_train_end(trainer, pl_module)
        self._save_last_now(trainer)

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        # Lightning forgets last (and the best's score) when the directory moved: the next last would be
        # last-v1.ckpt, and the next resume would pick the stale last.ckpt. Paths follow the directory instead.
        state = dict(state_dict)
        old = state.get("dirpath")
        if old and self.dirpath and os.path.normpath(old) != os.path.normpath(self.dirpath):
            state = _moved(state, str(old), str(self.dirpath))
        best = state.get("best_model_path")
        if best and not Path(best).is_file():  # a best that is gone is forgotten: the next validation saves one
            state.update(best_model_path="", best_model_score=None, best_k_models={}, kth_best_model_path="",
                         kth_value=self.kth_value)
        super().load_state_dict(state)


def _moved(state: dict, old: str, new: str) -> dict:
    """The callback's state with paths under ``old`` moved under ``new``."""
    def move(path: str) -> str:
        rel = os.path.relpath(path, old) if path else ".."
        return path if rel.startswith("..") else os.path.join(new, rel)

    state = {**state, "dirpath": new}
    for key in ("best_model_path", "kth_best_model_path", "last_model_path"):
        state[key] = move(state.get(key) or "")
    state["best_k_models"] = {move(k): v for k, v in (state.get("best_k_models") or {}).items()}
    return state


def validation_follows(trainer) -> bool:
    """Whether Lightning validates right after the current training step (its own rule, as the loop applies it)."""
    loop = trainer.fit_loop
    try:
        return bool(loop.epoch_loop._should_check_val_fx(loop._data_fetcher))
    except (AttributeError, TypeError):  # another Lightning: last is written twice at worst, never skipped
        return False


# -- reading a run back ---------------------------------------------------------------------------------------------
def load_checkpoint(path: str) -> dict:
    """The checkpoint dict at ``path`` (:func:`read_checkpoint`), with ``"path"`` set to it; one that is not an nvs
    checkpoint is a UserError."""
    ckpt = read_checkpoint(path)
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or not ckpt.get("nvs_config"):
        raise UserError(f"{path}: not an nvs checkpoint (no state_dict / nvs_config)")
    ckpt["nvs_config"] = upgrade_targets(ckpt["nvs_config"])  # a checkpoint of the flat layout names old modules
    ckpt["path"] = str(path)  # for the messages of restore_module
    return ckpt


def load_weights(module: NVSModule, ckpt: dict, path: str) -> None:
    """Load a checkpoint's weights into a module built from its config; any mismatch is one clear error."""
    name = module.model_name
    try:
        missing, unexpected = module.load_state_dict(ckpt["state_dict"], strict=False)
    except RuntimeError as err:  # weights of another shape: name the first one
        lines = [ln.strip() for ln in str(err).splitlines() if "size mismatch" in ln] or [str(err)]
        raise UserError(f"{path} does not fit model '{name}': {lines[0]}") from None
    if missing or unexpected:
        raise UserError(f"{path} does not fit model '{name}': {len(missing)} missing and {len(unexpected)} "
                        f"unexpected weights (e.g. {(missing or unexpected)[0]})")


# A reference model (copy_source, gt_warp) trains nothing; the module still takes an optimiser factory (never called).
_REFERENCE_RUN = {"loss": {}, "optim": {"_target_": "torch.optim.SGD", "_partial_": True, "lr": 0.0},
                  "nonfinite": "stop", "channels_last": False, "trainer": {"precision": "32-true"}}


def restore_run_config(cfg: DictConfig) -> tuple[DictConfig, dict | None]:
    """The run to rebuild from a tool's config (``conf/evaluate.yaml``, ``conf/viewer.yaml``): resolved, and the
    checkpoint (None for a reference model).

    ``cfg.ckpt_path``: the checkpoint's own config; a ``model=`` given as well must be the same model and option.
    Without a checkpoint, ``model=`` (a reference model) and ``data=`` build the run. ``data=<name>`` replaces the
    dataset (at the checkpoint's size), ``data.root=<dir>`` alone reads the checkpoint's dataset from there; ``seed``,
    ``paths`` and ``limit`` (test pairs) come from ``cfg``.
    """
    ckpt = None
    if cfg.get("ckpt_path"):
        ckpt = load_checkpoint(cfg.ckpt_path)
        run = OmegaConf.create(ckpt["nvs_config"])
        if cfg.get("model") is not None and cfg.model.get("name") != run.model.get("name"):
            raise UserError(f"{cfg.ckpt_path} holds model '{run.model.get('name')}', not '{cfg.model.get('name')}'")
        if cfg.get("model") is not None:
            diff = model_mismatch(OmegaConf.to_container(cfg.model, resolve=False),
                                  OmegaConf.to_container(run.model, resolve=False))
            if diff:
                raise UserError(f"{cfg.ckpt_path} holds another option of model '{run.model.get('name')}': {diff}")
    elif cfg.get("model") is not None:
        run = OmegaConf.create({"model": OmegaConf.to_container(cfg.model), **_REFERENCE_RUN})
    else:
        raise UserError("give ckpt_path=... (a trained model) or model=" + "|".join(REFERENCE_MODELS) + " (no training)")
    data_cli = cfg.get("data") or {}
    if data_cli.get("format") is not None:  # a data=<name> group: that dataset config
        data = OmegaConf.to_container(cfg.data, resolve=False)
        if "data" in run:
            data["size"] = run.data.size  # the network is built for the size it was trained at
        run.data = data
    elif "data" not in run:
        raise UserError("give data=<chairs|cars|drive|...> for a model without a checkpoint")
    elif data_cli.get("root") is not None:  # data.root=<dir> alone: the checkpoint's dataset, read from there
        run.data.root = str(data_cli.root)
    run.seed = int(cfg.seed)
    run.paths = OmegaConf.to_container(cfg.paths, resolve=True)
    if cfg.get("limit"):
        run.data.loader.limit_test_pairs = int(cfg.limit)
    OmegaConf.resolve(run)
    return run, ckpt


def restore_module(cfg_run: DictConfig, ckpt: dict | None, channels_last: bool | None = None) -> NVSModule:
    """The run's module (network at ``cfg_run.data.size``, its losses) with the checkpoint's weights, in eval mode.

    ``ckpt``: from :func:`restore_run_config` (None: a reference model, nothing to load); ``channels_last``: the
    layout the tool runs in (None: the run's own). A weight the checkpoint
    lacks, holds in excess or holds in another shape is a UserError naming the file and the first such weight.
    """
    cfg_run.model.image_size = cfg_run.data.size
    module = build_module(cfg_run, channels_last=channels_last)
    if ckpt is not None:
        load_weights(module, ckpt, ckpt.get("path", "the checkpoint"))
    return module.eval()
