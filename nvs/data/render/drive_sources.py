"""The drive scenes: what a scene source gives the renderer (centre-line runs, surfaces, sky), the TORCS and
SuperTuxKart sources, and the `sources=` option (which sources, how many sequences per round-robin turn)."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import numpy as np
from PIL import Image

from nvs.data.render.ac3d import read_ac3d
from nvs.data.render.assets import TORCS_DIR, ac3d_parts
from nvs.data.render.scene import Part
from nvs.data.render.torcs_track import centre_line, road_tracks

SKY_ELEVATION = (-10.0, 60.0)  # degrees spanned by background.png from bottom to top row (approximate)
DEFAULT_SOURCES = "stk:2,torcs"


@dataclass
class DriveScene:
    """A loaded scene: surfaces (y up, metres), centre-line runs [(points (n,3), road widths (n,))] in driving
    order, and sky colour of viewing directions (...,3) -> RGB (...,3) float 0..255."""

    parts: list[Part]
    runs: list[tuple[np.ndarray, np.ndarray]]
    sky: Callable[[np.ndarray], np.ndarray]
    missing: list[str]


@dataclass
class SceneSource:
    """One scene to drive through: source ('stk' | 'torcs' | 'trigger'), name, centre-line runs (cheap to read),
    the full loader, the Debian package, its licence and a credit line."""

    source: str
    name: str
    runs: Callable[[], list[tuple[np.ndarray, np.ndarray]]]
    load: Callable[[], DriveScene]
    package: str
    licence: str
    credit: str


def panorama_sky(panorama: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A cylindrical panorama (H,W,3) spanning SKY_ELEVATION -> sky colour of directions (...,3)."""

    def sky(d: np.ndarray) -> np.ndarray:
        azimuth = np.arctan2(d[..., 0], d[..., 2])
        elevation = np.degrees(np.arcsin(np.clip(d[..., 1], -1, 1)))
        H, W = panorama.shape[:2]
        col = ((azimuth / (2 * np.pi)) % 1.0 * W).astype(np.int64) % W
        lo, hi = SKY_ELEVATION
        row = np.clip(((hi - elevation) / (hi - lo) * (H - 1)).round().astype(np.int64), 0, H - 1)
        return panorama[row, col].astype(np.float32)

    return sky


@functools.lru_cache(maxsize=64)
def _track_centre_line(acc: str, mtime_ns: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """A TORCS track's centre line, read once per file version: planning and rendering ask for it again and again
    (a whole .acc parsed each time was two thirds of a small render). The arrays are read-only, being shared."""
    points, widths = centre_line(read_ac3d(acc))
    points.setflags(write=False)
    widths.setflags(write=False)
    return points, widths


def torcs_sources() -> list[SceneSource]:
    out = []
    for d in road_tracks():
        acc = d / f"{d.name}.acc"

        def runs(acc=acc):
            st = acc.stat()
            return [_track_centre_line(str(acc), st.st_mtime_ns, st.st_size)]

        def load(d=d, acc=acc, runs=runs):
            parts = ac3d_parts(acc, [d, TORCS_DIR / "data" / "textures"])
            with Image.open(d / "background.png") as im:
                panorama = np.asarray(im.convert("RGB"))
            return DriveScene(parts, runs(), panorama_sky(panorama), [])

        out.append(SceneSource("torcs", d.name, runs, load, "torcs-data", "GPL-2+ / Free Art License",
                               f"TORCS road track {d.name} (tracks/road/{d.name}/readme.txt)"))
    return out


def stk_sources() -> list[SceneSource]:
    from nvs.data.render import stk, stk_scene

    out = []
    for d in stk.race_tracks():
        info = stk.track_info(d)

        def load(d=d):
            parts, missing = stk_scene.load_scene(d)
            return DriveScene(parts, stk.driveline(d), stk_scene.sky_function(d), missing)

        out.append(SceneSource("stk", d.name, lambda d=d: stk.driveline(d), load, "supertuxkart-data",
                               "CC-BY-SA / GPL (see the package's copyright file)",
                               f"SuperTuxKart track '{info['name']}' by {info['designer'] or 'the STK team'} "
                               f"(tracks/{d.name})"))
    return out


SOURCES: dict[str, Callable[[], list[SceneSource]]] = {"stk": stk_sources, "torcs": torcs_sources}
INSTALL = {"stk": "scripts/install_drive_assets.sh", "torcs": "scripts/install_assets.sh"}


def parse_sources(names: str) -> dict[str, int]:
    """'stk:2,torcs' -> {'stk': 2, 'torcs': 1} (sequences per round-robin turn)."""
    out = {}
    for item in [n.strip() for n in names.split(",") if n.strip()]:
        name, _, k = item.partition(":")
        if name not in SOURCES:
            raise ValueError(f"unknown drive source {name!r}; known: {', '.join(SOURCES)}")
        if name in out:
            raise ValueError(f"drive source {name!r} given twice in {names!r}")
        try:
            out[name] = int(k) if k else 1
        except ValueError:
            raise ValueError(f"drive source weight must be an integer, got {item!r}") from None
        if out[name] < 1:
            raise ValueError(f"drive source weight must be >= 1, got {item!r}")
    if not out:
        raise ValueError("sources is empty")
    return out


def scene_sources(names: str) -> dict[str, list[SceneSource]]:
    """The requested sources' scenes, in source order; a requested source with nothing installed is an error."""
    out = {}
    for name in parse_sources(names):
        found = SOURCES[name]()
        if not found:
            raise FileNotFoundError(f"no {name} scenes installed; run {INSTALL[name]}")
        out[name] = found
    return out
