"""What every stress section runs its checks with: a finiteness test, silenced Lightning logs, a yes/NO cell."""

from __future__ import annotations

import contextlib
import logging
import warnings
from collections.abc import Iterator

import torch


def all_finite(*tensors) -> bool:
    """Every given tensor is finite everywhere (``None`` entries are skipped)."""
    return all(bool(torch.isfinite(t).all()) for t in tensors if t is not None)


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """Silence Lightning's and Python's warnings and info logs (the report carries what matters)."""
    loggers = [logging.getLogger(n) for n in ("lightning", "lightning.pytorch", "lightning.fabric")]
    levels = [lg.level for lg in loggers]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for lg in loggers:
            lg.setLevel(logging.ERROR)
        try:
            yield
        finally:
            for lg, lv in zip(loggers, levels):
                lg.setLevel(lv)


def yes(flag: bool) -> str:
    """A report cell for a check: a failure stands out."""
    return "yes" if flag else "**NO**"
