"""The typed schema of every command's config: OmegaConf structured configs (dataclasses) the composed config is
validated against (``nvs.run.config_check.check_config``), so that a wrong type or an unknown key, on the command
line or in a YAML file, is one error naming the key.

The schema types the config; it sets no value: every field is MISSING, so the composed config (what a run records
and what the sweep's staleness check compares) is exactly what the YAML files and the overrides make it. A component
(a mapping with ``_target_``: the model, each loss term, the optimiser, the trainer, each callback and logger, the
data's depth head) is typed by its target's own arguments (``nvs.run.component_schema``); its field here is marked
``component()``. Range rules (a positive batch size, ``limit >= 1``, a fidelity switch's choices) stay where the
value is used, beside the typed arguments they guard.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass
from typing import Any, Dict, List, Optional

from omegaconf import MISSING

from nvs.core.fidelity import SWITCHES


def _typed():
    return dataclasses.field(default=MISSING)


def component(*, each: bool = False, extra: dict[str, Any] | None = None, target: str | None = None):
    """A field holding a component (``each``: a mapping of named components, as ``loss``). ``extra``: keys the
    component may hold beside its target's arguments (the model's ``name``); ``target``: the arguments of this
    callable, for a node without ``_target_`` (nvs.evaluate's ``trainer``: Lightning Trainer arguments)."""
    return dataclasses.field(default=MISSING, metadata={"component": {"each": each, "extra": extra or {},
                                                                      "target": target}})


@dataclass
class Paths:
    root_dir: str = _typed()
    data_dir: str = _typed()
    log_dir: str = _typed()
    output_dir: str = _typed()


@dataclass
class Camera:  # nvs.data.datamodule.Camera
    fx: float = _typed()
    fy: float = _typed()
    cx: float = _typed()
    cy: float = _typed()
    size: int = _typed()
    pivot: List[float] = _typed()


@dataclass
class Augment:  # nvs.data.datamodule.PairDataset's augmentations
    mirror: bool = _typed()
    permute_rgb: bool = _typed()


@dataclass
class Loader:  # nvs.data.datamodule.LoaderSettings
    batch_size: int = _typed()
    eval_batch_size: int = _typed()
    num_workers: int = _typed()
    val_fraction: float = _typed()
    val_pairs_per_model: int = _typed()
    cache: bool = _typed()
    with_depth: bool = _typed()
    limit_test_pairs: Optional[int] = _typed()
    augment: Optional[Augment] = _typed()


class DataFormat(enum.Enum):
    objects = "objects"
    scenes = "scenes"


class OutsideSource(enum.Enum):
    border = "border"
    zeros = "zeros"


@dataclass
class Data:  # nvs.run.build.datamodule_arguments
    format: DataFormat = _typed()
    name: str = _typed()
    category: Optional[str] = _typed()
    size: int = _typed()
    root: Optional[str] = _typed()
    camera: Camera = _typed()
    outside_source: OutsideSource = _typed()
    translation_scale: float = _typed()
    max_delta_azimuth: int = _typed()
    train_fraction: float = _typed()
    depth_head: Any = component()
    loader: Loader = _typed()


def _switch_type(key: str) -> Any:
    """A fidelity switch's type: a string switch is an Enum of its choices (a value outside them is OmegaConf's
    error), a bool a bool, a factor a number; the choices of a number (vgg_size: 224 or null) stay core/fidelity's."""
    sw = SWITCHES[key]
    if sw.choices is None:
        return float
    kinds = {type(c) for c in sw.choices if c is not None}
    if kinds == {str}:
        return enum.Enum(key, {c: c for c in sw.choices})
    (kind,) = kinds
    return Optional[kind] if None in sw.choices else kind


Fidelity = dataclasses.make_dataclass("Fidelity", [(k, _switch_type(k), _typed()) for k in SWITCHES])


class NonFinite(enum.Enum):
    stop = "stop"
    skip = "skip"


@dataclass
class Train:  # conf/train.yaml
    paths: Paths = _typed()
    data: Data = _typed()
    loss: Optional[Dict[str, Any]] = component(each=True)
    model: Any = component(extra={"name": str})
    optim: Any = component()
    fidelity: Fidelity = _typed()
    scheduler: Any = component()
    trainer: Any = component()
    callbacks: Optional[Dict[str, Any]] = component(each=True)
    logger: Optional[Dict[str, Any]] = component(each=True)
    task_name: str = _typed()
    tags: List[str] = _typed()
    seed: int = _typed()
    nonfinite: NonFinite = _typed()
    channels_last: Any = _typed()  # auto, true or false (nvs.run.precision.choose)
    compile: bool = _typed()
    test: bool = _typed()
    ckpt_path: Optional[str] = _typed()


@dataclass
class Calibration:  # evaluate's fits of a route rule and of the adaptive threshold (nvs.run.validation_pass)
    tolerance: float = _typed()
    val_pairs: Optional[int] = _typed()
    candidates: int = _typed()


@dataclass
class Evaluate:  # conf/evaluate.yaml
    paths: Paths = _typed()
    data: Optional[Data] = _typed()
    model: Any = component(extra={"name": str})
    fidelity: Optional[Fidelity] = _typed()
    trainer: Any = component(target="lightning.pytorch.Trainer")
    task_name: str = _typed()
    ckpt_path: Optional[str] = _typed()
    seed: int = _typed()
    limit: Optional[int] = _typed()
    precision: Optional[str] = _typed()
    out_dir: str = _typed()
    route: Any = _typed()  # off, fit or a rule file (nvs.run.routing.route_option)
    skips_threshold: Any = _typed()  # null, calibrate or pixels (nvs.run.skips_calibration.threshold_option)
    calibration: Calibration = _typed()
    time_sizes: Any = _typed()  # null or image sizes (nvs.run.size_timing.sizes_option)
    time_repeats: int = _typed()


@dataclass
class _Tool:  # what every tool that opens a checkpoint's gallery shares
    paths: Paths = _typed()
    data: Optional[Data] = _typed()
    task_name: str = _typed()
    ckpt_path: Optional[str] = _typed()
    precision: Optional[str] = _typed()
    gallery: int = _typed()
    seed: int = _typed()


@dataclass
class ViewerLoad:
    requests: int = _typed()
    warmup: int = _typed()
    out: Optional[str] = _typed()


@dataclass
class ViewerScreenshot:
    out: str = _typed()
    source: int = _typed()
    drag: List[float] = _typed()


@dataclass
class Viewer(_Tool):  # conf/viewer.yaml
    host: str = _typed()
    port: int = _typed()
    threads: Optional[int] = _typed()
    compile: bool = _typed()  # torch.compile of the pose step, frozen weights (nvs.viewer.session)
    route: Optional[str] = _typed()  # a route_rule.json fitted on the checkpoint
    load: ViewerLoad = _typed()
    screenshot: ViewerScreenshot = _typed()


@dataclass
class RenderVideo(_Tool):  # conf/render_video.yaml
    source: Any = _typed()  # a gallery index, a test image id or an image file
    path: str = _typed()
    custom: Optional[str] = _typed()
    frames: Optional[int] = _typed()
    fps: float = _typed()
    scale: int = _typed()
    formats: List[str] = _typed()
    gif_colors: int = _typed()
    out_dir: Optional[str] = _typed()
    name: Optional[str] = _typed()
    progress: bool = _typed()


@dataclass
class ExportPly(_Tool):  # conf/export_ply.yaml
    source: Any = _typed()
    pose: Optional[Dict[str, float]] = _typed()
    max_depth: Optional[float] = _typed()
    keep_background: bool = _typed()
    out: Optional[str] = _typed()


# config name -> its schema
SCHEMAS: dict[str, type] = {"train": Train, "evaluate": Evaluate, "viewer": Viewer, "render_video": RenderVideo,
                            "export_ply": ExportPly}
