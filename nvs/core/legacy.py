"""What earlier versions of nvs recorded, read as today's names: configs in committed jobs and in checkpoints.

Up to 0.1 the package was flat (``nvs.checkpoints``, ``nvs.losses``, ...); the layers are folders now. A ``_target_``
string recorded then (``nvs.losses.ReconLoss``, ``nvs.checkpoints.ModelCheckpoint``) names the old module, so every
reader of a stored config maps it through :func:`upgrade_targets` before instantiating or comparing it.
"""

from __future__ import annotations

from typing import Any

# old module -> its module now (the flat layout of nvs 0.1 -> the layer folders)
MOVED = {
    "nvs.atomic": "nvs.core.atomic", "nvs.choices": "nvs.core.choices", "nvs.errors": "nvs.core.errors",
    "nvs.geometry": "nvs.core.geometry", "nvs.metric_spec": "nvs.core.metric_spec", "nvs.scales": "nvs.core.scales",
    "nvs.types": "nvs.core.types", "nvs.provenance": "nvs.core.provenance", "nvs.fidelity": "nvs.core.fidelity",
    "nvs.synthetic": "nvs.data.synthetic", "nvs.perceptual": "nvs.models.perceptual",
    "nvs.losses": "nvs.losses.terms", "nvs.losses_branches": "nvs.losses.branches",
    "nvs.losses_adversarial": "nvs.losses.adversarial", "nvs.metrics": "nvs.metrics.per_image",
    "nvs.module": "nvs.module.lightning_module", "nvs.gather": "nvs.module.gather",
    "nvs.build": "nvs.run.build", "nvs.compose": "nvs.run.compose", "nvs.config_check": "nvs.run.config_check",
    "nvs.checkpoints": "nvs.run.checkpoints", "nvs.training": "nvs.run.training",
    "nvs.fit_callbacks": "nvs.run.standard_callbacks", "nvs.callbacks": "nvs.run.display_callbacks",
    "nvs.convergence": "nvs.run.convergence", "nvs.run_files": "nvs.run.artifacts", "nvs.runs": "nvs.run.finished",
    "nvs.multirun": "nvs.run.multirun", "nvs.quiet": "nvs.run.quiet", "nvs.precision": "nvs.run.precision",
    "nvs.train_depth": "nvs.run.mean_depth", "nvs.visuals": "nvs.run.visuals",
    "nvs.paper_figures": "nvs.report.figures", "nvs.pointcloud": "nvs.report.pointcloud",
}

# (dotted key, recorded value, value now): defaults renamed with the behaviour kept. nvs.evaluate's precision
# null -> auto: a reference row (no checkpoint) runs in 32-true either way.
SAME_BEHAVIOUR = {("precision", None, "auto")}


def current_target(target: str) -> str:
    """``module.Name`` as importable today (a moved module replaced by its new place; anything else unchanged)."""
    module, dot, name = target.rpartition(".")
    return f"{MOVED[module]}.{name}" if dot and module in MOVED else target


def upgrade_targets(node: Any) -> Any:
    """A copy of a config container (dicts, lists) with every ``_target_`` string mapped by :func:`current_target`."""
    if isinstance(node, dict):
        return {k: current_target(v) if k == "_target_" and isinstance(v, str) else upgrade_targets(v)
                for k, v in node.items()}
    if isinstance(node, list):
        return [upgrade_targets(v) for v in node]
    return node
