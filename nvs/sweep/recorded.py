"""A committed job's recorded config, read as today's config would state the same run.

Two changes of how a run is written down, neither of what it does:
- the flat layout's ``_target_`` strings (``nvs.core.legacy``);
- ``model=mean_depth`` took the data config's settings one by one under other names (``model.data.fmt``, ...); it
  takes the run's ``data`` node now. A recorded mapping that equals what the run's own data node maps to is that node.
"""

from __future__ import annotations

from typing import Any

from nvs.core.legacy import upgrade_targets
from nvs.run.build import datamodule_arguments

MEAN_DEPTH = "nvs.run.mean_depth.mean_depth_warp"


def as_today(config: Any) -> Any:
    """``config`` (a recorded, resolved config container) with the old spellings above replaced; a copy."""
    config = upgrade_targets(config)
    if not isinstance(config, dict):
        return config
    model, data = config.get("model"), config.get("data")
    if isinstance(model, dict) and model.get("_target_") == MEAN_DEPTH and isinstance(data, dict) \
            and isinstance(model.get("data"), dict) and "fmt" in model["data"]:
        try:
            same = datamodule_arguments(data) == model["data"]
        except (KeyError, TypeError, ValueError):  # a data node that does not map: leave the record as it is
            same = False
        if same:
            config = {**config, "model": {**model, "data": data}}
    return config
