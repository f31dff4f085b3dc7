"""Render driving sequences along TORCS road tracks into the KITTI-odometry format read by nvs.data.kitti.

The camera (OpenCV, fx = fy = 160 at 256^2) rides 1.65 m above the centre of the right lane, 1 m between frames,
looking along the smoothed centre line (pitch follows the road, roll 0). The centre line comes from the mesh:
road-surface objects `TKMN*` are triangle strips whose vertex pairs are road cross-sections. Sky pixels get the
track's background.png panorama (cylindrical, approximate) and depth 0 (no data).
"""

from __future__ import annotations

import random
import time
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from nvs.atomic import write_json, write_text
from nvs.data.render.ac3d import AcModel, read_ac3d
from nvs.data.render.assets import COPYRIGHT, TORCS_DIR, ac3d_parts
from nvs.data.render.output import write_credits, write_depth, write_png
from nvs.data.render.scene import Renderer, scaled_K, to_pyrender

K256 = np.array([[160.0, 0.0, 128.0], [0.0, 160.0, 128.0], [0.0, 0.0, 1.0]])
CAMERA_HEIGHT = 1.65
STEP = 1.0
MAX_GAP = 2.0  # m: strip ends further apart than this are not chained (joined strips share their ends)
SMOOTH = 4  # m: half-window of the moving average applied to the centre line
MAX_PAIR_OFFSET = 7
UP = np.array([0.0, 1.0, 0.0])  # AC3D tracks are y up, in metres
SKY_ELEVATION = (-10.0, 60.0)  # degrees spanned by background.png from bottom to top row (approximate)


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


def sky_colour(panorama: np.ndarray, T_world_cam: np.ndarray, K: np.ndarray, size: int) -> np.ndarray:
    """Panorama colour (size,size,3) float of every pixel's viewing ray (cylindrical mapping)."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    d = rays @ T_world_cam[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    azimuth = np.arctan2(d[..., 0], d[..., 2])
    elevation = np.degrees(np.arcsin(np.clip(d[..., 1], -1, 1)))
    H, W = panorama.shape[:2]
    col = ((azimuth / (2 * np.pi)) % 1.0 * W).astype(np.int64) % W
    lo, hi = SKY_ELEVATION
    row = np.clip(((hi - elevation) / (hi - lo) * (H - 1)).round().astype(np.int64), 0, H - 1)
    return panorama[row, col].astype(np.float32)


def _split_sequences(n: int, seed: int) -> dict[str, list[int]]:
    order = list(range(n))
    random.Random(seed).shuffle(order)
    n_test = max(1, round(0.2 * n)) if n >= 3 else 0
    n_val = max(1, round(0.1 * n)) if n >= 3 else 0
    return {"test": sorted(order[:n_test]), "val": sorted(order[n_test:n_test + n_val]),
            "train": sorted(order[n_test + n_val:])}


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


def track_order(seed: int) -> list[str]:
    """Road tracks in a seeded order; sequence s drives the s-th usable one (cycling when there are more)."""
    tracks = [t.name for t in road_tracks()]
    if not tracks:
        raise FileNotFoundError("no TORCS road tracks found; install the asset packages with "
                                "scripts/install_assets.sh")
    random.Random(seed).shuffle(tracks)
    return tracks


def render_drive(out: Path, size: int = 256, seed: int = 0, sequences: int = 10, frames: int = 200,
                 supersample: int = 3, progress: bool = True) -> dict:
    """Render `sequences` x `frames` frames into `out` (KITTI-odometry format plus depth/, meta.json, CREDITS)."""
    from tqdm import tqdm

    out = Path(out)
    K = scaled_K(K256, size)
    Kss = scaled_K(K256, size * supersample)
    order = track_order(seed)
    rng_start = random.Random(seed + 2)
    renderer = Renderer(size * supersample, Kss, znear=0.3, zfar=1500.0, bg_color=(0.0, 0.0, 0.0), lit=False)
    poses_lines: dict[int, list[str]] = {}
    tracks_used, failed = [], []
    rendered = 0
    t0 = time.perf_counter()
    bar = tqdm(total=sequences * frames, desc=f"render drive {size}px", unit="frame", disable=not progress)
    queue = [n for _ in range(sequences) for n in order]  # cycle through the tracks in the seeded order
    bad: set[str] = set()
    try:
        for seq in range(sequences):
            while True:  # a track that fails to load or is too short is reported and the next one taken
                if not queue:
                    raise RuntimeError(f"no usable track left for sequence {seq}")
                name = queue.pop(0)
                if name in bad:
                    continue
                d = TORCS_DIR / "tracks" / "road" / name
                try:
                    path, widths = resample(*centre_line(read_ac3d(d / f"{name}.acc")), STEP)
                    if len(path) < frames + 10:
                        raise ValueError(f"centre line {len(path)} m is shorter than {frames + 10} m")
                    break
                except Exception as err:
                    bad.add(name)
                    failed.append(f"{name}: {err.__class__.__name__}: {err}")
                    tqdm.write(f"skipped track {name}: {err}")
            start = int(rng_start.random() * (len(path) - frames - 5)) + 2
            poses = camera_poses(path, widths, start, frames)
            T0_inv = np.linalg.inv(poses[0])
            poses_lines[seq] = [pose_line(frame_id(seq, i), T0_inv @ T) for i, T in enumerate(poses)]
            tracks_used.append({"seq": seq, "track": name, "start_m": start * STEP, "frames": frames})
            ids = [frame_id(seq, i) for i in range(frames)]
            if all((out / "images" / f"{i}.png").is_file() and (out / "depth" / f"{i}.npy").is_file() for i in ids):
                bar.update(frames)
                continue
            renderer.set_mesh(to_pyrender(ac3d_parts(d / f"{name}.acc", [d, TORCS_DIR / "data" / "textures"])))
            with Image.open(d / "background.png") as im:
                panorama = np.asarray(im.convert("RGB"))
            S = size * supersample
            c = supersample // 2
            for fid, T in zip(ids, poses):
                rgb, depth = renderer.render(T)
                sky = depth <= 0
                img = rgb.astype(np.float32)
                img[sky] = sky_colour(panorama, T, Kss, S)[sky]
                img = img.reshape(size, supersample, size, supersample, 3).mean(axis=(1, 3))
                write_depth(out / "depth" / f"{fid}.npy", depth[c::supersample, c::supersample])
                write_png(out / "images" / f"{fid}.png", np.clip(np.rint(img), 0, 255).astype(np.uint8))
                rendered += 1
                bar.update(1)
    finally:
        bar.close()
        renderer.close()
    seconds = time.perf_counter() - t0
    write_text(out / "poses.txt", "".join(line for s in sorted(poses_lines) for line in poses_lines[s]))
    split = _split_sequences(sequences, seed)
    rng = random.Random(seed + 1)
    train = [p for s in split["train"] for p in _pairs_all(s, frames)]
    val = [p for s in split["val"] for p in _pairs_sampled(s, frames, rng)]
    test = [p for s in split["test"] for p in _pairs_sampled(s, frames, rng)]
    for fname, pairs in (("pairs_train.txt", train), ("pairs_val.txt", val), ("eval_kitti.txt", test)):
        write_text(out / fname, "".join(f"{a} {b}\n" for a, b in pairs))
    names = sorted({t["track"] for t in tracks_used})
    write_credits(out, [f"track {n}: TORCS road track (tracks/road/{n}/readme.txt); package torcs-data; "
                        "licence: GPL-2+ / Free Art License" for n in names], ["torcs-data"], COPYRIGHT)
    meta = {
        "format": "scenes",
        "size": size,
        "K": K.tolist(),
        "seed": seed,
        "sequences": tracks_used,
        "split": {k: [f"{s:02d}" for s in v] for k, v in split.items()},
        "camera": {"height_m": CAMERA_HEIGHT, "step_m": STEP, "lane": "right lane centre (road width / 4)",
                   "poses": "camera-to-world of the OpenCV camera, relative to each sequence's first frame"},
        "depth": "depth/{id}.npy float32 z-depth in metres, 0 = sky / no data",
        "lighting": "unlit (texture colour); sky = background.png panorama, depth 0",
        "supersample": supersample,
        "licence": "TORCS tracks: GPL-2+ / Free Art License (torcs-data); see CREDITS.txt",
        "failed_tracks": failed,
        "render_seconds": round(seconds, 2),
        "frames_rendered": rendered,
    }
    write_json(out / "meta.json", meta)
    print(f"drive: {sequences} sequences x {frames} frames from {len(names)} tracks; {rendered} frames in "
          f"{seconds:.1f} s" + (f" ({1000 * seconds / rendered:.1f} ms/frame)" if rendered else ""))
    return meta
