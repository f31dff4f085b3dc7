"""What every object source shares: the ModelSource record, ids, the extracted-assets folder, AC3D and
trimesh-read files (OBJ, glTF) -> parts."""

from __future__ import annotations

import fnmatch
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

from nvs.core.errors import UserError
from nvs.data.render.ac3d import read_ac3d, triangles
from nvs.data.render.scene import Part

# Packages too large to install (flightgear-data-base, ufoai-data, ...) are extracted into one folder, their own paths
# kept, by scripts/install_object_assets.sh [DIR]. The render command finds it as assets=DIR, else $NVS_ASSETS, else
# data/assets under the working directory (the checkout when run from its root; an installed package has none).
DEFAULT_ASSETS = Path("data") / "assets"
ASSETS_ENV = "NVS_ASSETS"


def asset_dir(option: str | None = None, env: str | None = None) -> Path:
    """The folder of extracted asset packages: ``option`` (the command's assets=DIR), else ``env`` (the value of
    $NVS_ASSETS), else data/assets under the working directory. One that was asked for and is not a directory is a
    UserError; the default may be absent (the models of the installed Debian packages are rendered alone)."""
    for given, name in ((option, "assets"), (env, ASSETS_ENV)):
        if given:
            path = Path(given).expanduser()
            if not path.is_dir():
                raise UserError(f"{name}={given}: no such directory (extract the asset packages into it with "
                                f"scripts/install_object_assets.sh {given}, or leave {name} unset for data/assets)")
            return path.resolve()
    return DEFAULT_ASSETS.resolve()


@dataclass
class ModelSource:
    """A model to render: id (no '_'), display name, Debian package, licence/credit line, loader."""

    id: str
    name: str
    package: str
    licence: str
    credit: str
    load: Callable[[], list[Part]]


def slug(*words: str) -> str:
    s = "-".join(words).lower()
    return re.sub(r"[^a-z0-9]+", "-", s).strip("-")


def read_texture(name: str, dirs: list[Path]) -> Image.Image | None:
    """A texture by file name, looked up in dirs; SGI .rgb and PNG, with the other extension as a fallback."""
    stem = Path(name).stem
    for d in dirs:
        for cand in (name, f"{stem}.png", f"{stem}.rgb", f"{stem}.rgba"):
            p = d / cand
            if p.is_file():
                with Image.open(p) as im:
                    im.load()
                    return im.convert("RGBA")
    return None


def ac3d_parts(path: Path, texture_dirs: list[Path], keep=lambda obj: True) -> list[Part]:
    """AC3D file -> parts merged per texture (untextured objects per material colour)."""
    model = read_ac3d(path)
    images: dict[str, Image.Image | None] = {}
    groups: dict[tuple, list] = {}
    for obj in model.objects:
        if not keep(obj):
            continue
        for s in obj.surfaces:
            tri = triangles(s)
            if len(tri) == 0:
                continue
            if obj.texture and obj.texture not in images:
                images[obj.texture] = read_texture(obj.texture, texture_dirs)
            img = images.get(obj.texture) if obj.texture else None
            key = ("tex", obj.texture) if img is not None else ("mat", min(s.mat, len(model.material_rgb) - 1))
            corners = tri.reshape(-1)
            groups.setdefault(key, []).append((obj.vertices[s.refs[corners]], s.uvs[corners]))
    parts = []
    for key, chunks in groups.items():
        pos = np.concatenate([c[0] for c in chunks])
        uv = np.concatenate([c[1] for c in chunks])
        faces = np.arange(len(pos)).reshape(-1, 3)
        if key[0] == "tex":
            parts.append(Part(pos, faces, uv, images[key[1]], np.ones(4)))
        else:
            rgb = model.material_rgb[key[1]]
            parts.append(Part(pos, faces, None, None, np.array([*rgb, 1.0])))
    return parts


def trimesh_parts(obj_path: Path) -> list[Part]:
    """OBJ (+MTL, textures beside it) or glTF 2.0 -> parts, via trimesh, with scene transforms applied."""
    import trimesh

    scene = trimesh.load(obj_path, force="scene", process=False)
    parts = []
    for name in scene.graph.nodes_geometry:
        T, geom_name = scene.graph[name]
        g = scene.geometry[geom_name]
        if not isinstance(g, trimesh.Trimesh) or len(g.faces) == 0:
            continue
        pos = np.asarray(g.vertices, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
        uv, image, color = None, None, np.array([0.8, 0.8, 0.8, 1.0])
        vis = g.visual
        if vis.kind == "texture" or isinstance(vis, trimesh.visual.TextureVisuals):
            mat = vis.material
            if isinstance(mat, trimesh.visual.material.PBRMaterial):
                image = mat.baseColorTexture
                if mat.baseColorFactor is not None:
                    color = np.asarray(mat.baseColorFactor, dtype=np.float64) / 255.0
            else:
                image = getattr(mat, "image", None)
                color = np.asarray(mat.diffuse, dtype=np.float64) / 255.0
            if vis.uv is not None and len(vis.uv) == len(g.vertices):
                uv = np.asarray(vis.uv, dtype=np.float64)
            else:
                image = None
        elif vis.kind in ("face", "vertex"):
            color = np.asarray(vis.main_color, dtype=np.float64) / 255.0
        if image is not None:
            color = color.copy()
            color[:3] = np.maximum(color[:3], 1e-3)
            # MTL files often pair a texture with Kd = 0 or a dark Kd; SH3D shows the texture unmodulated.
            color[:3] = 1.0
        parts.append(Part(pos, np.asarray(g.faces, dtype=np.int64), uv, image, color))
    return parts


def dep5_licence(copyright_text: str, path: str) -> tuple[str, str]:
    """(copyright holders, licence) of `path` in a machine-readable Debian copyright file: the last Files
    paragraph with a matching pattern wins, as the format specifies; ('see copyright',) * 2 when none matches."""
    found = ("see copyright", "see copyright")
    field = r"^{}:(.*?)(?=^\S|\Z)"
    for para in re.split(r"\n[ \t]*\n", copyright_text):
        files = re.search(field.format("Files"), para, re.S | re.M)
        if files is None or not any(fnmatch.fnmatchcase(path, p) for p in files.group(1).split()):
            continue
        holders = re.search(field.format("Copyright"), para, re.S | re.M)
        licence = re.search(r"^License:[ \t]*(.+)$", para, re.M)
        found = (" ".join(holders.group(1).split()) if holders else "see copyright",
                 licence.group(1).strip() if licence else "see copyright")
    return found
