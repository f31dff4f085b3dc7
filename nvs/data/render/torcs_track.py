"""TORCS road tracks (AC3D) as drive scenes: the track folders and the centre line read off the mesh.

Road-surface objects are named `TKMN*`; each is a triangle strip whose vertex pairs are road cross-sections
every 4-10 m. Their midpoints, chained end to end, give the centre line (summing the track XML's segments does
not close on tracks with spiral segments).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nvs.data.render.ac3d import AcModel
from nvs.data.render.assets import TORCS_DIR

MAX_GAP = 2.0  # m: strip ends further apart than this are not chained (joined strips share their ends)


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
