"""UFO: Alien Invasion map objects (Debian `ufoai-data`, GPL-2+ code / CC and GPL art, see its copyright): cars
and chairs as MD2 with PNG/JPG skins, extracted by scripts/install_object_assets.sh from base/0models.pk3 under
data/assets/ufoai-data/ (package paths).

MD2 axes are x forward, y left, z up, but the length of the UFO:AI cars lies along x or y depending on the
model; the front is a per-model fact read off the renders (FRONT below). Wheels are separate MD2s placed in the
body's frame (`*_t.md2`, `*t.md2`) and are added to their body.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nvs.data.render.md2 import read_md2
from nvs.data.render.orient import face_front
from nvs.data.render.scene import Part
from nvs.data.render.sources import DEFAULT_ASSETS, ModelSource, dep5_licence, read_texture, slug

PACKAGE = "ufoai-data"

# (body md2, wheel md2s) relative to models/objects/. Not cars: the box trailer, the optional roof racks, the
# armoured 'puma' (a turret gun).
CARS = {
    "cars/4x4/4x4": ["cars/4x4/4x4_t"],
    "cars/buggy/buggy": [],
    "cars/car2/car2a": [],
    "cars/car2/car2b": [],
    "cars/car3/car3": [],
    "cars/car4/car": [],
    "cars/carcrashed/car1": [],
    "cars/carcrashed/car2": [],
    "cars/golf/car1": ["cars/golf/car1t"],
    "cars/hummer/hummer": [],
    "cars/jeep/jeep": [],
    "cars/landy/landy": [],
    "cars/policecar/policecar": [],
    "cars/transporter/transporter": [],
    "cars/van/van1": ["cars/van/van1t"],
    "cars/van2/van2": [],
    "cars/van3/van": [],
}
# Single seats only: bank1 and bench are benches, stleer a two-seat sofa; japan/stoel is a legless floor chair
# (cushion and backrest). Not the alien pilot seat (alien/seat, a cockpit pod).
CHAIRS = {f"furniture/chairs/{n}": [] for n in ("chair", "chair1", "chair2", "chair3")}
CHAIRS["japan/stoel"] = []

# MD2 (x forward, y left, z up) -> y up: (x, y, z) -> (y, z, x), a proper rotation; MD2's +x becomes +z.
_MD2_TO_YUP = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
# Front in the y-up axes where it is not the default (cars: the + end of the length axis; chairs: MD2's +x);
# read off view (0, 0).
FRONT_DEFAULT = {"x": "+x", "z": "+z"}
FRONT = {
    "cars/4x4/4x4": "-x", "cars/buggy/buggy": "-x", "cars/car2/car2a": "-z", "cars/car2/car2b": "-z",
    "cars/golf/car1": "-x", "cars/jeep/jeep": "-x", "cars/landy/landy": "-x", "japan/stoel": "+x",
}


def md2_part(path: Path) -> Part:
    """One MD2 (frame 0, first skin that exists beside it) -> a y-up part."""
    mesh = read_md2(path)
    image = None
    for skin in mesh.skins:
        # UFO:AI names skins '.name' (beside the model) or by a path under base/; the extension is left out.
        stem = Path(skin.lstrip("."))
        for cand in (path.parent / f"{stem.name}.png", path.parent / f"{stem.name}.jpg"):
            image = read_texture(cand.name, [cand.parent])
            if image is not None:
                break
        if image is not None:
            break
    if image is None:
        raise ValueError(f"{path}: none of the skins {mesh.skins} found beside it")
    return Part(mesh.positions @ _MD2_TO_YUP.T, mesh.faces, mesh.uvs, image, np.ones(4))


def root(assets: Path) -> Path:
    """Where the package is extracted in the asset folder ``assets`` (nvs.data.render.sources.asset_dir)."""
    return Path(assets) / PACKAGE


def copyright_file(assets: Path) -> Path:
    return root(assets) / "usr/share/doc/ufoai-data/copyright"


def _loader(body: str, wheels: list[str], objects: Path):
    def load() -> list[Part]:
        parts = [md2_part(objects / f"{m}.md2") for m in [body, *wheels]]
        return face_front(parts, body, FRONT.get(body, FRONT_DEFAULT if body.startswith("cars/") else "+z"))

    return load


def ufoai_models(kind: str, assets: Path = DEFAULT_ASSETS) -> list[ModelSource]:
    """The UFO:AI cars ('cars') or chairs ('chairs') present in the asset folder (none when not extracted)."""
    table = CARS if kind == "cars" else CHAIRS
    objects = root(assets) / "usr/share/games/ufoai/base/models/objects"
    notice = copyright_file(assets)
    text = notice.read_text(errors="replace") if notice.is_file() else ""
    out = []
    for body, wheels in table.items():
        if not (objects / f"{body}.md2").is_file():
            continue
        name = body.split("/", 1)[1]
        who, lic = dep5_licence(text, f"base/models/objects/{body}.md2")
        out.append(ModelSource(slug("ufoai", name), name, PACKAGE, f"{lic} (ufoai-data)",
                               f"UFO:AI map object models/objects/{body}.md2 (base/0models.pk3), (c) {who}",
                               _loader(body, wheels, objects)))
    return out
