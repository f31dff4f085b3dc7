"""A SuperTuxKart track's scene.xml as surfaces and sky: the track mesh and every object it places (static
objects, animated objects, library nodes, LOD instances), textures resolved through the materials files, merged
per texture; the sky-box or sky colour. Frame and transforms: nvs.data.render.stk.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from nvs.data.render.scene import Part
from nvs.data.render.spm import read_spm
from nvs.data.render.stk import MIRROR, STK_DIR, StkError, node_transform, xml_floats

# Materials that are effects, not surfaces: glows and light cones (additive), water distortion (displace),
# and anything the game itself hides.
_SKIP_SHADERS = {"additive", "displace"}


# --- textures and materials -------------------------------------------------------------------------------------

@dataclass
class _Textures:
    """Texture lookup by file name (model folder, track folder, then STK_DIR/textures recursively), cached."""

    track_dir: Path
    index: dict[str, Path] = field(default_factory=dict)
    cache: dict[Path, Image.Image | None] = field(default_factory=dict)
    shaders: dict[str, dict] = field(default_factory=dict)

    def __post_init__(self):
        for p in sorted((STK_DIR / "textures").rglob("*")):
            if p.suffix.lower() in (".png", ".jpg", ".jpeg"):
                self.index.setdefault(p.name, p)
        for mx in [STK_DIR / "textures" / "materials.xml", self.track_dir / "materials.xml"]:
            self._read_materials(mx)

    def _read_materials(self, path: Path) -> None:
        if path.is_file():
            for m in ET.parse(path).getroot().iter("material"):
                if m.get("name"):
                    self.shaders[m.get("name")] = dict(m.attrib)

    def add_materials(self, folder: Path) -> None:
        self._read_materials(folder / "materials.xml")

    def hidden(self, name: str) -> bool:
        m = self.shaders.get(name, {})
        return (m.get("shader") in _SKIP_SHADERS or m.get("ignore", "N").upper() == "Y"
                or "invisible" in name.lower())

    def image(self, name: str, model_dir: Path) -> Image.Image | None:
        name = Path(name).name
        for cand in (model_dir / name, self.track_dir / name, self.index.get(name)):
            if cand is not None and cand.is_file():
                if cand not in self.cache:
                    try:
                        with Image.open(cand) as im:
                            self.cache[cand] = im.convert("RGBA")
                    except OSError:
                        self.cache[cand] = None
                return self.cache[cand]
        return None


# --- scene ------------------------------------------------------------------------------------------------------

@dataclass
class _Loader:
    textures: _Textures
    parts: list[Part] = field(default_factory=list)
    meshes: dict[Path, list] = field(default_factory=dict)
    lod: dict[str, tuple[float, str, Path]] = field(default_factory=dict)
    missing: set[str] = field(default_factory=set)
    depth: int = 0

    def place(self, model_path: Path, T: np.ndarray) -> None:
        """Add one model's buffers transformed by T (game frame), mirrored."""
        if not model_path.is_file():
            self.missing.add(str(model_path.relative_to(STK_DIR)) if STK_DIR in model_path.parents
                             else str(model_path))
            return
        if model_path not in self.meshes:
            self.meshes[model_path] = read_spm(model_path)
        A = MIRROR @ T[:3, :3]
        b = MIRROR @ T[:3, 3]
        for buf in self.meshes[model_path]:
            if len(buf.faces) == 0 or (buf.texture and self.textures.hidden(buf.texture)):
                continue
            img = self.textures.image(buf.texture, model_path.parent) if buf.texture else None
            uvs = None
            if img is not None and buf.uvs is not None:
                uvs = buf.uvs.copy()
                uvs[:, 1] = 1.0 - uvs[:, 1]  # Irrlicht's uv origin is the top-left; pyrender's the bottom-left
            colour = np.ones(4)
            if img is None:
                # Untextured: the vertex colours' mean (STK bakes light and colour into vertex colours).
                colour[:3] = buf.colors.mean(axis=0)
            self.parts.append(Part(buf.positions @ A.T + b, buf.faces, uvs, img if uvs is not None else None,
                                   colour))

    def walk(self, root: ET.Element, folder: Path, T_parent: np.ndarray, where: str) -> None:
        """Place every model element under `root` (a scene or library node file) with T_parent applied."""
        self.depth += 1
        if self.depth > 8:
            raise StkError(f"{where}: library nodes nested more than 8 deep")
        for group in root.iter("lod"):
            for g in group.iter("group"):
                for so in g.iter("static-object"):
                    if so.get("model"):
                        dist = float(so.get("lod_distance", "1e9"))
                        best = self.lod.get(g.get("name", ""))
                        if best is None or dist < best[0]:
                            self.lod[g.get("name", "")] = (dist, so.get("model"), folder)
        templates = {id(so) for group in root.iter("lod") for so in group.iter("static-object")}
        for el in root.iter():
            tag = el.tag
            if tag not in ("track", "static-object", "object", "library") or id(el) in templates:
                continue
            if el.get("interaction") == "physics-only":
                continue
            label = f"{where}: <{tag} {el.get('id') or el.get('model') or el.get('name') or ''}>"
            if tag == "library":
                name = el.get("name", "")
                if not name or name.startswith("gfx_"):
                    continue  # effects (fireworks, sparks) have no surfaces worth rendering
                lib = STK_DIR / "library" / name
                if not (lib / "node.xml").is_file():
                    self.missing.add(f"library/{name}/node.xml")
                    continue
                self.textures.add_materials(lib)
                self.walk(ET.parse(lib / "node.xml").getroot(), lib, T_parent @ node_transform(el, label),
                          f"library/{name}/node.xml")
                continue
            if tag == "object" and el.get("type") not in ("animation", "movable"):
                continue
            T = T_parent @ node_transform(el, label)
            if el.get("lod_instance", "").lower() == "true":
                best = self.lod.get(el.get("lod_group", ""))
                if best is None:
                    self.missing.add(f"lod group {el.get('lod_group')!r}")
                    continue
                self.place(best[2] / best[1], T)
            elif el.get("model"):
                self.place(folder / el.get("model"), T)
        self.depth -= 1


def load_scene(d: Path) -> tuple[list[Part], list[str]]:
    """The track's surfaces as parts in the mirrored (right-handed, y up) frame, and what could not be found."""
    scene = d / "scene.xml"
    try:
        root = ET.parse(scene).getroot()
    except ET.ParseError as err:
        raise StkError(f"{scene}: {err}") from None
    loader = _Loader(_Textures(d))
    loader.walk(root, d, np.eye(4), f"tracks/{d.name}/scene.xml")
    if not loader.parts:
        raise StkError(f"{scene}: no visible surfaces")
    return merge_parts(loader.parts), sorted(loader.missing)


def merge_parts(parts: list[Part]) -> list[Part]:
    """One part per texture image (and per untextured colour): thousands of placed objects become a few hundred
    draw calls, which is what the software rasteriser's time per frame depends on."""
    groups: dict[tuple, list[Part]] = {}
    for p in parts:
        key = ("tex", id(p.image)) if p.image is not None else ("col", *np.round(p.color, 2))
        groups.setdefault(key, []).append(p)
    out = []
    for group in groups.values():
        offsets = np.cumsum([0] + [len(p.positions) for p in group[:-1]])
        pos = np.concatenate([p.positions for p in group])
        faces = np.concatenate([p.faces + o for p, o in zip(group, offsets)])
        uvs = np.concatenate([p.uvs for p in group]) if group[0].image is not None else None
        out.append(Part(pos, faces, uvs, group[0].image, group[0].color))
    return out


# --- sky --------------------------------------------------------------------------------------------------------

def sky_function(d: Path, textures: _Textures | None = None):
    """dirs (...,3) in the mirrored frame -> RGB (...,3) float 0..255 from the track's sky-box (cube faces
    'top bottom east west south north' = +y -y +x -x -z +z of the game frame, approximate orientation) or
    sky-color."""
    root = ET.parse(d / "scene.xml").getroot()
    box = root.find("sky-box")
    textures = textures or _Textures(d)
    if box is not None and box.get("texture"):
        names = box.get("texture").split()
        faces = [textures.image(n, d) for n in names]
        if len(names) == 6 and all(f is not None for f in faces):
            arrays = [np.asarray(f.convert("RGB").resize((256, 256)), dtype=np.float32) for f in faces]

            def cube(dirs: np.ndarray) -> np.ndarray:
                g = dirs @ MIRROR  # back to the game frame
                x, y, z = g[..., 0], g[..., 1], g[..., 2]
                ax, ay, az = np.abs(x), np.abs(y), np.abs(z)
                out = np.zeros(dirs.shape[:-1] + (3,), dtype=np.float32)
                choices = [
                    ((ay >= ax) & (ay >= az) & (y > 0), 0, x, z, ay),
                    ((ay >= ax) & (ay >= az) & (y <= 0), 1, x, -z, ay),
                    ((ax > ay) & (ax >= az) & (x > 0), 2, -z, -y, ax),
                    ((ax > ay) & (ax >= az) & (x <= 0), 3, z, -y, ax),
                    ((az > ax) & (az > ay) & (z <= 0), 4, x, -y, az),
                    ((az > ax) & (az > ay) & (z > 0), 5, -x, -y, az),
                ]
                for mask, face, u, v, m in choices:
                    if mask.any():
                        uu = ((u[mask] / m[mask] + 1) / 2 * 255).clip(0, 255).astype(np.int64)
                        vv = ((v[mask] / m[mask] + 1) / 2 * 255).clip(0, 255).astype(np.int64)
                        out[mask] = arrays[face][vv, uu]
                return out

            return cube
    colour = np.array([130.0, 170.0, 220.0], dtype=np.float32)
    sc = root.find("sky-color")
    if sc is not None and sc.get("rgb"):
        colour = xml_floats(sc.get("rgb"), 3, f"{d / 'scene.xml'} sky-color").astype(np.float32)
    return lambda dirs: np.broadcast_to(colour, dirs.shape[:-1] + (3,)).copy()
