"""Render driving sequences through game scenes into the KITTI-odometry format read by nvs.data.kitti.

Sources (`sources=` option, comma-separated, `name:k` takes k sequences per turn; round-robin over sources,
then over each source's scenes):
  stk      SuperTuxKart race tracks (nvs.data.render.stk): town streets, temples, mansions, forests; the
           centre line is the driveline (quads.xml); scripts/install_drive_assets.sh extracts the data.
  torcs    TORCS road tracks (AC3D, nvs.data.render.torcs_track): the centre line comes from the mesh:
           road-surface objects `TKMN*` are triangle strips whose vertex pairs are road cross-sections.

The camera (OpenCV; `camera=kitti`: the paper's KITTI intrinsics f = 718.9, c = 128 at 256^2, a ~20 degree view;
`camera=wide`: f = 160, ~77 degrees) rides 1.65 m above the centre of the right lane, 1 m between frames,
looking along the smoothed centre line (pitch follows the road, roll 0). A scene's sequences are disjoint
windows of its centre line. Splits are by scene (a test scene is never trained on). Sky pixels get the scene's
sky (panorama, sky-box or colour) and depth 0 (no data).

The pieces: drive_sources (scenes and the `sources=` option), torcs_track / stk (centre lines), drive_rig (camera
and poses), drive_plan (windows, splits, pairs), depth_stats (depth_stats.json); this file writes the render.
"""

from __future__ import annotations

import json
import random
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from nvs.core.atomic import write_json, write_text
from nvs.data.render.assets import copyright_files as object_copyright_files
from nvs.data.render.depth_stats import DEPTH_BINS, depth_histogram
from nvs.data.render.drive_plan import Planned, frame_id, pairs_all, pairs_sampled, plan_sequences, split_scenes
from nvs.data.render.drive_rig import CAMERA_HEIGHT, STEP, camera_K, camera_poses, resample, view_dirs
from nvs.data.render.drive_sources import DEFAULT_SOURCES, parse_sources, scene_sources
from nvs.data.render.output import write_credits, write_depth, write_png
from nvs.data.render.scene import Renderer, scaled_K, to_pyrender
from nvs.data.render.stk import STK_COPYRIGHT


def pose_line(fid: str, T: np.ndarray) -> str:
    r = Rotation.from_matrix(T[:3, :3]).as_euler("xyz")
    vals = [*r, *T[:3, 3]]
    return fid + " " + " ".join(f"{v:.9f}" for v in vals) + "\n"


def _check_plan(out: Path, plan: dict) -> None:
    """Frames on disk are reused only when they were rendered for the same plan (plan.json, written first)."""
    f = out / "plan.json"
    if f.is_file():
        before = json.loads(f.read_text())
        if before != plan:
            keys = sorted(k for k in plan if before.get(k) != plan[k])
            raise ValueError(f"{f}: {out} holds frames of another render ({', '.join(keys)} differ); "
                             "render into a new out= folder or delete this one")
    elif (out / "images").is_dir() and any((out / "images").iterdir()):
        raise ValueError(f"{out} holds frames but no plan.json (another renderer's output?); render into a new "
                         "out= folder or delete this one")
    write_json(f, plan)


def render_drive(out: Path, size: int = 256, seed: int = 0, sequences: int = 10, frames: int = 200,
                 supersample: int = 3, sources: str = DEFAULT_SOURCES, camera: str = "kitti",
                 progress: bool = True) -> dict:
    """Render `sequences` x `frames` frames into `out` (KITTI-odometry format plus depth/, meta.json,
    depth_stats.json, CREDITS.txt). Frames already on disk are kept (reruns resume)."""
    from tqdm import tqdm

    if sequences > 100:
        raise ValueError("at most 100 sequences (frame ids carry a two-digit sequence number)")
    out = Path(out)
    K256 = camera_K(camera)
    K = scaled_K(K256, size)
    Kss = scaled_K(K256, size * supersample)
    failed: list[str] = []
    plan = plan_sequences(scene_sources(sources), sequences, frames, seed, failed, parse_sources(sources))
    _check_plan(out, {"size": size, "supersample": supersample, "camera": camera, "frames": frames,
                      "sequences": [[p.scene.source, p.scene.name, p.run, p.start] for p in plan]})
    renderer = Renderer(size * supersample, Kss, znear=0.3, zfar=5000.0, bg_color=(0.0, 0.0, 0.0), lit=False)
    poses_lines: dict[int, list[str]] = {}
    missing: dict[str, list[str]] = {}
    rendered = 0
    seconds_by_source: dict[str, float] = {}
    t0 = time.perf_counter()
    bar = tqdm(total=sequences * frames, desc=f"render drive {size}px", unit="frame", disable=not progress)
    by_scene: dict[tuple[str, str], list[Planned]] = {}
    for p in plan:
        by_scene.setdefault((p.scene.source, p.scene.name), []).append(p)
    S, c = size * supersample, supersample // 2
    try:
        for (src, name), items in by_scene.items():
            ts = time.perf_counter()
            runs = [resample(pts, w, STEP) for pts, w in items[0].scene.runs()]
            todo = []
            for p in items:
                path, widths = runs[p.run]
                poses = camera_poses(path, widths, p.start, frames)
                T0_inv = np.linalg.inv(poses[0])
                poses_lines[p.seq] = [pose_line(frame_id(p.seq, i), T0_inv @ T) for i, T in enumerate(poses)]
                ids = [frame_id(p.seq, i) for i in range(frames)]
                if all((out / "images" / f"{i}.png").is_file() and (out / "depth" / f"{i}.npy").is_file()
                       for i in ids):
                    bar.update(frames)
                else:
                    todo.append((ids, poses))
            if todo:
                scene = items[0].scene.load()
                if scene.missing:
                    missing[f"{src}/{name}"] = scene.missing
                renderer.set_mesh(to_pyrender(scene.parts))
                for ids, poses in todo:
                    for fid, T in zip(ids, poses):
                        rgb, depth = renderer.render(T)
                        sky = depth <= 0
                        img = rgb.astype(np.float32)
                        if sky.any():
                            img[sky] = scene.sky(view_dirs(T, Kss, S)[sky])
                        img = img.reshape(size, supersample, size, supersample, 3).mean(axis=(1, 3))
                        write_depth(out / "depth" / f"{fid}.npy", depth[c::supersample, c::supersample])
                        write_png(out / "images" / f"{fid}.png", np.clip(np.rint(img), 0, 255).astype(np.uint8))
                        rendered += 1
                        bar.update(1)
            seconds_by_source[src] = seconds_by_source.get(src, 0.0) + time.perf_counter() - ts
    finally:
        bar.close()
        renderer.close()
    seconds = time.perf_counter() - t0
    write_text(out / "poses.txt", "".join(line for s in sorted(poses_lines) for line in poses_lines[s]))
    split = split_scenes(plan, seed)
    rng = random.Random(seed + 1)
    train = [p for s in split["train"] for p in pairs_all(s, frames)]
    val = [p for s in split["val"] for p in pairs_sampled(s, frames, rng)]
    test = [p for s in split["test"] for p in pairs_sampled(s, frames, rng)]
    for fname, pairs in (("pairs_train.txt", train), ("pairs_val.txt", val), ("eval_kitti.txt", test)):
        write_text(out / fname, "".join(f"{a} {b}\n" for a, b in pairs))
    used = {(p.scene.source, p.scene.name): p.scene for p in plan}
    packages = sorted({sc.package for sc in used.values()})
    copyright_files = object_copyright_files()  # the drive sources' packages are installed ones, not extracted
    copyright_files["supertuxkart-data"] = STK_COPYRIGHT
    write_credits(out, [f"{sc.credit}; package {sc.package}; licence: {sc.licence}"
                        for _, sc in sorted(used.items())], packages, copyright_files)
    counts = {}
    for src in sorted({p.scene.source for p in plan}):
        ids = [frame_id(p.seq, i) for p in plan if p.scene.source == src for i in range(frames)]
        counts[src] = depth_histogram(out, ids).tolist()
    write_json(out / "depth_stats.json", {
        "bins_m": DEPTH_BINS.tolist(),
        "about": "per source: [0] = pixels without depth (sky), then counts of depths in metres per bin "
                 "[bins_m[k], bins_m[k+1]); see nvs.data.render.depth_stats.representable_fraction",
        "size": size, "camera": camera, "K": K.tolist(), "sequences": sequences, "frames": frames,
        "counts": counts})
    meta = {
        "format": "scenes",
        "size": size,
        "K": K.tolist(),
        "camera": camera,
        "seed": seed,
        "sources": sources,
        "sequences": [{"seq": p.seq, "source": p.scene.source, "scene": p.scene.name, "run": p.run,
                       "start_m": p.start * STEP, "frames": frames} for p in plan],
        "split": {k: [f"{s:02d}" for s in v] for k, v in split.items()},
        "rig": {"height_m": CAMERA_HEIGHT, "step_m": STEP, "lane": "right lane centre (road width / 4)",
                "poses": "camera-to-world of the OpenCV camera, relative to each sequence's first frame"},
        "depth": "depth/{id}.npy float32 z-depth in metres, 0 = sky / no data",
        "lighting": "unlit (texture colour); sky from the scene's panorama / sky-box / colour, depth 0",
        "supersample": supersample,
        "licence": "per scene, see CREDITS.txt",
        "failed_scenes": failed,
        "missing_files": missing,
        "render_seconds": round(seconds, 2),
        "render_seconds_by_source": {k: round(v, 2) for k, v in seconds_by_source.items()},
        "frames_rendered": rendered,
    }
    write_json(out / "meta.json", meta)
    print(f"drive: {sequences} sequences x {frames} frames from {len(used)} scenes "
          f"({', '.join(f'{s}: {sum(p.scene.source == s for p in plan)}' for s in counts)}); {rendered} frames "
          f"in {seconds:.1f} s" + (f" ({1000 * seconds / rendered:.1f} ms/frame)" if rendered else ""))
    return meta
