"""python -m nvs.train experiment=<name> [key=value ...]: train, select on validation, evaluate on the test pairs."""

from __future__ import annotations

import collections
import statistics
import time
import zipfile
from pathlib import Path

import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from nvs.build import build_data, build_module, device_name, git_sha, parameter_count
from nvs.config_check import check_cli_overrides
from nvs.errors import UserError, exits_cleanly
from nvs.quiet import silence_known_noise
from nvs.run_files import summary_line, write_metrics, write_per_image


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
        self._step_start, self._segment_steps = None, 0

    def on_train_start(self, trainer, pl_module):
        self.start = time.perf_counter()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self._step_start = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.samples += batch["src"].shape[0]
        self._segment_steps += 1
        if self._step_start is not None and self._segment_steps > self.WARMUP_STEPS:
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
    return str(path)


def run(cfg: DictConfig, out_dir: Path) -> dict:
    """Train and test one configuration; writes metrics.json and test_per_image.csv into ``out_dir``."""
    silence_known_noise()
    L.seed_everything(int(cfg.seed), workers=True)
    torch.set_float32_matmul_precision("high")
    datamodule = build_data(cfg)
    module = build_module(cfg)
    callbacks = [instantiate(c) for c in cfg.get("callbacks", {}).values()]
    if not cfg.trainer.get("enable_progress_bar", True):  # the trainer's switch also turns the configured bar off
        callbacks = [c for c in callbacks if not isinstance(c, L.pytorch.callbacks.ProgressBar)]
    throughput = _Throughput()
    loggers = [instantiate(c) for c in cfg.get("logger", {}).values()]
    trainer = instantiate(cfg.trainer, callbacks=callbacks + [throughput], logger=loggers or False)
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
    if cfg.test and not cfg.trainer.get("fast_dev_run"):
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
        write_per_image(out_dir / "test_per_image.csv", module.test_rows)
    write_metrics(out_dir / "metrics.json", result)
    return result


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    check_cli_overrides("train", HydraConfig.get().overrides.task)
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    OmegaConf.resolve(cfg)
    result = run(cfg, out_dir)
    test = result.get("test", {})
    if test:
        print(summary_line(test))
    print(f"run directory: {out_dir}")


if __name__ == "__main__":
    main()
