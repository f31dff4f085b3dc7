"""Camera paths for videos: sequences of the viewer's control values, inside the range the model was trained on.

A path is a list of ``{axis name: value}`` dicts, one per frame; ``controls.pose`` turns each into ``T_tgt_src``
with the data module's own pose function (and rejects a value outside the trained range). Paths start at the
source view, so the first frame is the model re-rendering its input.

- ``orbit``: objects swing the azimuth over the whole trained change (+max, back, -max, back) while the elevation
  goes to the farther rendered extreme and back; scenes sway sideways over their range while moving forward (to the
  farthest trained motion) and back.
- ``forward``: scenes drive forward from the source position to the farthest trained forward motion (eased). Objects
  have no forward axis (their camera is on a sphere), so this path is one clear error for them.
- ``custom``: keyframes from a small YAML/JSON file, linearly interpolated to ``frames``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml

from nvs.core.errors import UserError
from nvs.viewer.controls import Axis, ObjectControls, SceneControls, check_values

Controls = ObjectControls | SceneControls
PATHS = ("orbit", "forward", "custom")


def _axes(controls: Controls) -> dict[str, Axis]:
    return {ax.name: ax for ax in controls.axes}


def orbit(controls: Controls, meta: dict[str, float], frames: int) -> list[dict[str, float]]:
    """One closed loop of ``frames`` frames starting (and ending next to) the source view."""
    t = np.arange(frames) / frames
    start = controls.initial(meta)
    ax = _axes(controls)
    if isinstance(controls, ObjectControls):
        az, el = ax["azimuth"], ax["elevation"]
        swing = min(-az.min, az.max)
        e0 = start["elevation"]
        far = el.max if el.max - e0 >= e0 - el.min else el.min
        return [{"azimuth": float(swing * np.sin(2 * np.pi * s)),
                 "elevation": float(e0 + (far - e0) * (1 - np.cos(2 * np.pi * s)) / 2)} for s in t]
    side, fwd = ax["sideways"], ax["forward"]
    sway = min(-side.min, side.max) if side.min < 0 < side.max else (side.max - side.min) / 2
    centre = 0.0 if side.min < 0 < side.max else (side.min + side.max) / 2
    return [{"sideways": float(np.clip(centre + sway * np.sin(2 * np.pi * s), side.min, side.max)),
             "forward": float(fwd.max * (1 - np.cos(2 * np.pi * s)) / 2)} for s in t]


def forward(controls: Controls, meta: dict[str, float], frames: int) -> list[dict[str, float]]:
    """Scenes: from the source position straight ahead to the farthest trained forward motion, eased in and out."""
    if not isinstance(controls, SceneControls):
        raise UserError("path=forward drives the camera forward, which scenes (data.format=scenes) have; an object "
                        "model's camera moves on a sphere around it: use path=orbit or path=custom")
    fwd = _axes(controls)["forward"]
    t = np.linspace(0.0, 1.0, frames)
    ease = (1 - np.cos(np.pi * t)) / 2
    return [{"sideways": 0.0, "forward": float(fwd.max * e)} for e in ease]


def read_keyframes(path: str | Path, controls: Controls) -> list[dict[str, float]]:
    """A YAML or JSON file: ``{poses: [{<axis>: value, ...}, ...]}`` or the bare list; each entry names every axis.

    Values are checked against the trained range when the frames are rendered (``controls.pose``).
    """
    p = Path(path)
    if not p.is_file():
        raise UserError(f"custom={path}: no such file")
    try:
        data = json.loads(p.read_text()) if p.suffix == ".json" else yaml.safe_load(p.read_text())
    except (json.JSONDecodeError, yaml.YAMLError) as err:
        raise UserError(f"{path}: not valid {'JSON' if p.suffix == '.json' else 'YAML'} ({err})") from None
    poses = data.get("poses") if isinstance(data, dict) else data
    names = [ax.name for ax in controls.axes]
    if not isinstance(poses, list) or not poses:
        raise UserError(f"{path}: expected a list of poses under 'poses', each with {', '.join(names)}")
    keyframes = []
    for i, pose in enumerate(poses):
        if not isinstance(pose, dict) or set(pose) != set(names):
            raise UserError(f"{path}: pose {i} is {pose!r}; each pose gives exactly {', '.join(names)}")
        try:
            keyframes.append({k: float(pose[k]) for k in names})
        except (TypeError, ValueError):
            raise UserError(f"{path}: pose {i} has a value that is not a number: {pose!r}") from None
    return keyframes


def interpolate(keyframes: list[dict[str, float]], frames: int | None) -> list[dict[str, float]]:
    """``frames`` frames evenly along the keyframes (piecewise linear); None: the keyframes themselves."""
    if frames is None:
        return [dict(k) for k in keyframes]
    if len(keyframes) == 1:
        return [dict(keyframes[0]) for _ in range(frames)]
    s = np.linspace(0.0, len(keyframes) - 1, frames)
    names = list(keyframes[0])
    table = np.array([[k[n] for n in names] for k in keyframes])
    return [{n: float(np.interp(v, np.arange(len(keyframes)), table[:, j])) for j, n in enumerate(names)} for v in s]


def camera_path(name: str, controls: Controls, meta: dict[str, float], frames: int | None,
                custom: str | Path | None = None) -> list[dict[str, float]]:
    """The control values of every frame of path ``name`` (see the module docstring)."""
    if frames is not None and (not isinstance(frames, int) or frames < 2):
        raise UserError(f"frames={frames!r}: expected a number of frames of at least 2")
    if name == "custom":
        if not custom:
            raise UserError("path=custom needs custom=<a YAML or JSON file of poses>")
        keyframes = read_keyframes(custom, controls)
        for i, values in enumerate(keyframes):  # before any frame is rendered (the frames between stay inside)
            try:
                check_values(controls.axes, values)
            except UserError as err:
                raise UserError(f"{custom}: pose {i}: {err}") from None
        return interpolate(keyframes, frames)
    if frames is None:
        raise UserError(f"path={name} needs frames=<N>")
    if name == "orbit":
        return orbit(controls, meta, frames)
    if name == "forward":
        return forward(controls, meta, frames)
    raise UserError(f"path={name!r}: expected one of {', '.join(PATHS)}")
