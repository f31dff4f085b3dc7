"""Pose controls of the viewer, one per data format: slider values -> T_tgt_src, in the range the model was trained on.

Poses come from the data modules' own functions (``shapenet.relative_pose``, ``kitti.relative_pose``), so a view
asked for in the viewer has exactly the pose the same pair would have in training.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from nvs.core.errors import UserError
from nvs.data import kitti, shapenet
from nvs.data.datamodule import NVSDataModule


@dataclass(frozen=True)
class Axis:
    """One slider. The page drags ``axes[0]`` horizontally and ``axes[1]`` vertically (up = larger)."""

    name: str
    label: str
    unit: str
    min: float
    max: float
    step: float


def check_values(axes: tuple[Axis, ...], values: dict[str, float]) -> None:
    """Every axis has a finite value inside its range; anything else is one UserError naming the axis."""
    for ax in axes:
        if ax.name not in values:
            raise UserError(f"missing pose value '{ax.name}'")
        v = values[ax.name]
        if not np.isfinite(v) or not ax.min - 1e-9 <= v <= ax.max + 1e-9:
            unit = ax.unit if ax.unit == "°" else f" {ax.unit}"
            raise UserError(f"{ax.name}={v:g}{unit} is outside the range the model was trained on "
                            f"[{ax.min:g}{unit}, {ax.max:g}{unit}]")


class ObjectControls:
    """Objects: azimuth relative to the source view and the target's elevation.

    Training pairs differ by at most ``max_delta_azimuth`` degrees of azimuth and have elevations within the
    rendered ones (``shapenet.ELEVATIONS``). An uploaded image is taken as seen from azimuth 0, elevation 0.
    """

    kind = "object"
    upload_meta = {"azimuth": 0.0, "elevation": 0.0}

    def __init__(self, max_delta_azimuth: float, centre: tuple[float, float, float],
                 elevations: tuple[int, ...] = shapenet.ELEVATIONS):
        self.axes = (Axis("azimuth", "azimuth change", "°", -float(max_delta_azimuth), float(max_delta_azimuth), 1.0),
                     Axis("elevation", "elevation", "°", float(min(elevations)), float(max(elevations)), 1.0))
        self.centre = np.asarray(centre, dtype=np.float64)

    def source_meta(self, fid: str) -> dict[str, float]:
        _, az, el = shapenet.parse_stem(fid)
        return {"azimuth": float(az), "elevation": float(el)}

    def initial(self, meta: dict[str, float]) -> dict[str, float]:
        """The values that reproduce the source view."""
        return {"azimuth": 0.0, "elevation": meta["elevation"]}

    def pose(self, values: dict[str, float], meta: dict[str, float]) -> torch.Tensor:
        """T_tgt_src (4,4) float32."""
        check_values(self.axes, values)
        src = (meta["azimuth"], meta["elevation"])
        tgt = (meta["azimuth"] + values["azimuth"], values["elevation"])
        return torch.from_numpy(shapenet.relative_pose(tgt, src, self.centre)).float()


class SceneControls:
    """Scenes: the target camera moved sideways (x, right) and forward (z) in the source camera's frame, no rotation.

    Ranges are those of the training pairs: the target camera's position in the source frame, in metres.
    """

    kind = "scene"
    upload_meta: dict[str, float] = {}

    def __init__(self, sideways: tuple[float, float], forward: tuple[float, float], translation_scale: float):
        self.axes = (Axis("sideways", "sideways", "m", *sideways, _step(sideways)),
                     Axis("forward", "forward", "m", *forward, _step(forward)))
        self.translation_scale = translation_scale

    @classmethod
    def from_pairs(cls, poses: dict, pairs: list[tuple[str, str]], translation_scale: float) -> SceneControls:
        """Ranges from (src, tgt) pairs of ``kitti.read_poses`` poses; each range includes 0 (the source view)."""
        if not pairs:
            raise UserError("no training pairs to take the viewer's motion range from")
        offsets = np.stack([poses[s][0].T @ (poses[t][1] - poses[s][1]) for s, t in pairs])
        span = lambda a: (round(float(min(0.0, a.min())), 2), round(float(max(0.0, a.max())), 2))  # noqa: E731
        return cls(span(offsets[:, 0]), span(offsets[:, 2]), translation_scale)

    def source_meta(self, fid: str) -> dict[str, float]:
        return {}

    def initial(self, meta: dict[str, float]) -> dict[str, float]:
        return {"sideways": 0.0, "forward": 0.0}

    def pose(self, values: dict[str, float], meta: dict[str, float]) -> torch.Tensor:
        """T_tgt_src (4,4) float32: the source camera is the world, the target sits at (sideways, 0, forward)."""
        check_values(self.axes, values)
        here = (np.eye(3), np.zeros(3))
        there = (np.eye(3), np.array([values["sideways"], 0.0, values["forward"]]))
        return torch.from_numpy(kitti.relative_pose(there, here, self.translation_scale)).float()


def _step(span: tuple[float, float]) -> float:
    return max((span[1] - span[0]) / 200.0, 1e-3)


def describe(controls: ObjectControls | SceneControls) -> dict:
    """What the page needs to draw the controls."""
    return {"kind": controls.kind, "axes": [asdict(ax) for ax in controls.axes]}


def build_controls(fmt: str, datamodule: NVSDataModule) -> ObjectControls | SceneControls:
    """The controls of a data format ('objects' | 'scenes'), chosen once at start-up."""
    if fmt == "objects":
        return ObjectControls(datamodule.max_delta_azimuth, tuple(datamodule.camera.pivot))
    if fmt == "scenes":
        lo = datamodule.loader
        pairs = datamodule.fmt.pairs("train", lo.val_fraction, datamodule.seed)
        return SceneControls.from_pairs(datamodule.fmt.poses, pairs, datamodule.fmt.translation_scale)
    raise UserError(f"data.format={fmt!r}: the viewer has controls for 'objects' and 'scenes'")
