"""Render driving sequences through game scenes into the KITTI-odometry format read by nvs.data.kitti.

Sources (`sources=` option, comma-separated, `name:k` takes k sequences per turn; round-robin over sources,
then over each source's scenes):
  stk      SuperTuxKart race tracks (nvs.data.render.stk): town streets, temples, mansions, forests; the
           centre line is the driveline (quads.xml); scripts/install_drive_assets.sh extracts the data.
  torcs    TORCS road tracks (AC3D): the centre line comes from the mesh: road-surface objects `TKMN*` are
           triangle strips whose vertex pairs are road cross-sections.

The camera (OpenCV; `camera=kitti`: the paper's KITTI intrinsics f = 718.9, c = 128 at 256^2, a ~20 degree view;
`camera=wide`: f = 160, ~77 degrees) rides 1.65 m above the centre of the right lane, 1 m between frames,
looking along the smoothed centre line (pitch follows the road, roll 0). A scene's sequences are disjoint
windows of its centre line. Splits are by scene (a test scene is never trained on). Sky pixels get the scene's
sky (panorama, sky-box or colour) and depth 0 (no data).
"""

from __future__ import annotations

import json
import random
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from nvs.atomic import write_json, write_text
from nvs.data.render.ac3d import AcModel, read_ac3d
from nvs.data.render.assets import COPYRIGHT, TORCS_DIR, ac3d_parts
from nvs.data.render.output import write_credits, write_depth, write_png
from nvs.data.render.scene import Part, Renderer, scaled_K, to_pyrender

# fx = fy at 256^2 (principal point at the centre), per camera option.
CAMERAS = {"kitti": 718.9, "wide": 160.0}
CAMERA_HEIGHT = 1.65
STEP = 1.0
WINDOW_GAP = 20.0  # m of centre line left between two sequences of one scene
MAX_GAP = 2.0  # m: strip ends further apart than this are not chained (joined strips share their ends)
SMOOTH = 4  # m: half-window of the moving average applied to the centre line
MAX_PAIR_OFFSET = 7
UP = np.array([0.0, 1.0, 0.0])  # every scene is returned y up, in metres
SKY_ELEVATION = (-10.0, 60.0)  # degrees spanned by background.png from bottom to top row (approximate)
DEFAULT_SOURCES = "stk:2,torcs"
# Depth histogram written with every render (depth_stats.json): log-spaced bins in metres.
DEPTH_BINS = np.logspace(-2, 5, 7 * 50 + 1)


def camera_K(camera: str) -> np.ndarray:
    """K (3,3) at 256^2 of a camera option."""
    if camera not in CAMERAS:
        raise ValueError(f"unknown camera {camera!r}; known: {', '.join(CAMERAS)}")
    f = CAMERAS[camera]
    return np.array([[f, 0.0, 128.0], [0.0, f, 128.0], [0.0, 0.0, 1.0]])


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


# --- TORCS ------------------------------------------------------------------------------------------------------

def road_tracks() -> list[Path]:
    """Track folders (road category) that have an AC3D mesh, sorted by name."""
    base = TORCS_DIR / "tracks" / "road"
    return sorted(d for d in base.iterdir() if (d / f"{d.name}.acc").is_file()) if base.is_dir() else []


def _strips(model: AcModel) -> list[tuple[np.ndarray, np.ndarray]]:
    """(midpoints (n,3), widths (n,)) of every road-surface strip, in strip order."""
    out = []
    for obj in model.objects:
        if not obj.name.upper().startswith("TKMN"):
            continue
        for s in obj.surfaces:
            if s.kind != 4 or len(s.refs) < 4:
                continue
            n = len(s.refs) // 2 * 2
            a, b = obj.vertices[s.refs[0:n:2]], obj.vertices[s.refs[1:n:2]]
            out.append(((a + b) / 2, np.linalg.norm(a - b, axis=1)))
    return out


def centre_line(model: AcModel) -> tuple[np.ndarray, np.ndarray]:
    """The longest chain of road-surface strips: points (n,3) and road widths (n,)."""
    strips = _strips(model)
    if not strips:
        raise ValueError("no road-surface (TKMN) strips")
    remaining = list(range(len(strips)))
    chains = []
    while remaining:
        first = remaining.pop(0)
        pts, wid = [strips[first][0]], [strips[first][1]]
        grew = True
        while grew and remaining:
            grew = False
            end, start = pts[-1][-1], pts[0][0]
            best = None
            for k in remaining:
                p = strips[k][0]
                for where, anchor in (("end", end), ("start", start)):
                    for rev in (False, True):
                        q = p[::-1] if rev else p
                        d = np.linalg.norm((q[0] if where == "end" else q[-1]) - anchor)
                        if best is None or d < best[0]:
                            best = (d, k, where, rev)
            if best is not None and best[0] <= MAX_GAP:
                _, k, where, rev = best
                p, w = strips[k]
                p, w = (p[::-1], w[::-1]) if rev else (p, w)
                if where == "end":
                    pts.append(p), wid.append(w)
                else:
                    pts.insert(0, p), wid.insert(0, w)
                remaining.remove(k)
                grew = True
        chains.append((np.concatenate(pts), np.concatenate(wid)))
    pts, wid = max(chains, key=lambda c: np.linalg.norm(np.diff(c[0], axis=0), axis=1).sum())
    keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 0.05])
    return pts[keep], wid[keep]


def resample(pts: np.ndarray, wid: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every `step` metres of arc length, then a moving average over +-SMOOTH metres."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    t = np.arange(0.0, s[-1], step)
    p = np.stack([np.interp(t, s, pts[:, i]) for i in range(3)], axis=1)
    w = np.interp(t, s, wid)
    k = int(round(SMOOTH / step))
    kernel = np.ones(2 * k + 1) / (2 * k + 1)
    padded = np.pad(p, ((k, k), (0, 0)), mode="edge")
    p = np.stack([np.convolve(padded[:, i], kernel, mode="valid") for i in range(3)], axis=1)
    return p, w


def camera_poses(path: np.ndarray, widths: np.ndarray, start: int, frames: int) -> np.ndarray:
    """OpenCV camera-to-world (frames,4,4) along a resampled path from index `start` (1 m apart)."""
    poses = []
    for i in range(start, start + frames):
        fwd = path[min(i + 2, len(path) - 1)] - path[max(i - 2, 0)]
        z = fwd / np.linalg.norm(fwd)
        x = np.cross(z, UP)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        # Right-lane centre: a quarter of the road width right of the centre line (horizontal offset).
        right = x - np.dot(x, UP) * UP
        right /= np.linalg.norm(right)
        c = path[i] + widths[i] / 4 * right + CAMERA_HEIGHT * UP
        T = np.eye(4)
        T[:3, :3] = np.stack([x, y, z], axis=1)
        T[:3, 3] = c
        poses.append(T)
    return np.stack(poses)


def view_dirs(T_world_cam: np.ndarray, K: np.ndarray, size: int) -> np.ndarray:
    """World direction (size,size,3) of every pixel's viewing ray (unit length)."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    d = rays @ T_world_cam[:3, :3].T
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


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


def torcs_sources() -> list[SceneSource]:
    out = []
    for d in road_tracks():
        acc = d / f"{d.name}.acc"

        def runs(acc=acc):
            return [centre_line(read_ac3d(acc))]

        def load(d=d, acc=acc, runs=runs):
            parts = ac3d_parts(acc, [d, TORCS_DIR / "data" / "textures"])
            with Image.open(d / "background.png") as im:
                panorama = np.asarray(im.convert("RGB"))
            return DriveScene(parts, runs(), panorama_sky(panorama), [])

        out.append(SceneSource("torcs", d.name, runs, load, "torcs-data", "GPL-2+ / Free Art License",
                               f"TORCS road track {d.name} (tracks/road/{d.name}/readme.txt)"))
    return out


def stk_sources() -> list[SceneSource]:
    from nvs.data.render import stk

    out = []
    for d in stk.race_tracks():
        info = stk.track_info(d)

        def load(d=d):
            parts, missing = stk.load_scene(d)
            return DriveScene(parts, stk.driveline(d), stk.sky_function(d), missing)

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
        if name not in SOURCES:
            raise ValueError(f"unknown drive source {name!r}; known: {', '.join(SOURCES)}")
        found = SOURCES[name]()
        if not found:
            raise FileNotFoundError(f"no {name} scenes installed; run {INSTALL[name]}")
        out[name] = found
    if not out:
        raise ValueError("sources is empty")
    return out


@dataclass
class Planned:
    seq: int
    scene: SceneSource
    run: int
    start: int  # index into the resampled run (metres from its start)


def _windows(runs: list[tuple[np.ndarray, np.ndarray]], frames: int) -> list[tuple[int, int]]:
    """(run, start) of disjoint windows of `frames` m (+ WINDOW_GAP between them) along the resampled runs."""
    out = []
    need = int(frames * STEP) + 10
    for r, (pts, _) in enumerate(runs):
        length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()) if len(pts) > 1 else 0.0
        n = int((length + WINDOW_GAP) // (need + WINDOW_GAP))
        out += [(r, 2 + int(k * (need + WINDOW_GAP))) for k in range(n)]
    return out


def plan_sequences(sources: dict[str, list[SceneSource]], sequences: int, frames: int, seed: int,
                   failed: list[str], weights: dict[str, int] | None = None) -> list[Planned]:
    """Round-robin over sources, then over each source's scenes (seeded order), each turn taking the scene's
    next window. Scenes whose centre line cannot be read are reported in `failed` and skipped."""
    rng = random.Random(seed)
    queues = {}
    for src, scenes in sources.items():
        order = list(scenes)
        rng.shuffle(order)
        queues[src] = order
    windows: dict[tuple[str, str], list[tuple[int, int]]] = {}
    plan: list[Planned] = []
    cursor = {src: 0 for src in queues}
    turns = [src for src in queues for _ in range((weights or {}).get(src, 1))]
    while len(plan) < sequences and any(queues.values()):
        for src in turns:
            if len(plan) >= sequences:
                break
            while queues[src]:
                i = cursor[src] % len(queues[src])
                sc = queues[src][i]
                key = (src, sc.name)
                if key not in windows:
                    try:
                        win = _windows([resample(p, w, STEP) for p, w in sc.runs()], frames)
                    except Exception as err:  # a scene that cannot be read is named and skipped
                        win = []
                        failed.append(f"{src}/{sc.name}: {err.__class__.__name__}: {err}")
                    rng.shuffle(win)
                    windows[key] = win
                if not windows[key]:
                    queues[src].pop(i)
                    continue
                run, start = windows[key].pop()
                plan.append(Planned(len(plan), sc, run, start))
                cursor[src] = i + 1
                break
    if len(plan) < sequences:
        raise RuntimeError(f"the scenes hold only {len(plan)} windows of {frames} m; asked for {sequences} "
                           "sequences (fewer frames or more sources)")
    return plan


def split_scenes(plan: list[Planned], seed: int) -> dict[str, list[int]]:
    """Sequences by split, splitting SCENES (per source, seeded): ~20% test, ~10% val, the rest train."""
    by_source: dict[str, list[str]] = {}
    for p in plan:
        names = by_source.setdefault(p.scene.source, [])
        if p.scene.name not in names:
            names.append(p.scene.name)
    where: dict[tuple[str, str], str] = {}
    rng = random.Random(seed)
    total = len({(p.scene.source, p.scene.name) for p in plan})
    for src, names in by_source.items():
        names = sorted(names)
        rng.shuffle(names)
        n = len(names)
        n_test = max(1, round(0.2 * n)) if total >= 3 else 0
        n_val = max(1, round(0.1 * n)) if total >= 3 and n >= 3 else 0
        for k, name in enumerate(names):
            where[(src, name)] = "test" if k < n_test else "val" if k < n_test + n_val else "train"
    out = {"test": [], "val": [], "train": []}
    for p in plan:
        out[where[(p.scene.source, p.scene.name)]].append(p.seq)
    if total >= 3 and not out["train"]:  # few scenes: keep a training scene
        out["train"].append(out["test"].pop())
    return out


def depth_histogram(root: Path, ids: list[str]) -> np.ndarray:
    """Counts (len(DEPTH_BINS)+1,) of depth values over the frames: [0] = no data (<= 0), then per bin
    (values beyond the last edge land in the last bin)."""
    counts = np.zeros(len(DEPTH_BINS) + 1, dtype=np.int64)
    for fid in ids:
        d = np.load(root / "depth" / f"{fid}.npy").reshape(-1)
        counts[0] += int((d <= 0).sum())
        v = d[d > 0]
        idx = np.clip(np.searchsorted(DEPTH_BINS, v, side="right") - 1, 0, len(DEPTH_BINS) - 2)
        counts[1:len(DEPTH_BINS)] += np.bincount(idx, minlength=len(DEPTH_BINS) - 1)
    return counts


def representable_fraction(counts, min_depth_m: float, max_depth_m: float) -> float:
    """Fraction of valid depths (counts from depth_histogram) that are certainly inside (min, max) metres:
    only bins entirely inside count, so the answer errs low."""
    counts = np.asarray(counts)
    valid = counts[1:len(DEPTH_BINS)]
    lo, hi = DEPTH_BINS[:-1], DEPTH_BINS[1:]
    inside = (lo >= min_depth_m) & (hi <= max_depth_m)
    total = valid.sum()
    return float(valid[inside].sum() / total) if total else 0.0


def frame_id(seq: int, frame: int) -> str:
    return f"{seq:02d}_{frame:06d}"


def _pairs_all(seq: int, frames: int) -> list[tuple[str, str]]:
    return [(frame_id(seq, i), frame_id(seq, j)) for i in range(frames) for j in range(frames)
            if i != j and abs(i - j) <= MAX_PAIR_OFFSET]


def _pairs_sampled(seq: int, frames: int, rng: random.Random) -> list[tuple[str, str]]:
    out = []
    for i in range(frames):
        j = i + rng.choice([d for d in range(-MAX_PAIR_OFFSET, MAX_PAIR_OFFSET + 1)
                            if d != 0 and 0 <= i + d < frames])
        out.append((frame_id(seq, i), frame_id(seq, j)))
    return out


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
    train = [p for s in split["train"] for p in _pairs_all(s, frames)]
    val = [p for s in split["val"] for p in _pairs_sampled(s, frames, rng)]
    test = [p for s in split["test"] for p in _pairs_sampled(s, frames, rng)]
    for fname, pairs in (("pairs_train.txt", train), ("pairs_val.txt", val), ("eval_kitti.txt", test)):
        write_text(out / fname, "".join(f"{a} {b}\n" for a, b in pairs))
    used = {(p.scene.source, p.scene.name): p.scene for p in plan}
    packages = sorted({sc.package for sc in used.values()})
    copyright_files = dict(COPYRIGHT)
    from nvs.data.render.stk import STK_COPYRIGHT

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
                 "[bins_m[k], bins_m[k+1]); see nvs.data.render.drive.representable_fraction",
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
