"""Render object categories (chairs, cars) into the ShapeNet-renders format read by nvs.data.shapenet.

Camera (OpenCV): view (az, el) has R_v = Rotation.from_euler('xyz', [-el, az, 0], degrees=True); an object point
X appears in that camera at R_v^T X + c, c = (0, 0, 2). The object frame is the camera frame of view (0, 0)
minus c: x right, y down, z away from that camera, so view (0, 0) shows the model's front and el > 0 looks down.
"""

from __future__ import annotations

import random
import time
from pathlib import Path

from nvs.core.atomic import write_json, write_text
from nvs.data.render.assets import ModelSource, category_models, copyright_files
from nvs.data.render.sources import DEFAULT_ASSETS
# the per-model view geometry lives with the render job; re-exported for the dataset's readers and tests
from nvs.data.render.object_jobs import (AZIMUTHS, CENTRE, ELEVATIONS, K256, Job, Result, Runner,  # noqa: F401
                                         camera_to_object, geometry_signature, is_done, normalised,
                                         view_stems)
from nvs.data.render.output import write_credits
from nvs.data.render.scene import scaled_K

CATEGORY_NAME = {"chairs": "chair", "cars": "car"}
MAX_AZIMUTH_GAP = 40


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


def _report_failure(failed: list[tuple[str, str]], source: ModelSource, res: Result, progress: bool) -> None:
    from tqdm import tqdm

    failed.append((source.id, res.error))
    tqdm.write(f"skipped model {source.id} ({source.name}): {res.error}")
    if progress and res.trace:
        tqdm.write(res.trace)


def _remove_views(root: Path, model: str) -> None:
    for stem, _, _ in view_stems(model):
        (root / "images" / f"{stem}.png").unlink(missing_ok=True)
        (root / "depth" / f"{stem}.npy").unlink(missing_ok=True)


def render_objects(category: str, out: Path, size: int = 256, seed: int = 0, max_models: int | None = None,
                   sources: list[ModelSource] | None = None, supersample: int = 3, pairs_per_model: int = 30,
                   progress: bool = True, workers: int = 1, assets: Path = DEFAULT_ASSETS) -> dict:
    """Render a category into `out` (ShapeNet-renders format plus depth/, id_val/id_test, meta.json, CREDITS).
    `workers` > 1 renders models in that many forked processes (same files; see nvs.data.render.object_jobs).
    `assets`: the folder of extracted asset packages (nvs.data.render.sources.asset_dir)."""
    from tqdm import tqdm

    out = Path(out)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers={workers!r}: expected an integer >= 1")
    assets = Path(assets).resolve()
    sources = category_models(category, assets) if sources is None else sources
    by_id = {m.id: m for m in sources}
    order = sorted(sources, key=lambda m: m.id)
    random.Random(seed).shuffle(order)  # max_models takes a seeded sample; failures are replaced by the next
    K = scaled_K(K256, size)
    used: list[ModelSource] = []
    failed: list[tuple[str, str]] = []
    duplicates: dict[str, str] = {}  # model -> the model with identical geometry that is used instead
    skipped = views = 0
    t0 = time.perf_counter()
    fresh: set[str] = set()  # rendered by this run
    runner = Runner(sources, min(workers, len(sources)) if sources else 1)
    try:
        # Pass 1, in id order: geometry signatures (cached per model); of identical geometries the first, i.e. the
        # smallest, id is kept, so the kept model does not depend on the seed, max_models or the other sources
        # present. A full render (no max_models) renders each kept model here, while it is loaded.
        keep: dict[str, str] = {}
        job = Job(out, size, supersample, render=max_models is None)
        results = runner.map(sorted(by_id), job, kept=lambda: frozenset(keep))
        for res in tqdm(results, total=len(by_id), desc=f"render {category} {size}px", unit="model",
                        disable=not progress):
            if res.error is not None:
                _report_failure(failed, by_id[res.id], res, progress)  # an identical model later takes its place
            elif res.sig in keep:
                duplicates[res.id] = keep[res.sig]
                if res.views:  # rendered ahead by a worker: not part of the dataset
                    _remove_views(out, res.id)
            else:
                keep[res.sig] = res.id
                views += res.views
                fresh.update([res.id] if res.views else [])
        kept = set(keep.values())
        want = len(kept) if max_models is None else min(max_models, len(kept))
        # Pass 2: the kept models in the seeded order until `want` are rendered (max_models takes a seeded sample).
        candidates = [m.id for m in order if m.id in kept]
        render = Job(out, size, supersample, render=True)
        while len(used) < want and candidates:
            batch, candidates = candidates[:want - len(used)], candidates[want - len(used):]
            todo = [i for i in batch if not is_done(out, i)]
            done = {r.id: r for r in runner.map(todo, render)}
            for i in batch:
                res = done.get(i)
                if res is not None and res.error is not None:
                    _report_failure(failed, by_id[i], res, progress)
                    continue
                skipped += res is None and i not in fresh
                views += res.views if res is not None else 0
                used.append(by_id[i])
    finally:
        runner.close()
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
                        (by_id[i] for i in ids)], packages, copyright_files(assets))
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
