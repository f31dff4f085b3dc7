"""One training run as a library call: build from a config, fit, select on validation, test, write the artifacts.

``python -m nvs.train`` is its command line; the stress suite and tests call :func:`run` in-process.
"""

from __future__ import annotations

import difflib
import inspect
import shlex
import signal
import time
import zipfile
from pathlib import Path

import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig

from nvs.core.errors import Interrupted, UserError, user_message
from nvs.core.provenance import device_name, git_sha
from nvs.run.artifacts import check_writable, is_global_zero, remove_unstarted_run, write_metrics, write_per_image
from nvs.run.build import build_data, build_module, choose_precision, parameter_count
from nvs.run.checkpoints import AtomicCheckpointIO
from nvs.run.loggers import log_run_config
from nvs.run.precision import Choice
from nvs.run.quiet import silence_known_noise
from nvs.run.standard_callbacks import Interruption, Throughput


def resume_command(out_dir: Path) -> str:
    """The command that resumes this run: the same overrides, with the run directory pinned."""
    task = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []
    return shlex.join(["python", "-m", "nvs.train", *task, f"hydra.run.dir={out_dir}"])


def _trainer(cfg: DictConfig, **kwargs) -> L.Trainer:
    """The Trainer of ``cfg.trainer``; an unknown argument or a value the Trainer refuses is one UserError."""
    if cfg.trainer.get("_target_") in ("lightning.pytorch.Trainer", "lightning.Trainer",
                                       "lightning.pytorch.trainer.trainer.Trainer"):
        known = set(inspect.signature(L.Trainer.__init__).parameters) - {"self"}
        for key in cfg.trainer:
            if key != "_target_" and key not in known:
                hint = difflib.get_close_matches(str(key), known, n=1)
                raise UserError(f"config 'trainer.{key}': not an argument of lightning.Trainer"
                                + (f"; did you mean trainer.{hint[0]}?" if hint else ""))
    try:
        return instantiate(cfg.trainer, **kwargs)
    except InstantiationException as err:
        cause = err.__cause__ or err
        message = user_message(cause) or f"{cause.__class__.__name__}: {cause}"
        raise UserError(f"config 'trainer': {message}") from None


def _short_run(cfg: DictConfig) -> dict:
    """``log_every_n_steps`` and a step-count ``val_check_interval`` capped at ``max_steps``: a run shorter than
    either still logs its loss, and validates (and so tests a validation-selected checkpoint) at its last step."""
    steps, capped = cfg.trainer.get("max_steps"), {}
    for key in ("log_every_n_steps", "val_check_interval"):
        every = cfg.trainer.get(key)
        if isinstance(every, int) and not isinstance(every, bool) and isinstance(steps, int) and 0 < steps < every:
            capped[key] = steps
    return capped


def _resume_path(cfg: DictConfig, out_dir: Path) -> str | None:
    if cfg.ckpt_path in (None, "none", "null"):
        return None
    if cfg.ckpt_path == "auto":
        last = out_dir / "checkpoints" / "last.ckpt"
        return _complete(last) if last.is_file() else None
    if not Path(cfg.ckpt_path).is_file():
        raise UserError(f"ckpt_path={cfg.ckpt_path}: no such checkpoint")
    return _complete(Path(cfg.ckpt_path))


def _complete(path: Path) -> str:
    # torch.save writes a zip whose directory sits at the end: a write cut short by a kill has none.
    if not zipfile.is_zipfile(path):
        raise UserError(f"{path}: incomplete checkpoint (the run was probably killed while writing it); "
                        "delete it to resume from scratch, or pass ckpt_path=<another checkpoint>")
    try:  # every member's CRC: flipped bytes inside an intact zip would otherwise fail deep inside unpickling
        with zipfile.ZipFile(path) as zf:
            bad = zf.testzip()
    except (zipfile.BadZipFile, OSError, EOFError) as err:
        bad = f"({err})"
    if bad:
        raise UserError(f"{path}: corrupt checkpoint (member {bad} fails its checksum); delete it to resume from "
                        "scratch, or pass ckpt_path=<another checkpoint>")
    return str(path)


def run(cfg: DictConfig, out_dir: Path, keep_unstarted: bool = True) -> dict:
    """Train and test one configuration; writes metrics.json and test_per_image.csv into ``out_dir``.

    ``keep_unstarted=False``: a failure before the first training step removes what the run wrote (and ``out_dir``
    if that empties it).
    """
    throughput = Throughput()  # counts the steps of this process
    try:
        return _run(cfg, out_dir, throughput)
    except BaseException:
        if not keep_unstarted and is_global_zero() and throughput.segment_steps == 0:
            remove_unstarted_run(out_dir, job_name())
        raise


def job_name() -> str:
    return HydraConfig.get().job.name if HydraConfig.initialized() else "train"


def _run(cfg: DictConfig, out_dir: Path, throughput: Throughput) -> dict:
    silence_known_noise()
    L.seed_everything(int(cfg.seed), workers=True)
    torch.set_float32_matmul_precision("high")
    datamodule = build_data(cfg)
    fast_dev_run = bool(cfg.trainer.get("fast_dev_run"))
    testing = bool(cfg.test) and not fast_dev_run
    # Every list and referenced file of the splits this run reads, before the first step (seconds).
    datamodule.validate(("train", "val", "test") if testing else ("train", "val"))
    choice = choose_precision(cfg)
    if is_global_zero():
        print(choice.line(), flush=True)
    module = build_module(cfg, channels_last=choice.channels_last)
    callbacks = [instantiate(c) for c in cfg.get("callbacks", {}).values()]
    if not cfg.trainer.get("enable_progress_bar", True):  # the trainer's switch also turns the configured bar off
        callbacks = [c for c in callbacks if not isinstance(c, L.pytorch.callbacks.ProgressBar)]
    checkpoint_cbs = [cb for cb in callbacks if isinstance(cb, L.pytorch.callbacks.ModelCheckpoint)]
    loggers = [instantiate(c) for c in cfg.get("logger", {}).values()]
    if is_global_zero():  # every output location is writable, or one line now instead of a lost run later
        check_writable(out_dir)
        for cb in checkpoint_cbs:
            if cb.dirpath and not fast_dev_run:
                check_writable(cb.dirpath)
        for lg in loggers:
            if getattr(lg, "log_dir", None):
                check_writable(lg.log_dir)
    ckpt_dir = Path(checkpoint_cbs[0].dirpath) if checkpoint_cbs and checkpoint_cbs[0].dirpath else out_dir
    interruption = Interruption(ckpt_dir / "last.ckpt", resume_command(out_dir))
    carried = [throughput, interruption]
    if loggers:  # the learning rate of each parameter group at every logged step (it needs a logger)
        carried.append(L.pytorch.callbacks.LearningRateMonitor(logging_interval="step"))
    trainer = _trainer(cfg, callbacks=callbacks + carried, logger=loggers or False,
                       plugins=[AtomicCheckpointIO()], precision=choice.precision, **_short_run(cfg))
    log_run_config(loggers, cfg)
    interruption.install()
    try:
        return _fit_and_test(cfg, out_dir, trainer, module, datamodule, callbacks, throughput, choice, testing)
    except SIGTERMException:  # Lightning's own stop on SIGTERM (inside validation); last.ckpt saved on the way
        raise Interrupted(signal.SIGTERM, interruption.message(interruption.last.is_file(), trainer.global_step)) \
            from None
    finally:
        interruption.restore()


def _fit_and_test(cfg: DictConfig, out_dir: Path, trainer: L.Trainer, module, datamodule, callbacks: list,
                  throughput: Throughput, choice: Choice, testing: bool) -> dict:
    trainer.fit(module, datamodule=datamodule, ckpt_path=_resume_path(cfg, out_dir))
    result = {
        "model": module.model_name,
        "data": cfg.data.name,
        "image_size": cfg.data.size,
        "seed": int(cfg.seed),
        "steps": int(trainer.global_step),
        "train_wall_s": throughput.train_s,
        "train_samples_per_s": throughput.samples / throughput.train_s if throughput.train_s else None,
        "train_step_ms": throughput.step_ms(),
        "params": parameter_count(module.net),
        "device": device_name(module.device),
        "precision": choice.precision,
        "precision_choice": choice.record(),
        "git_sha": git_sha(),
        "overrides": list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else [],
    }
    if testing:
        ckpt = None
        for cb in callbacks:
            if isinstance(cb, L.pytorch.callbacks.ModelCheckpoint) and cb.best_model_path:
                ckpt = cb.best_model_path
        t0 = time.perf_counter()
        trainer.test(module, datamodule=datamodule, ckpt_path=ckpt, verbose=False)
        n = max(len(module.test_rows), 1)
        result["eval_ms_per_image"] = 1000 * (time.perf_counter() - t0) / n  # whole test loop, metrics included
        result["eval_forward_ms_per_image"] = module.test_forward_ms_per_image()
        result["checkpoint"] = ckpt
        # which weights the test metrics are of: no validation ran (limit_val_batches=0, ...) means the final ones
        result["tested_weights"] = ("best validation checkpoint" if ckpt
                                    else f"final weights (step {trainer.global_step})")
        result["test"] = module.test_summary()
        if trainer.is_global_zero:  # the rows are gathered from every rank: one writer
            write_per_image(out_dir / "test_per_image.csv", module.test_rows)
    if trainer.is_global_zero:
        write_metrics(out_dir / "metrics.json", result)
    return result
