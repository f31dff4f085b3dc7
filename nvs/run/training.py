"""One training run as a library call: build from a config, fit, select on validation, test, write the artifacts.

``python -m nvs.train`` is its command line; the stress suite and tests call :func:`run` in-process.
"""

from __future__ import annotations

import shlex
import signal
import time
import warnings
from pathlib import Path

import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf

from nvs.core.errors import Interrupted, UserError, user_message
from nvs.data.datamodule import NVSDataModule
from nvs.module.lightning_module import NVSModule
from nvs.run.artifacts import (check_writable, existing_files, is_global_zero, remove_unstarted_run, run_record,
                               test_record, write_run_results)
from nvs.run.build import build_data, build_module, choose_precision
from nvs.run.checkpoint_files import held_precision, read_checkpoint, resume_checkpoint
from nvs.run.checkpoints import AtomicCheckpointIO
from nvs.run.config_check import component_problems
from nvs.run.csv_log import continue_from
from nvs.run.loggers import log_run_config
from nvs.run.overrides import hydra_value
from nvs.run.precision import Choice, kept_through_resume
from nvs.run.quiet import silence_known_noise
from nvs.run.run_checks import check_batches, check_resume, check_run_config, check_trained, resume_load_error
from nvs.run.standard_callbacks import Interruption, PrecisionRecord, Throughput


def resume_command(out_dir: Path) -> str:
    """The command that resumes this run: the same overrides, with the run directory pinned."""
    task = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []
    # Hydra-quoted where its grammar needs it (non-ASCII, spaces, commas), then shell-quoted: it runs as printed.
    return shlex.join(["python", "-m", "nvs.train", *task, f"hydra.run.dir={hydra_value(str(out_dir))}"])


def _trainer(cfg: DictConfig, **kwargs) -> L.Trainer:
    """The Trainer of ``cfg.trainer``; an unknown argument or a value the Trainer refuses is one UserError."""
    problems = component_problems(OmegaConf.to_container(cfg.trainer, resolve=True), "trainer")
    if problems:  # a library call (not checked at the command line): the trainer's arguments checked here
        raise UserError("; ".join(f"config '{key}': {why}" for key, why in problems))
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


def run(cfg: DictConfig, out_dir: Path, keep_unstarted: bool = True, existing: frozenset[str] | None = None) -> dict:
    """Train and test one configuration; writes metrics.json and test_per_image.csv into ``out_dir``.

    ``keep_unstarted=False``: a failure before the first training step removes what the run wrote (and ``out_dir``
    if that empties it); ``existing``: what ``out_dir`` held before (default: what it holds now), never removed.
    """
    throughput = Throughput()  # counts the steps of this process
    existing = existing_files(out_dir) if existing is None else existing
    try:
        return _run(cfg, out_dir, throughput)
    except BaseException:
        if not keep_unstarted and is_global_zero() and throughput.segment_steps == 0:
            remove_unstarted_run(out_dir, job_name(), existing)
        raise


def job_name() -> str:
    return HydraConfig.get().job.name if HydraConfig.initialized() else "train"


def _run(cfg: DictConfig, out_dir: Path, throughput: Throughput) -> dict:
    silence_known_noise()
    L.seed_everything(int(cfg.seed), workers=True)
    torch.set_float32_matmul_precision("high")
    check_run_config(cfg)
    datamodule = build_data(cfg)
    fast_dev_run = bool(cfg.trainer.get("fast_dev_run"))
    testing = bool(cfg.test) and not fast_dev_run
    # Every list and referenced file of the splits this run reads, before the first step (seconds).
    datamodule.validate(("train", "val", "test") if testing else ("train", "val"))
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
    resume = resume_checkpoint(cfg.ckpt_path, ckpt_dir)
    if resume is not None:  # resuming into the run's own checkpoint folder is the design, not a surprise
        warnings.filterwarnings("ignore", message=r"Checkpoint directory .* exists and is not empty")
    choice = choose_precision(cfg)
    if str(cfg.get("channels_last", "auto")) == "auto":  # a resumed auto run keeps the mode it started in
        choice = kept_through_resume(choice, held_precision(resume[0] if resume is not None else None))
    if is_global_zero():
        print(choice.line(), flush=True)
    module = build_module(cfg, channels_last=choice.channels_last)
    for lg in loggers:  # the curve of the steps before the checkpoint stays; the steps trained again are re-logged
        if isinstance(lg, L.pytorch.loggers.CSVLogger) and is_global_zero():
            continue_from(lg, resume[1] if resume is not None else None)
    interruption = Interruption(ckpt_dir / "last.ckpt", resume_command(out_dir))
    carried = [throughput, interruption, PrecisionRecord(choice.record())]
    if loggers:  # the learning rate of each parameter group at every logged step (it needs a logger)
        carried.append(L.pytorch.callbacks.LearningRateMonitor(logging_interval="step"))
    trainer = _trainer(cfg, callbacks=callbacks + carried, logger=loggers or False,
                       plugins=[AtomicCheckpointIO()], precision=choice.precision, **_short_run(cfg))
    log_run_config(loggers, cfg)
    if not fast_dev_run:
        check_batches(int(cfg.data.loader.batch_size), len(datamodule.dataset("train")), trainer.world_size)
    interruption.install()
    try:
        return _fit_and_test(cfg, out_dir, trainer, module, datamodule, checkpoints=checkpoint_cbs,
                             throughput=throughput, choice=choice, testing=testing,
                             resume=resume[0] if resume else None)
    except SIGTERMException:  # Lightning's own stop on SIGTERM (inside validation); last.ckpt saved on the way
        raise Interrupted(signal.SIGTERM, interruption.message(interruption.last.is_file(), trainer.global_step)) \
            from None
    finally:
        interruption.restore()


def _fit_and_test(cfg: DictConfig, out_dir: Path, trainer: L.Trainer, module: NVSModule, datamodule: NVSDataModule,
                  *, checkpoints: list[L.pytorch.callbacks.ModelCheckpoint], throughput: Throughput, choice: Choice,
                  testing: bool, resume: str | None) -> dict:
    """Fit (from ``resume``, a checkpoint path, or from scratch), then test the best checkpoint of ``checkpoints``
    when ``testing``; write and return the run's metrics.json record."""
    check_resume(cfg, resume)
    try:
        trainer.fit(module, datamodule=datamodule, ckpt_path=resume)
    except RuntimeError as err:
        mismatch = resume_load_error(err, resume)
        if mismatch is None:
            raise
        raise mismatch from None
    check_trained(int(trainer.global_step))
    result = run_record(module, cfg, choice, training={
        "steps": int(trainer.global_step),
        "train_wall_s": throughput.train_s,
        "train_samples_per_s": throughput.samples / throughput.train_s if throughput.train_s else None,
        "train_step_ms": throughput.step_ms(),
        "overrides": list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []})
    if testing:
        ckpt = None
        for cb in checkpoints:
            if cb.best_model_path:
                ckpt = cb.best_model_path
        if ckpt:
            read_checkpoint(ckpt, mmap=True)  # whole and its hash matching, as every tool reads it
        t0 = time.perf_counter()
        trainer.test(module, datamodule=datamodule, ckpt_path=ckpt, verbose=False)
        # which weights the test metrics are of: no validation ran (limit_val_batches=0, ...) means the final ones
        tested = "best validation checkpoint" if ckpt else f"final weights (step {trainer.global_step})"
        result.update(test_record(module, time.perf_counter() - t0, ckpt, tested))
    if trainer.is_global_zero:  # the rows are gathered from every rank: one writer
        write_run_results(out_dir, result, module.test_rows if testing else None)
    return result
