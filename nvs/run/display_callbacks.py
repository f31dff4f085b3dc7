"""Training callbacks of the run's look: a progress bar in optimizer steps (its test bar in pairs), and an image grid at
each validation.

Both go through Lightning's public hooks and the module's ``forward(batch)``, so they work for every network of the
forward contract and never touch the training or validation steps.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.callbacks import TQDMProgressBar
from lightning.pytorch.callbacks.progress.tqdm_progress import Tqdm
from lightning.pytorch.loggers import TensorBoardLogger, WandbLogger
from PIL import Image

from nvs.run.visuals import image_grid, to_uint8_hwc


def _test_pairs(trainer: L.Trainer, dataloader_idx: int) -> int | None:
    """Test pairs this process evaluates from one test loader: its sampler's share (a DDP process's included), at
    most ``limit_test_batches`` full batches; None where the loader does not say."""
    loaders = trainer.test_dataloaders
    loader = loaders[dataloader_idx] if isinstance(loaders, (list, tuple)) else loaders
    batches = trainer.num_test_batches
    batches = batches[dataloader_idx] if isinstance(batches, list) else batches
    sampler, size = getattr(loader, "sampler", None), getattr(loader, "batch_size", None)
    try:
        pairs = len(sampler)
    except TypeError:
        return None
    return pairs if size is None or batches == float("inf") else min(pairs, int(batches) * size)


def _batch_pairs(batch: Any) -> int:
    """Pairs in a batch of the data contract (its source images, (B,3,H,W)); 1 for anything else."""
    src = batch.get("src") if isinstance(batch, dict) else None
    return int(src.shape[0]) if isinstance(src, torch.Tensor) and src.dim() == 4 else 1


class PairTestBar(TQDMProgressBar):
    """Lightning's tqdm bar whose test bar counts test pairs, not batches (a batch holds eval_batch_size pairs).

    When stdout is not a terminal (a log file) the test bar is one line per tenth of the pairs (the same text, no
    carriage returns)."""

    LINES = 10  # lines of a test's (or a run's) progress in a log file
    TEST_LINES = True  # False: no test progress at all in a log file

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self._test_lines: dict | None = None  # the test's line mode state, set at each test loader's first batch

    @staticmethod
    def _terminal() -> bool:
        return sys.stdout.isatty()

    @property
    def test_description(self) -> str:
        return "test pairs"

    def init_test_tqdm(self) -> Tqdm:
        if not self._terminal():
            return Tqdm(disable=True)  # lines instead (on_test_batch_end), where TEST_LINES
        # Lightning's test bar, named and paced in pairs (the rate in pairs per second)
        return Tqdm(desc=self.test_description, unit=" pairs", position=2 * self.process_position,
                    disable=self.is_disabled, leave=True, dynamic_ncols=True, file=sys.stdout,
                    bar_format=self.BAR_FORMAT)

    def on_test_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int,
                            dataloader_idx: int = 0) -> None:
        if not self.has_dataloader_changed(dataloader_idx):
            return
        if not self._terminal():
            self._test_lines = None if self.is_disabled or not self.TEST_LINES else {
                "t0": time.perf_counter(), "n": 0, "printed": 0, "total": _test_pairs(trainer, dataloader_idx)}
            return
        bar = self.test_progress_bar
        bar.reset(total=_test_pairs(trainer, dataloader_idx))
        bar.initial = 0
        several = isinstance(trainer.test_dataloaders, (list, tuple)) and len(trainer.test_dataloaders) > 1
        bar.set_description(self.test_description + (f" (loader {dataloader_idx})" if several else ""))

    def on_test_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                          batch_idx: int, dataloader_idx: int = 0) -> None:
        state = self._test_lines
        if state is not None and not self._terminal():
            state["n"] += _batch_pairs(batch)
            n, total = state["n"], state["total"]
            if n - state["printed"] >= max(1, (total or 1000) // self.LINES) or n == total:
                state["printed"] = n
                print(Tqdm.format_meter(n, total, time.perf_counter() - state["t0"], prefix=self.test_description,
                                        unit=" pairs"), flush=True)
            return
        bar = self.test_progress_bar
        if bar is None or bar.disable:
            return
        bar.n += _batch_pairs(batch)
        if (batch_idx + 1) % self.refresh_rate == 0 or bar.n == bar.total:
            bar.refresh()


class StepProgressBar(PairTestBar):
    """Lightning's tqdm bar whose training bar counts optimizer steps toward ``trainer.max_steps`` (or the steps of
    ``max_epochs``) over the whole run, so its ETA is the run's; the test bar counts pairs (:class:`PairTestBar`), the
    validation bars are Lightning's own.

    A resumed run starts the bar at the step it resumes from; the ETA is measured on the steps of this process
    (averaged over them, validation time included). The bar shows the logged values without the logger's version.
    When stdout is not a terminal (a log file) the bar is one line per tenth of the run (the same text, no carriage
    returns) and the sanity, validation and test bars are off: they would write carriage returns and cursor-up
    escapes into the file.
    """

    TEST_LINES = False  # a run's test in a log file: its metrics line is enough

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self._lines: dict | None = None  # the line mode's state, set at the start of training

    def init_sanity_tqdm(self) -> Tqdm:
        return super().init_sanity_tqdm() if self._terminal() else Tqdm(disable=True)

    def init_train_tqdm(self) -> Tqdm:
        return super().init_train_tqdm() if self._terminal() else Tqdm(disable=True)

    def get_metrics(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict:
        items = super().get_metrics(trainer, pl_module)
        items.pop("v_num", None)
        return items

    def init_validation_tqdm(self) -> Tqdm:
        if self.trainer.state.fn == "validate" or self._terminal():
            return super().init_validation_tqdm()
        return Tqdm(disable=True)

    @property
    def train_description(self) -> str:
        return "train steps"

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_train_start(trainer, pl_module)
        bar = self.train_progress_bar
        total = trainer.estimated_stepping_batches
        bar.reset(total=None if total == float("inf") else int(total))
        bar.initial = bar.n = trainer.global_step
        bar.refresh()
        if not self._terminal() and not self.is_disabled:
            self._lines = {"t0": time.perf_counter(), "initial": trainer.global_step, "printed": trainer.global_step}

    def on_train_epoch_start(self, trainer: L.Trainer, *_: Any) -> None:
        pass  # one bar for the run: Lightning's resets it at every epoch

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        bar = self.train_progress_bar
        step = trainer.global_step
        if self._lines is not None:
            self._line(trainer, pl_module, step, bar.total if bar is not None else None)
            return
        if bar is None or bar.disable or step == bar.n:
            return
        if step % self.refresh_rate == 0 or step == bar.total:
            bar.n = step
            bar.set_postfix(self.get_metrics(trainer, pl_module), refresh=False)
            bar.refresh()

    def _line(self, trainer: L.Trainer, pl_module: L.LightningModule, step: int, total: int | None) -> None:
        state = self._lines
        every = max(1, (total or 1000) // self.LINES)
        if step == state["printed"] or (step - state["printed"] < every and step != total):
            return
        state["printed"] = step
        postfix = ", ".join(f"{k}={Tqdm.format_num(v) if isinstance(v, float) else v}"
                            for k, v in self.get_metrics(trainer, pl_module).items())
        line = Tqdm.format_meter(step, total, time.perf_counter() - state["t0"], prefix=self.train_description,
                                 postfix=postfix or None, initial=state["initial"])
        print(line, flush=True)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.train_progress_bar is not None and not self.train_progress_bar.disable:
            self.train_progress_bar.set_postfix(self.get_metrics(trainer, pl_module))


class ValidationImages(L.Callback):
    """At each validation, the module's prediction on a fixed validation batch as one image, logged as ``val/grid``.

    Rows are samples; columns are source, target, prediction and predicted depth (grey, near = bright; the column is
    left out for networks without depth). The batch is ``samples`` pairs spread evenly over the validation split
    (its pairs are listed model by model, so these are distinct models where the split has enough; the split is not
    shuffled, so they are the same pairs all run long). Each logger gets the grid its own
    way: TensorBoard ``add_image``, W&B ``log_image``, any other logger with a ``log_dir`` (CSV) a PNG under
    ``<log_dir>/images/``.

    Args:
        samples: pairs (rows) in the grid.
        scale: nearest-neighbour upscaling of each tile (64² tiles are small in a dashboard).
    """

    KEY = "val/grid"
    COLUMNS = ("source", "target", "prediction", "depth")

    def __init__(self, samples: int = 4, scale: int = 2):
        if samples < 1 or scale < 1:
            raise ValueError(f"samples={samples}, scale={scale}: both must be at least 1")
        self.samples, self.scale = samples, scale
        self.batch: dict | None = None
        self.columns = self.COLUMNS

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.batch is not None:
            return
        loaders = trainer.val_dataloaders
        loader = loaders[0] if isinstance(loaders, (list, tuple)) else loaders
        dataset = getattr(loader, "dataset", None)
        if dataset is not None and hasattr(dataset, "__len__") and len(dataset) > 0:
            items = [dataset[i] for i in spread(len(dataset), self.samples)]
            self.batch = loader.collate_fn(items)

    def on_validation_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int,
                                  dataloader_idx: int = 0) -> None:
        if self.batch is None and batch_idx == 0 and dataloader_idx == 0:  # a split without random access
            n = self.samples
            self.batch = {k: (v[:n].detach().cpu().clone() if torch.is_tensor(v) else list(v[:n]))
                          for k, v in batch.items()}

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking or self.batch is None or not trainer.is_global_zero or not trainer.loggers:
            return
        grid = self.grid(pl_module)
        for logger in trainer.loggers:
            self._log(logger, grid, trainer.global_step)

    @torch.no_grad()
    def grid(self, pl_module: L.LightningModule) -> torch.Tensor:
        """(3,H,W) float in [0,1]: the prediction on the fixed batch (the module is in eval mode at validation end)."""
        batch = {k: (v.to(pl_module.device) if torch.is_tensor(v) else v) for k, v in self.batch.items()}
        out = pl_module(batch)
        columns = [batch["src"], batch["tgt"], out["rgb"]]
        if out.get("depth") is not None:
            columns.append(out["depth"])
        self.columns = self.COLUMNS[:len(columns)]
        return image_grid(columns, scale=self.scale)

    def _log(self, logger: Any, grid: torch.Tensor, step: int) -> None:
        caption = " | ".join(self.columns)
        if isinstance(logger, TensorBoardLogger):
            logger.experiment.add_image(self.KEY, grid, global_step=step, dataformats="CHW")
        elif isinstance(logger, WandbLogger):
            logger.log_image(self.KEY, [to_uint8_hwc(grid)], step=step, caption=[caption])
        elif getattr(logger, "log_dir", None):
            out = Path(logger.log_dir) / "images" / f"val_grid_step{step:07d}.png"
            out.parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(to_uint8_hwc(grid)).save(out)


def spread(n: int, k: int) -> list[int]:
    """``min(k, n)`` distinct indices in ``range(n)`` spread evenly, the first one 0."""
    k = min(k, n)
    return [i * n // k for i in range(k)]
