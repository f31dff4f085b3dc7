"""Reader for SuperTuxKart's binary `.spm` meshes (static 'SPMN' and skinned 'SPMA'; the skinned bind pose).

Layout (little endian), as STK 1.x writes it::

    b"SP"  u8 (version << 3 | kind)   kind 0 = space-partitioned (unused, rejected), 1 = skinned, 2 = static
    u8 flags                          bit 0 normals, bit 1 vertex colours, bit 2 tangents
    f32[6] bounding box
    u16 n_materials, then per material: u8 len + texture 1 name, u8 len + texture 2 name (may be empty)
    u16 n_meshes, then per mesh: u16 n_buffers, then per buffer:
        u32 n_vertices (<= 65535), u32 n_indices, u16 material
        per vertex: f32[3] position; u32 packed normal (flag); vertex colour (flag): u8 marker, and unless the
        marker is 128 (white) u8 r, g, b; when the material has texture 1: f16[2] uv, f16[2] uv2 (texture 2),
        u32 tangent (flag); skinned: i16[4] joints + f16[4] weights
        indices: u16 when n_vertices > 255 else u8 (triangle list)
    skinned files then carry armature/animation data, which is not read.

Coordinates are the game's (Irrlicht: left-handed, y up); uvs have their origin at the image's top-left.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np


class SpmError(ValueError):
    """A malformed .spm file; the message names the file."""


@dataclass
class SpmBuffer:
    """One material's triangles: positions (N,3) float64, faces (M,3) int64, uvs (N,2) or None (top-left
    origin), colors (N,3) float in [0,1] (vertex colours, white without them), texture names."""

    positions: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None
    colors: np.ndarray
    texture: str
    texture2: str


class _Reader:
    def __init__(self, data: bytes, path: Path):
        self.data, self.pos, self.path = data, 0, path

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise SpmError(f"{self.path}: truncated at byte {self.pos} (wanted {n} more of {len(self.data)})")
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def unpack(self, fmt: str):
        return struct.unpack("<" + fmt, self.take(struct.calcsize("<" + fmt)))

    def name(self) -> str:
        (n,) = self.unpack("B")
        return self.take(n).decode("utf-8", errors="replace")


def _vertex_dtype(normals: bool, uv1: bool, uv2: bool, tangents: bool, skinned: bool,
                  colour: bool, position: bool = True) -> np.dtype:
    fields = [("pos", "<f4", (3,))] if position else []
    if normals:
        fields.append(("normal", "<u4"))
    if colour:
        fields.append(("rgb", "u1", (3,)))
    if uv1:
        fields.append(("uv", "<f2", (2,)))
        if uv2:
            fields.append(("uv2", "<f2", (2,)))
        if tangents:
            fields.append(("tangent", "<u4"))
    if skinned:
        fields.append(("joints", "<i2", (4,)))
        fields.append(("weights", "<f2", (4,)))
    return np.dtype(fields)


def _read_vertices(r: _Reader, n: int, normals: bool, colours: bool, uv1: bool, uv2: bool, tangents: bool,
                   skinned: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    if not colours:
        dt = _vertex_dtype(normals, uv1, uv2, tangents, skinned, False)
        v = np.frombuffer(r.take(n * dt.itemsize), dtype=dt)
        return v["pos"].astype(np.float64), (v["uv"].astype(np.float64) if uv1 else None), np.ones((n, 3))
    # Vertex colours make the record length vary (a white marker has no rgb bytes): read one by one.
    before = _vertex_dtype(normals, False, False, False, False, False)
    after = _vertex_dtype(False, uv1, uv2, tangents, skinned, False, position=False)
    pos, uvs, cols = np.empty((n, 3)), (np.empty((n, 2)) if uv1 else None), np.ones((n, 3))
    for i in range(n):
        pos[i] = np.frombuffer(r.take(before.itemsize), dtype=before)["pos"][0]
        (marker,) = r.unpack("B")
        if marker != 128:
            cols[i] = np.frombuffer(r.take(3), dtype=np.uint8) / 255.0
        if after.names:
            rec = np.frombuffer(r.take(after.itemsize), dtype=after)
            if uv1:
                uvs[i] = rec["uv"][0]
    return pos, uvs, cols


def read_spm(path: str | Path) -> list[SpmBuffer]:
    """All triangle buffers of an .spm file (positions in the game's left-handed frame)."""
    path = Path(path)
    r = _Reader(path.read_bytes(), path)
    if r.take(2) != b"SP":
        raise SpmError(f"{path}: not an .spm file (magic is not 'SP')")
    (byte,) = r.unpack("B")
    version, kind = byte >> 3, byte & ~0x08
    if version != 1:
        raise SpmError(f"{path}: unsupported .spm version {version} (this reader knows version 1)")
    if kind not in (1, 2):
        raise SpmError(f"{path}: unsupported .spm kind {kind} (space-partitioned meshes are not supported)")
    skinned = kind == 1
    (flags,) = r.unpack("B")
    normals, colours, tangents = bool(flags & 1), bool(flags >> 1 & 1), bool(flags >> 2 & 1)
    r.take(24)  # bounding box
    (n_mat,) = r.unpack("H")
    materials = [(r.name(), r.name()) for _ in range(n_mat)]
    (n_mesh,) = r.unpack("H")
    out = []
    for _ in range(n_mesh):
        (n_buf,) = r.unpack("H")
        for _ in range(n_buf):
            nv, ni, mat = r.unpack("IIH")
            if nv > 65535:
                raise SpmError(f"{path}: buffer with {nv} vertices (the format allows 65535)")
            if mat >= len(materials):
                raise SpmError(f"{path}: material index {mat} out of range ({len(materials)} materials)")
            if ni % 3:
                raise SpmError(f"{path}: {ni} indices is not a triangle list")
            tex1, tex2 = materials[mat]
            pos, uvs, cols = _read_vertices(r, nv, normals, colours, bool(tex1), bool(tex2), tangents, skinned)
            idx = np.frombuffer(r.take(ni * (2 if nv > 255 else 1)), dtype="<u2" if nv > 255 else "u1")
            faces = idx.astype(np.int64).reshape(-1, 3)
            if len(faces) and faces.max() >= nv:
                raise SpmError(f"{path}: index {faces.max()} out of range ({nv} vertices)")
            if uvs is not None and not np.isfinite(uvs).all():
                uvs = np.nan_to_num(uvs, nan=0.0, posinf=0.0, neginf=0.0)
            out.append(SpmBuffer(pos, faces, uvs, cols, tex1, tex2))
    if not skinned and r.pos != len(r.data):
        raise SpmError(f"{path}: {len(r.data) - r.pos} bytes left after the last mesh (layout not understood)")
    return out
