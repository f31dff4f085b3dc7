"""Silence the known start-up noise of Lightning and torch, and only that: each filter matches one message.

- Lightning's "💡 Tip: ... litlogger / litmodels" adverts (INFO lines on every run).
- torch's FutureWarning that Lightning's own pytree helper uses ``LeafSpec``.
- "Found N module(s) in eval mode at the start of training": nvs's frozen loss networks (VGG, LPIPS) are meant to
  stay in eval mode.
- Each Lightning log line printed twice under a Hydra command: once by the stderr handler ``import lightning`` adds
  to its ``lightning`` logger ("INFO: ..."), once by the root logger Hydra configures (the console and the run's
  ``<job>.log``). Where the root logger has a handler, Lightning's own goes: one line each, and the log file has it.

Every other warning and log line still comes through. Called by the entry points, never at import.
"""

from __future__ import annotations

import logging
import sys
import warnings

# rank_zero_info logs to whichever of these Lightning set last (lightning_utilities.core.rank_zero.log)
_TIP_LOGGERS = ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero",
                "pytorch_lightning.utilities.rank_zero")


class _DropTips(logging.Filter):
    """Drops Lightning's advert lines (litlogger, litmodels)."""

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        return not (msg.startswith("💡 Tip:") and ("litlogger" in msg or "litmodels" in msg))


def silence_known_noise() -> None:
    """Install the filters (idempotent)."""
    warnings.filterwarnings("ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated", category=FutureWarning)
    warnings.filterwarnings("ignore", message=r"Found \d+ module\(s\) in eval mode at the start of training")
    for name in _TIP_LOGGERS:
        log = logging.getLogger(name)
        if not any(isinstance(f, _DropTips) for f in log.filters):
            log.addFilter(_DropTips())
    _one_line_per_lightning_record()


def _one_line_per_lightning_record() -> None:
    """Lightning's console handler removed where the root logger prints its records (under Hydra); a no-op before
    Lightning is imported (call again after the import) and outside a configured root logger."""
    if "lightning" not in sys.modules or not logging.getLogger().handlers:
        return
    log = logging.getLogger("lightning")
    if log.propagate:
        for handler in [h for h in log.handlers if type(h) is logging.StreamHandler]:
            log.removeHandler(handler)
