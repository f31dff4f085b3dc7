"""Quake II MD2 reader (the UFO:AI object models): the first animation frame as positions, triangles, uvs, skins.

Layout (little endian): a 68-byte header of 17 int32 (magic 'IDP2', version 8, skin width/height, frame size,
counts of skins/vertices/uvs/triangles/GL commands/frames, then the offsets of skins/uvs/triangles/frames/GL
commands/end); skins are 64-byte names; uvs are int16 (s, t) in skin pixels; a triangle is int16 vertex[3] and
int16 uv[3]; a frame is float32 scale[3], translate[3], a 16-byte name, then per vertex uint8 x, y, z, normal.
A vertex is byte * scale + translate. Model axes: x forward, y left, z up.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAGIC = b"IDP2"
VERSION = 8
_HEADER = struct.Struct("<4s16i")


@dataclass
class Md2Mesh:
    """Triangle soup of frame 0: positions (T*3,3) float64, faces (T,3), uvs (T*3,2) in [0,1] (v up), skins."""

    positions: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    skins: list[str]


def read_md2(path: str | Path) -> Md2Mesh:
    """Parse an .md2 file; raises ValueError naming the file on anything malformed."""
    data = Path(path).read_bytes()
    if len(data) < _HEADER.size:
        raise ValueError(f"{path}: too short for an MD2 header ({len(data)} bytes)")
    (magic, version, skin_w, skin_h, frame_size, n_skins, n_verts, n_st, n_tris, _n_gl, n_frames,
     ofs_skins, ofs_st, ofs_tris, ofs_frames, _ofs_gl, ofs_end) = _HEADER.unpack_from(data)
    if magic != MAGIC or version != VERSION:
        raise ValueError(f"{path}: not an MD2 v8 file (magic {magic!r}, version {version})")
    if ofs_end > len(data) or n_frames < 1 or n_verts < 1 or n_tris < 1 or skin_w <= 0 or skin_h <= 0:
        raise ValueError(f"{path}: inconsistent MD2 header (end {ofs_end} of {len(data)} bytes, "
                         f"{n_frames} frames, {n_verts} vertices, {n_tris} triangles, skin {skin_w}x{skin_h})")
    if frame_size != 40 + 4 * n_verts or ofs_frames + frame_size > len(data):
        raise ValueError(f"{path}: frame size {frame_size} does not match {n_verts} vertices")
    skins = [data[ofs_skins + 64 * i: ofs_skins + 64 * (i + 1)].split(b"\0", 1)[0].decode("latin-1")
             for i in range(n_skins)]
    st = np.frombuffer(data, dtype="<i2", count=2 * n_st, offset=ofs_st).reshape(n_st, 2).astype(np.float64)
    tris = np.frombuffer(data, dtype="<i2", count=6 * n_tris, offset=ofs_tris).reshape(n_tris, 6).astype(np.int64)
    scale = np.frombuffer(data, dtype="<f4", count=3, offset=ofs_frames).astype(np.float64)
    translate = np.frombuffer(data, dtype="<f4", count=3, offset=ofs_frames + 12).astype(np.float64)
    raw = np.frombuffer(data, dtype=np.uint8, count=4 * n_verts, offset=ofs_frames + 40).reshape(n_verts, 4)
    verts = raw[:, :3].astype(np.float64) * scale + translate
    vi, ti = tris[:, :3], tris[:, 3:]
    if vi.min() < 0 or vi.max() >= n_verts or ti.min() < 0 or ti.max() >= n_st:
        raise ValueError(f"{path}: triangle indices out of range")
    # Per-corner soup: MD2 indexes positions and uvs separately.
    positions = verts[vi.reshape(-1)]
    uvs = st[ti.reshape(-1)] / np.array([skin_w, skin_h])
    uvs[:, 1] = 1.0 - uvs[:, 1]  # MD2's t grows downwards in the skin image; GL's v grows upwards
    return Md2Mesh(positions, np.arange(3 * n_tris).reshape(n_tris, 3), uvs, skins)
