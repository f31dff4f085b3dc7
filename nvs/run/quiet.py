"""Silence the known start-up noise of Lightning and torch, and only that: each filter matches one message.

- Lightning's "💡 Tip: ... litlogger / litmodels" adverts (INFO lines on every run).
- torch's FutureWarning that Lightning's own pytree helper uses ``LeafSpec``.
- "Found N module(s) in eval mode at the start of training": nvs's frozen loss networks (VGG, LPIPS) are meant to
  stay in eval mode.

Every other warning and log line still comes through. Called by the entry points, never at import.
"""

from __future__ import annotations

import logging
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
