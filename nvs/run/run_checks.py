"""What a training run refuses before (and right after) fitting: settings that train nothing or crash deep inside
Lightning, and a resume that would silently train something other than what the run records.

Every refusal is one ``UserError`` naming the key (exit 2 at the command line):
- ``optim.lr`` <= 0, ``trainer.val_check_interval`` <= 0, ``trainer.max_steps=0`` / ``trainer.max_epochs=0``;
- ``data.loader.batch_size`` larger than one process's share of the training pairs (the last partial batch is
  dropped, so no step would run), and, whatever the cause, a fit that ran no step: its test metrics would be an
  untrained network's;
- a resume whose command asks for another model, image size, optimiser or schedule than the checkpoint was trained
  with. Lightning restores the optimiser's state (its learning rate included) from the checkpoint, so an override
  such as ``optim.lr=0.5`` would be recorded in the config and metrics.json but not trained with: it is refused.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from nvs.core.errors import UserError
from nvs.core.legacy import upgrade_targets


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def model_mismatch(asked: Mapping, held: Mapping, prefix: str = "model") -> str | None:
    """First difference between the model config a command asks for and the one a checkpoint was trained with.

    ``asked``, ``held``: plain containers (``OmegaConf.to_container``). ``image_size`` follows the checkpoint's data
    and values still holding an interpolation (``${data.depth_head}``) are the data's business; both are skipped.
    Returns 'key: the checkpoint has X, the command asks for Y', or None when they agree.
    """
    for key in sorted(set(asked) | set(held)):
        if key == "image_size":
            continue
        a, h = asked.get(key, "<absent>"), held.get(key, "<absent>")
        if isinstance(a, str) and "${" in a:
            continue
        if isinstance(a, Mapping) and isinstance(h, Mapping):
            inner = model_mismatch(a, h, f"{prefix}.{key}")
            if inner:
                return inner
        elif a != h:
            return f"{prefix}.{key}: the checkpoint has {h!r}, the command asks for {a!r}"
    return None


def check_run_config(cfg: DictConfig) -> None:
    """Settings that would train nothing, or fail with a traceback inside the optimiser or the Trainer."""
    lr = (cfg.get("optim") or {}).get("lr")
    if _number(lr) and not lr > 0:
        raise UserError(f"config 'optim.lr': expected a positive learning rate, got {lr}")
    trainer = cfg.get("trainer") or {}
    if trainer.get("fast_dev_run"):
        return
    interval = trainer.get("val_check_interval")
    if _number(interval) and not interval > 0:
        raise UserError(f"config 'trainer.val_check_interval': expected a positive number of steps (or a fraction of "
                        f"an epoch in (0, 1]), got {interval}")
    for key in ("max_steps", "max_epochs"):
        if trainer.get(key) == 0:
            raise UserError(f"config 'trainer.{key}=0': no training step would run, and the test metrics would be "
                            "an untrained network's (evaluate a checkpoint with python -m nvs.evaluate ckpt_path=...)")


def check_batches(batch_size: int, train_pairs: int, world_size: int = 1) -> None:
    """At least one full training batch per process (the training loader drops the last partial batch)."""
    per_rank = math.ceil(train_pairs / max(world_size, 1))
    if batch_size > per_rank:
        share = f" ({per_rank} per process over {world_size})" if world_size > 1 else ""
        raise UserError(f"data.loader.batch_size={batch_size}: larger than the {train_pairs} training pairs{share}; "
                        "the partial batch is dropped, so no step would run: lower it")


def check_trained(steps: int) -> None:
    """After fit: a run that took no step (whatever the cause) does not report an untrained network's metrics."""
    if steps == 0:
        raise UserError("no training step ran (check trainer.max_steps, trainer.limit_train_batches and "
                        "data.loader.batch_size against the training split); nothing is tested or written")


def _first_difference(asked, held, prefix: str) -> str | None:
    if isinstance(asked, Mapping) and isinstance(held, Mapping):
        for key in sorted(set(asked) | set(held), key=str):
            diff = _first_difference(asked.get(key, "<absent>"), held.get(key, "<absent>"), f"{prefix}.{key}")
            if diff:
                return diff
        return None
    if asked != held:
        return f"{prefix}: the checkpoint has {held!r}, the command asks for {asked!r}"
    return None


def check_resume(cfg: DictConfig, ckpt_path: str | Path | None) -> None:
    """The run being resumed from ``ckpt_path`` is the one the command describes (model, size, optimiser, schedule).

    Reads the checkpoint memory-mapped (its config only; Lightning loads the weights itself). A checkpoint without
    an nvs config (not written by nvs.train) is left to Lightning.
    """
    if ckpt_path is None:
        return
    try:
        ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=False, mmap=True)
    except Exception:  # noqa: BLE001 - an unreadable file is reported by the resume itself, with its own message
        return
    held = ckpt.get("nvs_config") if isinstance(ckpt, dict) else None
    if not held:
        return
    held = upgrade_targets(held)  # a checkpoint of the flat layout names old modules
    asked = OmegaConf.to_container(cfg, resolve=True)
    why = "a resume continues the checkpoint's run"
    diff = model_mismatch(asked.get("model") or {}, held.get("model") or {})
    size_a, size_h = (asked.get("data") or {}).get("size"), (held.get("data") or {}).get("size")
    if diff is None and size_a != size_h:
        diff = f"data.size: the checkpoint has {size_h!r}, the command asks for {size_a!r}"
    if diff is None:
        why = "a resume restores the optimiser's state (its learning rate included) from the checkpoint"
        for key in ("optim", "scheduler"):
            diff = diff or _first_difference(asked.get(key), held.get(key), key)
    if diff:
        raise UserError(f"{ckpt_path}: cannot resume with other settings ({diff}); {why}: drop the override, or "
                        "start a new run (another hydra.run.dir, or ckpt_path=none)")


def resume_load_error(err: BaseException, ckpt_path: str | None) -> UserError | None:
    """Lightning's multi-line state_dict error on resume, as one line naming the checkpoint (None: another error)."""
    text = str(err)
    if ckpt_path is None or not isinstance(err, RuntimeError) or "Error(s) in loading state_dict" not in text:
        return None
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    detail = next((ln for ln in lines[1:] if "size mismatch" in ln), lines[1] if len(lines) > 1 else lines[0])
    return UserError(f"{ckpt_path}: does not fit this run's model ({detail[:200]}); resume with the command that "
                     "wrote it, or start a new run (another hydra.run.dir, or ckpt_path=none)")
