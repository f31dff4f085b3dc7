"""A stopping rule for training: stop once validation L1 stopped improving, within ``trainer.max_steps``.

Validation runs every ``trainer.val_check_interval`` steps; after each one the callback reads the monitored value
(``val/l1``) and asks :func:`converged`: over the last ``window`` (25%) of the steps so far, did the best value
improve by less than ``min_improvement`` (1%) of the best value before that window? Then training stops, and the
callback writes ``convergence.json`` in the run directory (why, at which step, and every validation with its step
and training wall time: the convergence curves). A run that reaches ``trainer.max_steps`` first records that
instead. ``metrics.json``'s ``steps`` is the step training stopped at. Enabled with ``callbacks=convergence``
(``conf/callbacks/convergence.yaml``).
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import lightning as L

from nvs.core.atomic import write_json
from nvs.core.errors import UserError

RECORD = "convergence.json"


def converged(history: list[tuple[int, float]], window: float = 0.25, min_improvement: float = 0.01,
              min_steps: int = 0) -> str:
    """Why training may stop now ('' when it may not). ``history``: (step, value) of every validation, in order.

    At the last validation's step s, the reference is the best value among validations at steps <= (1 - window) s
    and the candidate is the best value of all; stop when (reference - candidate) < min_improvement x reference.
    Needs a validation at or before (1 - window) s, and s >= min_steps. Lower values are better.
    """
    if not history:
        return ""
    step = history[-1][0]
    if step < min_steps:
        return ""
    cut = (1.0 - window) * step
    before = [v for s, v in history if s <= cut and math.isfinite(v)]
    finite = [v for _, v in history if math.isfinite(v)]
    if not before or len(finite) < 2:
        return ""
    ref, best = min(before), min(finite)
    gain = (ref - best) / abs(ref) if ref else 0.0
    if gain >= min_improvement:
        return ""
    return (f"best validation value {best:.6g} improved {100 * gain:.2f}% on {ref:.6g} (the best up to step "
            f"{int(cut)}) over the last {100 * window:g}% of {step} steps: below {100 * min_improvement:g}%")


class Convergence(L.Callback):
    """Stops training when :func:`converged` says so; records why and when in ``<dirpath>/convergence.json``."""

    def __init__(self, dirpath: str, monitor: str = "val/l1", window: float = 0.25, min_improvement: float = 0.01,
                 min_steps: int = 0):
        if not 0 < window < 1:
            raise UserError(f"callbacks.convergence.window={window!r}: a fraction in (0, 1)")
        if not min_improvement >= 0:
            raise UserError(f"callbacks.convergence.min_improvement={min_improvement!r}: a fraction >= 0")
        if not (isinstance(min_steps, int) and min_steps >= 0):
            raise UserError(f"callbacks.convergence.min_steps={min_steps!r}: a step count >= 0")
        self.dirpath, self.monitor = Path(dirpath), monitor
        self.window, self.min_improvement, self.min_steps = float(window), float(min_improvement), min_steps
        self.history: list[tuple[int, float]] = []
        self.wall_s: list[float] = []      # training wall time at each validation, summed over resumed segments
        self._segment_start, self._before = None, 0.0
        self.stopped_step: int | None = None
        self.reason = ""

    def on_train_start(self, trainer, pl_module):
        self._segment_start, self._before = time.perf_counter(), (self.wall_s[-1] if self.wall_s else 0.0)
        # Resumed from a checkpoint written when the rule fired (last.ckpt at the stop step): stop again at once.
        if self.stopped_step is not None:
            trainer.should_stop = True

    def on_validation_end(self, trainer, pl_module):
        if trainer.sanity_checking or self.stopped_step is not None:
            return
        value = trainer.callback_metrics.get(self.monitor)
        if value is None:
            raise UserError(f"callbacks.convergence: '{self.monitor}' was not logged at validation; monitor one of "
                           f"{sorted(trainer.callback_metrics)}")
        step = int(trainer.global_step)
        wall = self._before + (time.perf_counter() - self._segment_start if self._segment_start else 0.0)
        if self.history and self.history[-1][0] == step:  # a validation repeated at the same step (resume)
            self.history[-1], self.wall_s[-1] = (step, float(value)), wall
        else:
            self.history.append((step, float(value)))
            self.wall_s.append(wall)
        reason = converged(self.history, self.window, self.min_improvement, self.min_steps)
        if reason:
            self.stopped_step, self.reason = step, reason
            trainer.should_stop = True
            if trainer.is_global_zero:
                print(f"[convergence] stopping at step {step}: {reason}", file=sys.stderr)
            self._write(trainer, "converged")

    def on_train_end(self, trainer, pl_module):
        if self.stopped_step is None:
            self.reason = (f"reached trainer.max_steps={trainer.max_steps} before converging (last "
                           f"{100 * self.window:g}% of steps improved >= {100 * self.min_improvement:g}%)")
            if trainer.is_global_zero:
                print(f"[convergence] {self.reason}", file=sys.stderr)
            self._write(trainer, "max_steps")

    def _write(self, trainer, outcome: str) -> None:
        if not trainer.is_global_zero:
            return
        write_json(self.dirpath / RECORD, {
            "outcome": outcome, "step": int(trainer.global_step), "max_steps": int(trainer.max_steps),
            "reason": self.reason, "monitor": self.monitor, "window": self.window,
            "min_improvement": self.min_improvement, "min_steps": self.min_steps,
            "history": [{"step": s, "value": v, "wall_s": round(w, 3)}
                        for (s, v), w in zip(self.history, self.wall_s)]})

    def state_dict(self) -> dict:
        return {"history": [list(h) for h in self.history], "wall_s": list(self.wall_s),
                "stopped_step": self.stopped_step, "reason": self.reason}

    def load_state_dict(self, state_dict: dict) -> None:
        self.history = [(int(s), float(v)) for s, v in state_dict.get("history", [])]
        self.wall_s = [float(w) for w in state_dict.get("wall_s", [0.0] * len(self.history))]
        self.stopped_step = state_dict.get("stopped_step")
        self.reason = state_dict.get("reason", "")


def read_record(run_dir: str | Path) -> dict | None:
    """A run's ``convergence.json`` (None when absent or unreadable)."""
    try:
        return json.loads((Path(run_dir) / RECORD).read_text())
    except (OSError, ValueError):
        return None
