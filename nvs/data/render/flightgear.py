"""FlightGear scenery models (Debian `flightgear-data-base`, GPL-2+): road vehicles and seats as AC3D with PNG
textures, extracted by scripts/install_object_assets.sh under data/assets/flightgear-data-base/ (package paths).

FlightGear's AC3D files are y up; the vehicles' length lies along x or z depending on the author, and the front
direction is a per-model fact read off the renders (FRONT below).
"""

from __future__ import annotations

from pathlib import Path

from nvs.data.render.orient import face_front
from nvs.data.render.scene import Part
from nvs.data.render.sources import DEFAULT_ASSETS, ModelSource, ac3d_parts, slug

PACKAGE = "flightgear-data-base"
LICENCE = "GPL-2+ (flightgear-data-base)"

# Road cars, SUVs, pickups and vans (ShapeNet's car class), by folder; not buses, trucks or airport machinery.
CARS = {
    "Transport": (
        "VWJetta_S1 VWPassat_S1 bmw3silver camaroblack camaroblue camarored camarowhite dodgeramblue dodgeramgreen "
        "dodgeramred dodgeramwhite dodgeramyellow gr_paramedic1 gr_policar1 hatchback_black hatchback_blue "
        "hatchback_green hatchback_red hatchback_silver honda1 hondacrvblack hondacrvred hondacrvsilver "
        "hummerh2-ba it_policecar1 mazda_wagontaxi minibusblue1 minibusgreen1 minibuswhite1 pickupblue pickupred1 "
        "pickupwhite pickupwhite1 pickupyelwhite tcamryblack tcamryblue tcamryred tcamrysilver van-blue-muc "
        "van_blue_dirty van_red van_silver vantransitwhite1 vanwhite vanwhite1 vanyellow1 volvoxc90s1 voyager1 "
        "vwgolfsilver").split(),
    "Airport/Vehicle": (
        "BFD_Sprinter_308 ELW_Sprinter_215 RTW_Sprinter_515 RTW_Sprinter_515_BL EDDI-FollowMe EDDT-FollowMe "
        "airvehpickupgreen1 airvehpickupwhite1 gr_van-followme hatchback_red_follow_me rover-aegean van-aegean "
        "fourgon-ba traffic-ba").split(),
    "Military": ["humvee-pickup-odrab-low-poly"],
}
# Chairs (ShapeNet's chair class): none. The package's seats are a park bench (Misc/parkbench1), a group of
# recliners under parasols (Misc/recliners_parasols) and a two-seat hooded beach chair (Misc/strandkorb).
CHAIRS: dict[str, list[str]] = {}

# Front direction in the file's y-up axes where it is not the default (the +/- end of the length axis that
# FRONT_DEFAULT names); read off view (0, 0) of the contact sheets.
FRONT_DEFAULT = {"x": "-x", "z": "-z"}  # x: FlightGear's convention (x towards the tail); z: most authors'
FRONT = {"it_policecar1": "+z", "vwgolfsilver": "+z"}


def root(assets: Path) -> Path:
    """Where the package is extracted in the asset folder ``assets`` (nvs.data.render.sources.asset_dir)."""
    return Path(assets) / PACKAGE


def copyright_file(assets: Path) -> Path:
    return root(assets) / "usr/share/doc/flightgear-data-base/copyright"


def _models(assets: Path) -> Path:
    return root(assets) / "usr/share/games/flightgear/Scenery/Models"


def _loader(path: Path, name: str, models: Path):
    def load() -> list[Part]:
        parts = ac3d_parts(path, [path.parent, path.parent.parent / "Textures", models / "Textures"])
        return face_front(parts, str(path), FRONT.get(name, FRONT_DEFAULT))

    return load


def flightgear_models(kind: str, assets: Path = DEFAULT_ASSETS) -> list[ModelSource]:
    """The FlightGear cars ('cars') or chairs ('chairs') present in the asset folder (none when not extracted)."""
    table = CARS if kind == "cars" else CHAIRS
    models = _models(assets)
    out = []
    for folder, names in table.items():
        for name in names:
            path = models / folder / f"{name}.ac"
            if not path.is_file():
                continue
            out.append(ModelSource(slug("fg", name), name, PACKAGE, LICENCE,
                                   f"FlightGear scenery model Scenery/Models/{folder}/{name}.ac "
                                   "(authors: flightgear-data-base AUTHORS)", _loader(path, name, models)))
    return out
