"""AC3D (.ac / TORCS .acc) reader: objects with world-space vertices, texture names and surfaces.

TORCS extends AC3D with several texture layers (`texture "x" base|tiled|skids|shad`), per-vertex normals after
the positions, several uv pairs per surface reference and surface type 4 (triangle strip). Only the first
texture layer and the first uv pair are used: that is the colour map.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class Surface:
    """One AC3D surface: type (0 polygon, 1/2 line, 4 strip), material index, vertex refs (n,), uvs (n,2)."""

    kind: int
    mat: int
    refs: np.ndarray
    uvs: np.ndarray


@dataclass
class AcObject:
    """A poly object: name, first texture (None if untextured), world vertices (N,3), surfaces."""

    name: str
    texture: str | None
    vertices: np.ndarray
    surfaces: list[Surface] = field(default_factory=list)
    path: tuple[str, ...] = ()


@dataclass
class AcModel:
    """All poly objects of a file plus the material colours (M,3) in [0,1]."""

    objects: list[AcObject]
    material_rgb: np.ndarray


class _Lines:
    def __init__(self, text: str):
        self.lines = text.splitlines()
        self.i = 0

    def at_end(self) -> bool:
        while self.i < len(self.lines) and not self.lines[self.i].strip():
            self.i += 1
        return self.i >= len(self.lines)

    def next(self) -> str:
        while self.i < len(self.lines):
            s = self.lines[self.i].strip()
            self.i += 1
            if s:
                return s
        raise ValueError("unexpected end of file")


def _quoted(s: str) -> str:
    s = s.strip()
    return s[1:-1] if s.startswith('"') and s.endswith('"') else s


def _read_object(lines: _Lines, header: str, rot: np.ndarray, loc: np.ndarray, path: tuple[str, ...],
                 out: list[AcObject]) -> None:
    name, texture = "", None
    verts = np.zeros((0, 3))
    surfaces: list[Surface] = []
    R, t = np.eye(3), np.zeros(3)
    have_texture = False
    while True:
        s = lines.next()
        key, _, rest = s.partition(" ")
        if key == "name":
            name = _quoted(rest)
        elif key == "texture":
            # The first texture line is the colour map; TORCS' further layers (tiled/skids/shad) are ignored.
            if not have_texture:
                tex = rest.split()[0] if rest else ""
                tex = _quoted(tex)
                texture = None if tex in ("", "empty_texture_no_mapping") else tex
                have_texture = True
        elif key == "rot":
            R = np.array([float(v) for v in rest.split()], dtype=np.float64).reshape(3, 3)
        elif key == "loc":
            t = np.array([float(v) for v in rest.split()], dtype=np.float64)
        elif key == "numvert":
            n = int(rest)
            verts = np.array([[float(v) for v in lines.next().split()[:3]] for _ in range(n)], dtype=np.float64)
        elif key == "numsurf":
            for _ in range(int(rest)):
                surfaces.append(_read_surface(lines))
        elif key == "kids":
            # Child coordinates are relative to this object: world = R_parent (R v + t) + t_parent.
            R_w, t_w = rot @ R, rot @ t + loc
            full = path + (name,)
            if len(verts):
                out.append(AcObject(name, texture, verts @ R_w.T + t_w, surfaces, path))
            for _ in range(int(rest)):
                if lines.at_end():  # some TORCS tracks declare more kids than they hold
                    return
                child = lines.next()
                if not child.startswith("OBJECT"):
                    raise ValueError(f"expected OBJECT, got {child!r}")
                _read_object(lines, child, R_w, t_w, full, out)
            return
        # data/url/crease/texrep/texoff/subdiv/hidden/locked/folded: not needed for rendering.
        elif key == "data":
            n = int(rest)
            got = 0
            while got < n:  # data blocks may span lines
                got += len(lines.lines[lines.i]) + 1
                lines.i += 1


def _read_surface(lines: _Lines) -> Surface:
    head = lines.next()
    if not head.startswith("SURF"):
        raise ValueError(f"expected SURF, got {head!r}")
    flags = int(head.split()[1], 0)
    mat = 0
    while True:
        s = lines.next()
        if s.startswith("mat"):
            mat = int(s.split()[1])
        elif s.startswith("refs"):
            n = int(s.split()[1])
            rows = [lines.next().split() for _ in range(n)]
            refs = np.array([int(r[0]) for r in rows], dtype=np.int64)
            uvs = np.array([[float(r[1]), float(r[2])] if len(r) >= 3 else [0.0, 0.0] for r in rows])
            return Surface(flags & 0xF, mat, refs, uvs.reshape(-1, 2))


def read_ac3d(path: str | Path) -> AcModel:
    """Parse an .ac/.acc file into world-space poly objects."""
    text = Path(path).read_text(errors="replace")
    lines = _Lines(text)
    if not lines.next().startswith("AC3D"):
        raise ValueError(f"{path}: not an AC3D file")
    mats, objects = [], []
    while lines.i < len(lines.lines):
        try:
            s = lines.next()
        except ValueError:
            break
        if s.startswith("MATERIAL"):
            parts = s.split()
            k = parts.index("rgb")
            mats.append([float(v) for v in parts[k + 1:k + 4]])
        elif s.startswith("OBJECT"):
            _read_object(lines, s, np.eye(3), np.zeros(3), (), objects)
    rgb = np.array(mats, dtype=np.float64).reshape(-1, 3) if mats else np.ones((1, 3))
    return AcModel(objects, rgb)


def triangles(surface: Surface) -> np.ndarray:
    """Corner indices (T,3) into surface.refs: polygons as fans, strips alternating; lines give none."""
    n = len(surface.refs)
    if surface.kind == 4:
        idx = [(i, i + 1, i + 2) if i % 2 == 0 else (i + 1, i, i + 2) for i in range(n - 2)]
    elif surface.kind == 0:
        idx = [(0, i, i + 1) for i in range(1, n - 1)]
    else:
        idx = []
    return np.array(idx, dtype=np.int64).reshape(-1, 3)
