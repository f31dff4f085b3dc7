"""SuperTuxKart library objects (Debian `supertuxkart-data`, per-file licences in its copyright, mostly CC-BY-SA):
the road cars and chairs of `data/library/`, as STK's .spm meshes. The data is extracted by
scripts/install_drive_assets.sh (the drive renderer's tracks come from the same package).

.spm coordinates are left-handed with y up (Irrlicht): z is mirrored to make them right-handed; uvs have their
origin at the image's top-left and are flipped to OpenGL's bottom-left. The front is a per-model fact read off
the renders (FRONT below).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nvs.data.render.orient import face_front
from nvs.data.render.scene import Part
from nvs.data.render.sources import ModelSource, dep5_licence, read_texture, slug
from nvs.data.render.spm import read_spm

PACKAGE = "supertuxkart-data"
DATA = Path("/usr/share/games/supertuxkart/data")
LIBRARY = DATA / "library"
COPYRIGHT = Path("/usr/share/doc/supertuxkart-data/copyright")

# library node -> its .spm mesh (one car or chair each). Not cars: the karts, the combine harvester, the steam
# locomotive, the car-traffic node's three boxes (stand-ins); not chairs: the bench (stklib_bench_a) and the love
# alcove (a two-seat bench).
CARS = {
    "stklib_oldCar_a": "stklib_oldCar_a/stklib_oldCar_a_main.spm",
    "stklib_tvVan_a": "stklib_tvVan_a/stklib_tvVan_a_main.spm",
}
CHAIRS = {
    "stklib_armchair_a": "stklib_armchair_a/stklib_armchair_a_main.spm",
    "stklib_classchair_a": "stklib_classchair_a/stklib_classchair_a_main.spm",
}
# Front in the (mirrored, right-handed) y-up axes where it is not the default; read off view (0, 0).
FRONT_DEFAULT = {"x": "+x", "z": "+z"}
FRONT = {"stklib_tvVan_a": "-x", "stklib_armchair_a": "+x", "stklib_classchair_a": "-z"}
_MIRROR_Z = np.array([1.0, 1.0, -1.0])


def spm_parts(path: Path) -> list[Part]:
    """.spm -> right-handed y-up parts with their textures (looked up beside the mesh, then in data/textures)."""
    parts = []
    for buf in read_spm(path):
        image = read_texture(buf.texture, [path.parent, DATA / "textures"]) if buf.texture else None
        uvs = None
        if image is not None and buf.uvs is not None:
            uvs = buf.uvs.copy()
            uvs[:, 1] = 1.0 - uvs[:, 1]
        else:
            image = None
        color = np.ones(4) if image is not None else np.array([*np.clip(buf.colors.mean(0), 0, 1), 1.0])
        parts.append(Part(buf.positions * _MIRROR_Z, buf.faces, uvs, image, color))
    if not parts:
        raise ValueError(f"{path}: no triangles")
    return parts


def _loader(key: str, path: Path, car: bool):
    def load() -> list[Part]:
        return face_front(spm_parts(path), str(path), FRONT.get(key, FRONT_DEFAULT if car else "+z"))

    return load


def stk_models(kind: str) -> list[ModelSource]:
    """SuperTuxKart library cars ('cars') or chairs ('chairs'); none when the package data is not there."""
    table = CARS if kind == "cars" else CHAIRS
    if not LIBRARY.is_dir():
        return []
    text = COPYRIGHT.read_text(errors="replace") if COPYRIGHT.is_file() else ""
    out = []
    for key, rel in table.items():
        path = LIBRARY / rel
        if not path.is_file():
            continue
        who, lic = dep5_licence(text, f"data/library/{rel}")
        out.append(ModelSource(slug("stk", key.replace("stklib_", "")), key, PACKAGE, f"{lic} (supertuxkart-data)",
                               f"SuperTuxKart library object data/library/{rel}, (c) {who}",
                               _loader(key, path, kind == "cars")))
    return out
