"""python -m nvs.train experiment=<name> [key=value ...]: train, select on validation, evaluate on the test pairs."""

from __future__ import annotations

import collections
import difflib
import inspect
import shlex
import signal
import statistics
import time
import zipfile
from pathlib import Path

import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.types import RunMode
from hydra.utils import instantiate
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf

from nvs.build import build_data, build_module, device_name, git_sha, parameter_count
from nvs.checkpoints import AtomicCheckpointIO
from nvs.config_check import check_cli_overrides, trainer_arguments
from nvs.errors import Interrupted, UserError, exits_cleanly, user_message
from nvs.quiet import silence_known_noise
from nvs.run_files import (check_creatable, check_writable, is_global_zero, remove_unstarted_run, run_dir_of,
                           summary_line, write_metrics, write_per_image)


class _Throughput(L.Callback):
    """Wall time and samples/s of the fit (validation excluded from samples, included in wall time), and the median
    time of one training step (forward, backward, optimizer; data loading and validation excluded).

    Its state travels in checkpoints, so a resumed run reports the time and samples of all its segments.
    """

    WARMUP_STEPS = 5  # first steps of each process segment left out of the step-time median (allocation, caches)
    KEPT_STEPS = 2000  # the median is over the most recent steps

    def __init__(self):
        self.samples, self.start, self.prior_s, self.train_s = 0, None, 0.0, 0.0
        self.step_s: collections.deque[float] = collections.deque(maxlen=self.KEPT_STEPS)
        self._step_start, self.segment_steps = None, 0

    def on_train_start(self, trainer, pl_module):
        self.start = time.perf_counter()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self._step_start = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.samples += batch["src"].shape[0]
        self.segment_steps += 1
        if self._step_start is not None and self.segment_steps > self.WARMUP_STEPS:
            self.step_s.append(time.perf_counter() - self._step_start)

    def on_train_end(self, trainer, pl_module):
        self.train_s = self.prior_s + time.perf_counter() - self.start

    def step_ms(self) -> float | None:
        """Median training-step time in ms (None before any step past the warm-up)."""
        return 1000 * statistics.median(self.step_s) if self.step_s else None

    def state_dict(self):
        elapsed = time.perf_counter() - self.start if self.start is not None else 0.0
        return {"train_s": self.prior_s + elapsed, "samples": self.samples, "step_s": list(self.step_s)}

    def load_state_dict(self, state_dict):
        self.prior_s, self.samples = float(state_dict["train_s"]), int(state_dict["samples"])
        self.step_s.extend(state_dict.get("step_s", []))


class _Interruption(L.Callback):
    """SIGINT / SIGTERM: save ``last.ckpt`` and stop with :class:`Interrupted` (one line: where, how to resume).

    During training the signal is acted on at the end of the current step (or at once inside validation, where
    Lightning itself stops on SIGTERM); outside training it interrupts at once.
    """

    def __init__(self, last: Path, resume: str):
        self.last, self.resume = last, resume
        self.signum: int | None = None
        self.fitting = False
        self._previous: dict[int, object] = {}

    def install(self) -> None:
        for s in (signal.SIGINT, signal.SIGTERM):
            self._previous[s] = signal.signal(s, self._handler)

    def restore(self) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous = {}

    def _handler(self, signum, frame) -> None:
        first = self.signum is None
        self.signum = signum
        if not self.fitting or not first:  # outside a step (or a second Ctrl-C): at once
            raise Interrupted(signum, self.message(saved=self.last.is_file(), step=None))

    def message(self, saved: bool, step: int | None) -> str:
        name = signal.Signals(self.signum).name
        at = f" at step {step}" if step is not None else ""
        if not saved:
            return f"interrupted by {name}{at} before any checkpoint was written: nothing to resume"
        return f"interrupted by {name}{at}: saved {self.last}; resume with: {self.resume}"

    def _stop(self, trainer) -> None:
        self.fitting = False
        saved = self._save(trainer)
        raise Interrupted(self.signum, self.message(saved, trainer.global_step))

    def _save(self, trainer) -> bool:
        if trainer.global_step == 0:
            return self.last.is_file()
        if not self.last.is_file() or torch.load(self.last, map_location="cpu", weights_only=False,
                                                 mmap=True).get("global_step") != trainer.global_step:
            for cb in trainer.checkpoint_callbacks:  # the resumed callback then writes last.ckpt, not last-v1.ckpt
                if Path(cb.dirpath or "") == self.last.parent:
                    cb.last_model_path = str(self.last)
            trainer.save_checkpoint(self.last, weights_only=False)
        return True

    def on_train_start(self, trainer, pl_module):
        self.fitting = True
        if self.signum is not None:
            self._stop(trainer)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if self.signum is not None:
            self._stop(trainer)

    def on_train_end(self, trainer, pl_module):
        if self.signum is not None:
            self._stop(trainer)
        self.fitting = False

    def on_exception(self, trainer, pl_module, exception):
        # Lightning stops on SIGTERM inside validation with its own SIGTERMException: the weights are still here.
        if isinstance(exception, SIGTERMException) and self.signum is not None and self.fitting:
            self.fitting = False
            self._save(trainer)


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
    throughput = _Throughput()  # counts the steps of this process
    try:
        return _run(cfg, out_dir, throughput)
    except BaseException:
        if not keep_unstarted and is_global_zero() and throughput.segment_steps == 0:
            remove_unstarted_run(out_dir, _job_name())
        raise


def _job_name() -> str:
    return HydraConfig.get().job.name if HydraConfig.initialized() else "train"


def _run(cfg: DictConfig, out_dir: Path, throughput: _Throughput) -> dict:
    silence_known_noise()
    L.seed_everything(int(cfg.seed), workers=True)
    torch.set_float32_matmul_precision("high")
    datamodule = build_data(cfg)
    fast_dev_run = bool(cfg.trainer.get("fast_dev_run"))
    testing = bool(cfg.test) and not fast_dev_run
    # Every list and referenced file of the splits this run reads, before the first step (seconds).
    datamodule.validate(("train", "val", "test") if testing else ("train", "val"))
    module = build_module(cfg)
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
    interruption = _Interruption(ckpt_dir / "last.ckpt", resume_command(out_dir))
    trainer = _trainer(cfg, callbacks=callbacks + [throughput, interruption], logger=loggers or False,
                       plugins=[AtomicCheckpointIO()])
    interruption.install()
    try:
        return _fit_and_test(cfg, out_dir, trainer, module, datamodule, callbacks, throughput, interruption,
                             testing)
    except SIGTERMException:  # Lightning's own stop on SIGTERM (inside validation); last.ckpt saved on the way
        raise Interrupted(signal.SIGTERM, interruption.message(interruption.last.is_file(), trainer.global_step)) \
            from None
    finally:
        interruption.restore()


def _fit_and_test(cfg, out_dir, trainer, module, datamodule, callbacks, throughput, interruption, testing) -> dict:
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
        "precision": str(cfg.trainer.precision),
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
        result["test"] = module.test_summary()
        if trainer.is_global_zero:  # the rows are gathered from every rank: one writer
            write_per_image(out_dir / "test_per_image.csv", module.test_rows)
    if trainer.is_global_zero:
        write_metrics(out_dir / "metrics.json", result)
    return result


def main_cli() -> None:
    """``python -m nvs.train``: every Lightning Trainer argument is ``trainer.<arg>=...`` (nvs.config_check)."""
    import sys

    try:
        sys.argv[1:] = trainer_arguments(sys.argv[1:])
        check_creatable(run_dir_of(sys.argv[1:], "train"))  # Hydra creates it before main(), with a traceback
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    main()


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    # A run that ends before its first step leaves no directory behind (a multirun job's stays: it is reported).
    keep = HydraConfig.get().mode != RunMode.RUN
    try:
        check_cli_overrides("train", HydraConfig.get().overrides.task)
        OmegaConf.resolve(cfg)
    except BaseException:
        if not keep and is_global_zero():
            remove_unstarted_run(out_dir, _job_name())
        raise
    result = run(cfg, out_dir, keep_unstarted=keep)
    if not is_global_zero():
        return
    test = result.get("test", {})
    if test:
        print(summary_line(test))
    print(f"run directory: {out_dir}")


if __name__ == "__main__":
    main_cli()
