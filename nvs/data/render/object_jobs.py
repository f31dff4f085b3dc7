"""One object model's render job (signature, then its 54 views), in this process or in a pool of worker processes,
and the per-model view geometry it needs (the camera convention is in nvs.data.render.objects).

Rendering is single-threaded Python around Mesa's llvmpipe (a model's load, its scene and the PNG/npy writes), so
two worker processes on two cores render a category in about half the wall time. Each worker owns one offscreen
context. Workers are forked: a model's loader is a closure, which a fork inherits and a pickle cannot carry. A
process that has already opened an offscreen context cannot fork one safely (Mesa's state is not fork-safe: the
child hangs), so there the jobs run in-process, with one printed line. A worker that dies ends the render with an
error (BrokenProcessPool), never a hang.
"""

from __future__ import annotations

import hashlib
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from nvs.core.atomic import write_text
from nvs.data.render.output import write_depth, write_png
from nvs.data.render.scene import (Part, Renderer, bounds, contexts_opened, scaled_K, supersampled, to_pyrender,
                                   transform_parts)
from nvs.data.render.sources import ModelSource

AZIMUTHS = tuple(range(0, 360, 20))
ELEVATIONS = (0, 10, 20)
CENTRE = np.array([0.0, 0.0, 2.0])
K256 = np.array([[480.0, 0.0, 128.0], [0.0, 480.0, 128.0], [0.0, 0.0, 1.0]])
# Canonical model frame (y up, front towards +z) -> object frame (y down, z away from the az=0 camera).
CANON_TO_OBJECT = np.diag([1.0, -1.0, -1.0])


def view_rotation(az: float, el: float) -> np.ndarray:
    return Rotation.from_euler("xyz", [-el, az, 0.0], degrees=True).as_matrix()


def camera_to_object(az: float, el: float) -> np.ndarray:
    """T_obj_cam (4,4): the OpenCV camera of view (az, el) in the object frame (inverse of X -> R^T X + c)."""
    R = view_rotation(az, el)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ CENTRE
    return T


def normalised(parts: list[Part]) -> list[Part]:
    """Canonical parts -> object frame, unit bounding box (largest side 1) centred at the origin."""
    lo, hi = bounds(parts)
    scale = 1.0 / float(np.max(hi - lo))
    centre = (lo + hi) / 2
    return transform_parts(parts, CANON_TO_OBJECT * scale, -CANON_TO_OBJECT @ centre * scale)


def view_stems(model: str) -> list[tuple[str, int, int]]:
    return [(f"{model}_{az}_{el}", az, el) for az in AZIMUTHS for el in ELEVATIONS]


def is_done(root: Path, model: str) -> bool:
    return all((root / "images" / f"{s}.png").is_file() and (root / "depth" / f"{s}.npy").is_file()
               for s, _, _ in view_stems(model))


def geometry_signature(parts: list[Part]) -> str:
    """Hash of a normalised model's vertex set on a 1e-4 grid: equal for identical geometry, whatever the texture."""
    pts = np.concatenate([p.positions[p.faces.reshape(-1)] for p in parts if len(p.faces)])
    grid = np.unique(np.round(pts * 1e4).astype(np.int64), axis=0)
    return hashlib.sha1(grid.tobytes()).hexdigest()


def render_views(renderer: Renderer, root: Path, model: str, parts: list[Part], factor: int) -> int:
    """Render the 54 views of one normalised model; returns the number of views written."""
    renderer.set_mesh(to_pyrender(parts))
    for stem, az, el in view_stems(model):
        rgb, depth = supersampled(renderer, camera_to_object(az, el), factor)
        write_depth(root / "depth" / f"{stem}.npy", depth)
        write_png(root / "images" / f"{stem}.png", rgb)
    return len(AZIMUTHS) * len(ELEVATIONS)


@dataclass(frozen=True)
class Job:
    """What one job renders: out/size/supersample; `render=False` computes the signature only."""

    out: Path
    size: int
    supersample: int
    render: bool


@dataclass
class Result:
    id: str
    sig: str | None = None
    views: int = 0          # views written by this job (0: already rendered, or signature only)
    error: str | None = None
    trace: str | None = None


# Set before a pool forks (inherited by the workers) or used in-process: the sources and one renderer per process.
_SOURCES: Sequence[ModelSource] = ()
_RENDERER: dict[tuple, Renderer] = {}


def _renderer(job: Job) -> Renderer:
    key = (job.size, job.supersample)
    if key not in _RENDERER:
        n = job.size * job.supersample
        _RENDERER[key] = Renderer(n, scaled_K(K256, n), znear=0.5, zfar=4.0, lit=True)
    return _RENDERER[key]


def close_renderers() -> None:
    for r in _RENDERER.values():
        r.close()
    _RENDERER.clear()


def run_one(index: int, job: Job, skip_sigs: frozenset = frozenset()) -> Result:
    """The signature of source `index` (cached in signatures/<id>.txt) and, if `job.render`, its views unless they
    exist or the geometry is in `skip_sigs` (a smaller id with that geometry is already kept)."""
    source = _SOURCES[index]
    res = Result(source.id)
    try:
        sig_file = job.out / "signatures" / f"{source.id}.txt"
        parts: list[Part] | None = None
        if sig_file.is_file():
            res.sig = sig_file.read_text().strip()
        else:
            parts = normalised(source.load())
            res.sig = geometry_signature(parts)
            write_text(sig_file, res.sig + "\n")
        if job.render and res.sig not in skip_sigs and not is_done(job.out, source.id):
            parts = normalised(source.load()) if parts is None else parts
            res.views = render_views(_renderer(job), job.out, source.id, parts, job.supersample)
    except Exception as err:  # a broken model must not stop the dataset; the caller names and skips it
        res.error, res.trace = f"{err.__class__.__name__}: {err}", traceback.format_exc(limit=2)
    return res


def _pool_one(args: tuple[int, Job]) -> Result:
    return run_one(*args)


class Runner:
    """Runs jobs in order, in this process (workers=1) or in `workers` forked processes; results come in order."""

    def __init__(self, sources: Sequence[ModelSource], workers: int):
        global _SOURCES
        _SOURCES = sources
        self.index = {s.id: i for i, s in enumerate(sources)}
        if workers > 1 and contexts_opened():
            print(f"workers={workers}: this process has rendered before (an offscreen context cannot be forked); "
                  "rendering in-process", flush=True)
            workers = 1
        self.pool = (ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"))
                     if workers > 1 else None)

    def map(self, ids: Sequence[str], job: Job, kept: Callable[[], frozenset] = frozenset) -> Iterator[Result]:
        """Results of `ids` in order. In-process, each job skips the geometries `kept()` holds at its turn (no
        duplicate is rendered); workers run ahead, so a duplicate's views may be rendered and are then removed."""
        if self.pool is None:
            return (run_one(self.index[i], job, kept()) for i in ids)
        return self.pool.map(_pool_one, [(self.index[i], job) for i in ids])

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)
        close_renderers()
