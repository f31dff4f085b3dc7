"""Planning a drive render: disjoint windows of the scenes' centre lines taken round-robin over sources, the split
by scene (a test scene is never trained on), and the frame pairs of each split."""

from __future__ import annotations

import random
from dataclasses import dataclass

import numpy as np

from nvs.data.render.drive_rig import STEP, resample
from nvs.data.render.drive_sources import SceneSource

WINDOW_GAP = 20.0  # m of centre line left between two sequences of one scene
MAX_PAIR_OFFSET = 7


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


def frame_id(seq: int, frame: int) -> str:
    return f"{seq:02d}_{frame:06d}"


def pairs_all(seq: int, frames: int) -> list[tuple[str, str]]:
    """Every ordered pair of distinct frames of a sequence at most MAX_PAIR_OFFSET apart (training)."""
    return [(frame_id(seq, i), frame_id(seq, j)) for i in range(frames) for j in range(frames)
            if i != j and abs(i - j) <= MAX_PAIR_OFFSET]


def pairs_sampled(seq: int, frames: int, rng: random.Random) -> list[tuple[str, str]]:
    """One pair per source frame, the target drawn within MAX_PAIR_OFFSET (validation, test)."""
    out = []
    for i in range(frames):
        j = i + rng.choice([d for d in range(-MAX_PAIR_OFFSET, MAX_PAIR_OFFSET + 1)
                            if d != 0 and 0 <= i + d < frames])
        out.append((frame_id(seq, i), frame_id(seq, j)))
    return out
