"""The callbacks every training run carries (not configurable): its throughput, its stop on SIGINT/SIGTERM and the
record of the precision it trains in."""

from __future__ import annotations

import collections
import signal
import statistics
import time
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.utilities.exceptions import SIGTERMException

from nvs.core.errors import Interrupted
from nvs.run.checkpoints import validation_follows


class Throughput(L.Callback):
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


class SignalStop(L.Callback):
    """SIGINT / SIGTERM in a test (``nvs.evaluate``, the test after training): every rank stops at the same test batch
    with :class:`Interrupted` and nothing is written (the results are written when the test completes); outside a
    stage that defers it, at once.

    Under DDP the handler only records the signal and each test batch ends with one all-reduce of that record: a rank
    that left on its own would leave the others waiting in the gather of the rows (Lightning's handler broadcasts
    from inside the handler, and lets a test with one batch run on as if nothing happened).
    """

    def __init__(self):
        self.signum: int | None = None
        self.testing = False
        self._previous: dict[int, object] = {}

    def install(self) -> None:
        for s in (signal.SIGINT, signal.SIGTERM):
            self._previous[s] = signal.signal(s, self._handler)

    def restore(self) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous = {}

    def _deferred(self) -> bool:
        """Whether a signal now waits for the ranks' agreement (else it interrupts at once)."""
        return self.testing

    def _handler(self, signum, frame) -> None:
        first = self.signum is None
        self.signum = signum
        if not self._deferred() or not first:  # outside a deferring stage (or a second Ctrl-C): at once
            raise Interrupted(signum, self.stop_line(None))

    def stop_line(self, trainer) -> str:
        """The one line printed at the stop (``trainer``: None outside a stage)."""
        return (f"interrupted by {signal.Signals(self.signum).name} during the evaluation: nothing written "
                "(metrics.json and test_per_image.csv are written when it completes); run the same command again")

    def _own_handlers(self) -> None:
        """This callback's handlers alone (Lightning installs its own SIGTERM handler in every stage)."""
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, self._handler)

    def _agreed_signal(self, trainer) -> int | None:
        """The signal any rank received (every rank calls this at the same step: one all-reduce under DDP)."""
        if trainer.world_size == 1:
            return self.signum
        got = trainer.strategy.reduce(torch.tensor([self.signum or 0], device=trainer.strategy.root_device),
                                      reduce_op="max")
        if int(got.item()):
            self.signum = self.signum or int(got.item())
        return self.signum if int(got.item()) else None

    def _test_stop(self, trainer) -> None:
        if self._agreed_signal(trainer) is not None:
            self.testing = False
            raise Interrupted(self.signum, self.stop_line(trainer))

    def on_test_start(self, trainer, pl_module):
        self._own_handlers()
        self.testing = True
        self._test_stop(trainer)

    def on_test_batch_end(self, trainer, *args):
        self._test_stop(trainer)

    def on_test_epoch_end(self, trainer, pl_module):  # before the module's gather of the rows
        self._test_stop(trainer)

    def on_test_end(self, trainer, pl_module):
        self.testing = False

    def on_exception(self, trainer, pl_module, exception):
        if isinstance(exception, Interrupted):
            stop_launched_ranks(trainer)


class Interruption(SignalStop):
    """SIGINT / SIGTERM during a training run: save ``last.ckpt`` and stop with :class:`Interrupted` (one line: where,
    how to resume).

    During training the signal is acted on at the end of the current step, or, when a validation is due after that
    step, at the end of that validation: the saved step then has its validation row and a resume neither skips nor
    repeats it (Lightning's own SIGTERM handler, which stops inside validation, is replaced). In the test after
    training every rank stops at the same test batch (:class:`SignalStop`); ``last.ckpt`` holds the trained weights,
    and the resume command tests them. Outside these, or at a second signal, it interrupts at once.

    Under DDP every rank stops at the same step, whichever ranks got the signal: the handler only records it, and
    each step ends with one all-reduce of that record (Lightning's handler also broadcasts from inside the handler,
    pairing with whatever collective the other rank is in: both ranks then wait forever). A rank interrupted outside
    the steps takes the ranks it launched with it, instead of leaving them waiting in a collective.
    """

    def __init__(self, last: Path, resume: str):
        super().__init__()
        self.last, self.resume = last, resume
        self.fitting = False
        self._after_validation = False  # the agreed stop waits for the validation of its step

    def _deferred(self) -> bool:
        return self.fitting or self.testing

    def stop_line(self, trainer) -> str:
        return self.message(saved=self.last.is_file(), step=None if trainer is None else trainer.global_step)

    def message(self, saved: bool, step: int | None) -> str:
        name = signal.Signals(self.signum).name
        at = f" at step {step}" if step is not None else ""
        if not saved:
            return f"interrupted by {name}{at} before any checkpoint was written: nothing to resume"
        return f"interrupted by {name}{at}: saved {self.last}; resume with: {self.resume}"

    def _stop(self, trainer, in_step: bool = False) -> None:
        self.fitting = self._after_validation = False
        try:  # this step's row of the training curve: Lightning logs it after the hook this stop leaves
            if in_step:
                trainer._logger_connector.update_train_step_metrics()
        except AttributeError:  # another Lightning: the resumed curve lacks that one row
            pass
        for logger in trainer.loggers:
            logger.save()
        saved = self._save(trainer)
        raise Interrupted(self.signum, self.message(saved, trainer.global_step))

    def _save(self, trainer) -> bool:
        if trainer.global_step == 0:
            return self.last.is_file()
        stale = not self.last.is_file() or torch.load(self.last, map_location="cpu", weights_only=False,
                                                      mmap=True).get("global_step") != trainer.global_step
        if trainer.world_size > 1:  # rank 0's answer for all: saving is a collective (its barrier)
            stale = trainer.strategy.broadcast(stale, src=0)
        if stale:
            for cb in trainer.checkpoint_callbacks:  # the resumed callback then writes last.ckpt, not last-v1.ckpt
                if Path(cb.dirpath or "") == self.last.parent:
                    cb.last_model_path = str(self.last)
            trainer.save_checkpoint(self.last, weights_only=False)
        return True

    def on_sanity_check_start(self, trainer, pl_module):
        self._own_handlers()

    def on_train_start(self, trainer, pl_module):
        self._own_handlers()
        self.fitting = True
        if self._agreed_signal(trainer) is not None:
            self._stop(trainer)

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if self._after_validation:  # the previous step's validation (and its checkpoints) done
            self._stop(trainer)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if self._agreed_signal(trainer) is not None:
            if validation_follows(trainer):  # the same answer on every rank
                self._after_validation = True
            else:
                self._stop(trainer, in_step=True)

    def on_train_end(self, trainer, pl_module):
        if self._after_validation or self._agreed_signal(trainer) is not None:
            self._stop(trainer)
        self.fitting = False
        # Under DDP a signal before the test starts waits for the test's first agreement (a rank that left now would
        # leave the others in the test's collectives); without a test the run ends normally.
        self.testing = trainer.world_size > 1

    def on_exception(self, trainer, pl_module, exception):
        # Lightning's SIGTERMException (its handler, in place until this callback's replace it): the weights are
        # still here.
        if isinstance(exception, SIGTERMException) and self.signum is not None and self.fitting:
            self.fitting = False
            self._save(trainer)
        super().on_exception(trainer, pl_module, exception)


def stop_launched_ranks(trainer, grace_s: float = 10.0) -> None:
    """The ranks this process launched (Lightning's subprocess launcher) end: given ``grace_s`` to stop on their
    own (an agreed stop), then killed (one left in a collective would wait for its time-out, 30 minutes by default)."""
    procs = getattr(trainer.strategy.launcher, "procs", None) or []
    deadline = time.monotonic() + grace_s
    for proc in procs:
        try:
            proc.wait(timeout=max(deadline - time.monotonic(), 0.01))
        except Exception:  # noqa: BLE001 - still running (subprocess.TimeoutExpired): it will not finish by itself
            proc.kill()


class PrecisionRecord(L.Callback):
    """The run's precision choice (``nvs.run.precision.Choice.record()``) in its checkpoints, so that a resumed
    ``precision=auto`` run trains its remaining steps in the mode it started in, whatever this machine's probe says
    now (``nvs.run.precision.kept_through_resume``)."""

    def __init__(self, record: dict):
        self.record = dict(record)

    def state_dict(self) -> dict:
        return dict(self.record)

    def load_state_dict(self, state_dict: dict) -> None:
        """The resumed run's choice is made before the Trainer restores this: nothing to take over."""
