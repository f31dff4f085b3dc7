"""A job's composed config as the sweep stores and compares it: the fingerprint, its digest, what makes it stale.

The fingerprint is the composed config resolved, with the keys that only place or display a run (``NEUTRAL_KEYS``)
left out; ``config_changes`` lists the keys whose difference makes a finished job stale (the rule is in the module
doc of ``nvs.sweep.jobs``).
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

from omegaconf import DictConfig, OmegaConf

from nvs.core.legacy import SAME_BEHAVIOUR

# Keys that place or display a run but do not change its result; left out of the key and of the stored config.
NEUTRAL_KEYS = ("paths", "hydra", "ckpt_path", "out_dir", "task_name", "tags",
                "trainer.enable_progress_bar", "trainer.enable_model_summary")


def _drop(container: dict, dotted: str) -> None:
    *parents, last = dotted.split(".")
    node = container
    for p in parents:
        node = node.get(p) if isinstance(node, dict) else None
        if node is None:
            return
    if isinstance(node, dict):
        node.pop(last, None)


def config_fingerprint(cfg: DictConfig) -> dict:
    """The composed config resolved, with placement-only keys removed (what sweep_job.json stores and checks)."""
    cfg = cfg.copy()
    if "paths" in cfg and "output_dir" in cfg.paths:
        cfg.paths.output_dir = "<job dir>"  # a hydra: interpolation; its value is the job dir either way
    if "out_dir" in cfg:
        cfg.out_dir = "<job dir>"
    container = OmegaConf.to_container(cfg, resolve=True)
    for key in NEUTRAL_KEYS:
        _drop(container, key)
    return container


def config_digest(fingerprint: dict) -> str:
    blob = json.dumps(fingerprint, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def config_changes(old: Any, new: Any, prefix: str = "") -> list[str]:
    """The dotted keys that make a result stale: changed or removed ones, and new components (see the module doc of
    ``nvs.sweep.jobs``)."""
    if not (isinstance(old, dict) and isinstance(new, dict)):
        key = prefix.rstrip(".")  # SAME_BEHAVIOUR compared, not hashed: a leaf may be a list
        return [] if old == new or any(r == (key, old, new) for r in SAME_BEHAVIOUR) else [key or "<config>"]
    out = []
    for k in sorted(set(old) | set(new), key=str):
        if k not in new:
            out.append(f"{prefix}{k}")
        elif k not in old:
            if _has_component(new[k]):
                out.append(f"{prefix}{k}")
        else:
            out += config_changes(old[k], new[k], f"{prefix}{k}.")
    return out


def _has_component(node: Any) -> bool:
    """Whether a config node is, or holds at any depth, a component (a mapping with ``_target_``)."""
    if isinstance(node, dict):
        return "_target_" in node or any(_has_component(v) for v in node.values())
    if isinstance(node, list):
        return any(_has_component(v) for v in node)
    return False
