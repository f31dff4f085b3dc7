"""Render object categories (chairs, cars) into the ShapeNet-renders format read by nvs.data.shapenet.

Camera (OpenCV): view (az, el) has R_v = Rotation.from_euler('xyz', [-el, az, 0], degrees=True); an object point
X appears in that camera at R_v^T X + c, c = (0, 0, 2). The object frame is the camera frame of view (0, 0)
minus c: x right, y down, z away from that camera, so view (0, 0) shows the model's front and el > 0 looks down.
"""

from __future__ import annotations

import hashlib
import random
import time
import traceback
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from nvs.atomic import write_json, write_text
from nvs.data.render.assets import COPYRIGHT, ModelSource, category_models
from nvs.data.render.output import write_credits, write_depth, write_png
from nvs.data.render.scene import Part, Renderer, bounds, scaled_K, supersampled, to_pyrender, transform_parts

AZIMUTHS = tuple(range(0, 360, 20))
ELEVATIONS = (0, 10, 20)
CENTRE = np.array([0.0, 0.0, 2.0])
K256 = np.array([[480.0, 0.0, 128.0], [0.0, 480.0, 128.0], [0.0, 0.0, 1.0]])
CATEGORY_NAME = {"chairs": "chair", "cars": "car"}
# Canonical model frame (y up, front towards +z) -> object frame (y down, z away from the az=0 camera).
CANON_TO_OBJECT = np.diag([1.0, -1.0, -1.0])
MAX_AZIMUTH_GAP = 40


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


def split_models(models: list[str], seed: int) -> dict[str, list[str]]:
    """Model-level 70/10/20 train/val/test split, seeded; every split non-empty when there are >= 3 models."""
    order = sorted(models)
    random.Random(seed).shuffle(order)
    n = len(order)
    n_test = max(1, round(0.2 * n)) if n >= 3 else 0
    n_val = max(1, round(0.1 * n)) if n >= 3 else 0
    return {"test": sorted(order[:n_test]), "val": sorted(order[n_test:n_test + n_val]),
            "train": sorted(order[n_test + n_val:])}


def azimuth_gap(a: int, b: int) -> int:
    d = abs(a - b) % 360
    return min(d, 360 - d)


def eval_pairs(test_models: list[str], per_model: int, seed: int) -> list[tuple[str, str]]:
    """Seeded (source, target) view pairs of each test model, |delta azimuth| <= 40 with wrap-around."""
    rng = random.Random(seed + 1)
    pairs = []
    for m in sorted(test_models):
        views = view_stems(m)
        chosen: set[tuple[str, str]] = set()
        while len(chosen) < per_model:  # distinct pairs (the loader rejects duplicates)
            a = rng.choice(views)
            partners = [v for v in views if v != a and azimuth_gap(v[1], a[1]) <= MAX_AZIMUTH_GAP]
            b = rng.choice(partners)
            if (a[0], b[0]) not in chosen:
                chosen.add((a[0], b[0]))
                pairs.append((a[0], b[0]))
    return pairs


def geometry_signature(parts: list[Part]) -> str:
    """Hash of a normalised model's vertex set on a 1e-4 grid: equal for identical geometry, whatever the texture."""
    pts = np.concatenate([p.positions[p.faces.reshape(-1)] for p in parts if len(p.faces)])
    grid = np.unique(np.round(pts * 1e4).astype(np.int64), axis=0)
    return hashlib.sha1(grid.tobytes()).hexdigest()


def _signature_path(root: Path, model: str) -> Path:
    return root / "signatures" / f"{model}.txt"


def _report_failure(failed: list[tuple[str, str]], source: ModelSource, err: Exception, progress: bool) -> None:
    from tqdm import tqdm

    msg = f"{err.__class__.__name__}: {err}"
    failed.append((source.id, msg))
    tqdm.write(f"skipped model {source.id} ({source.name}): {msg}")
    if progress:
        tqdm.write(traceback.format_exc(limit=2))


def _render_model(renderer: Renderer, root: Path, model: str, parts: list[Part], factor: int) -> int:
    """Render the 54 views of one normalised model; returns the number of views written."""
    renderer.set_mesh(to_pyrender(parts))
    for stem, az, el in view_stems(model):
        rgb, depth = supersampled(renderer, camera_to_object(az, el), factor)
        write_depth(root / "depth" / f"{stem}.npy", depth)
        write_png(root / "images" / f"{stem}.png", rgb)
    return len(AZIMUTHS) * len(ELEVATIONS)


def render_objects(category: str, out: Path, size: int = 256, seed: int = 0, max_models: int | None = None,
                   sources: list[ModelSource] | None = None, supersample: int = 3, pairs_per_model: int = 30,
                   progress: bool = True) -> dict:
    """Render a category into `out` (ShapeNet-renders format plus depth/, id_val/id_test, meta.json, CREDITS)."""
    from tqdm import tqdm

    out = Path(out)
    sources = category_models(category) if sources is None else sources
    order = sorted(sources, key=lambda m: m.id)
    random.Random(seed).shuffle(order)  # max_models takes a seeded sample; failures are replaced by the next
    K = scaled_K(K256, size)
    renderer = Renderer(size * supersample, scaled_K(K256, size * supersample), znear=0.5, zfar=4.0, lit=True)
    used: list[ModelSource] = []
    failed: list[tuple[str, str]] = []
    duplicates: dict[str, str] = {}  # model -> the model with identical geometry that is used instead
    skipped = views = 0
    t0 = time.perf_counter()
    fresh: set[str] = set()  # rendered by this run
    try:
        # Pass 1, in id order: geometry signatures (cached per model); of identical geometries the first, i.e. the
        # smallest, id is kept, so the kept model does not depend on the seed, max_models or the other sources
        # present. A full render (no max_models) renders each kept model here, while it is loaded.
        keep: dict[str, str] = {}
        for source in tqdm(sorted(order, key=lambda m: m.id), desc=f"render {category} {size}px", unit="model",
                           disable=not progress):
            sig = None
            try:
                sig_file = _signature_path(out, source.id)
                parts = None
                if sig_file.is_file():
                    sig = sig_file.read_text().strip()
                else:
                    parts = normalised(source.load())
                    sig = geometry_signature(parts)
                    write_text(sig_file, sig + "\n")
                if sig in keep:
                    duplicates[source.id] = keep[sig]
                    continue
                keep[sig] = source.id
                if max_models is None and not is_done(out, source.id):
                    parts = normalised(source.load()) if parts is None else parts
                    views += _render_model(renderer, out, source.id, parts, supersample)
                    fresh.add(source.id)
            except Exception as err:  # a broken model must not stop the dataset; it is named and skipped
                if sig is not None and keep.get(sig) == source.id:
                    del keep[sig]  # an identical model later in id order takes its place
                _report_failure(failed, source, err, progress)
        kept = set(keep.values())
        want = len(kept) if max_models is None else min(max_models, len(kept))
        # Pass 2: the kept models in the seeded order until `want` are rendered (max_models takes a seeded sample).
        for source in order:
            if len(used) >= want:
                break
            if source.id not in kept:
                continue
            try:
                if is_done(out, source.id):
                    skipped += source.id not in fresh
                else:
                    views += _render_model(renderer, out, source.id, normalised(source.load()), supersample)
                used.append(source)
            except Exception as err:
                _report_failure(failed, source, err, progress)
    finally:
        renderer.close()
    seconds = time.perf_counter() - t0
    ids = sorted(m.id for m in used)
    if len(ids) < 3:
        raise RuntimeError(f"only {len(ids)} usable models; need >= 3 for train/val/test splits")
    splits = split_models(ids, seed)
    for name, models in splits.items():
        write_text(out / f"id_{name}.txt", "".join(f"{m}\n" for m in models))
    pairs = eval_pairs(splits["test"], pairs_per_model, seed)
    write_text(out / f"eval_{CATEGORY_NAME[category]}_40.txt", "".join(f"{a} {b}\n" for a, b in pairs))
    by_id = {m.id: m for m in used}
    packages = sorted({m.package for m in used})
    write_credits(out, [f"{m.id}: {m.credit}; package {m.package}; licence: {m.licence}" for m in
                        (by_id[i] for i in ids)], packages, COPYRIGHT)
    meta = {
        "format": "objects",
        "category": CATEGORY_NAME[category],
        "size": size,
        "K": K.tolist(),
        "seed": seed,
        "camera": {"centre": CENTRE.tolist(), "azimuths": list(AZIMUTHS), "elevations": list(ELEVATIONS),
                   "rotation": "Rotation.from_euler('xyz', [-el, az, 0], degrees=True)",
                   "front": "view (0, 0) shows the model's front"},
        "depth": "depth/{stem}.npy float32 z-depth in metres, 0 = background",
        "lighting": "two directional lights fixed in the object frame (key 2.5 from above-front-left, fill 1.0 "
                    "from above-behind-right) + ambient 0.35; double-sided faces",
        "supersample": supersample,
        "models": [{"id": i, "name": by_id[i].name, "package": by_id[i].package, "licence": by_id[i].licence,
                    "credit": by_id[i].credit} for i in ids],
        "failed": [{"id": i, "error": e} for i, e in failed],
        "duplicates": [{"id": i, "same_geometry_as": j} for i, j in sorted(duplicates.items())],
        "models_per_package": {p: sum(by_id[i].package == p for i in ids) for p in packages},
        "render_seconds": round(seconds, 2),
        "views_rendered": views,
    }
    write_json(out / "meta.json", meta)
    print(f"{category}: used {len(ids)} models ({skipped} already rendered), {len(duplicates)} duplicates, "
          f"failed {len(failed)}"
          + (f" ({', '.join(i for i, _ in failed)})" if failed else "")
          + f"; {views} views in {seconds:.1f} s" + (f" ({1000 * seconds / views:.1f} ms/view)" if views else ""))
    return meta
