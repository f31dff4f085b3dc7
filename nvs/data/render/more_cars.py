"""Cars of three small packages, fetched by scripts/install_object_assets.sh under data/assets/<package>/ (the
package's own paths kept):

  opencity-data      Debian, GPL-2+: OpenCity's road vehicles, AC3D with PNG textures (low-poly, 30-70 triangles).
  pgdrive            PyPI wheel 0.1.2, Apache-2.0: PGDrive's vehicles as glTF 2.0 (read by trimesh). Files exported
                     from Sketchfab carry their own author, licence and source in `asset.extras`; those go into
                     the credit line and licence.
  assimp-testmodels  Debian, BSD-3-clause; the model's readme: "FREE for use however you like": Psionic's jeep,
                     MS3D converted to OBJ by `assimp export` at install time.

Every file is y up with the front towards +z (glTF's convention; the others read off view (0, 0)). Not cars: the
OpenCity fire engine and truck, PGDrive's light commercial truck; left out: PGDrive's Lada (CC-BY-NC-4.0).
"""

from __future__ import annotations

import json
from pathlib import Path

from nvs.data.render.orient import face_front
from nvs.data.render.scene import Part
from nvs.data.render.sources import DEFAULT_ASSETS, ModelSource, ac3d_parts, slug, trimesh_parts

OPENCITY = "usr/share/games/opencity/graphism/vehicle"
PGDRIVE = "pgdrive/assets/models"
# package -> (licence of the package, its copyright / licence file, {model name: file under the package root})
PACKAGES = {
    "opencity-data": ("GPL-2+ (opencity-data)", "usr/share/doc/opencity-data/copyright",
                      {n: f"{OPENCITY}/{d}/{d}.ac" for n, d in (("buick", "buickS"), ("clio", "clior"),
                                                                ("police", "police"), ("r8", "renault8-sport"))}),
    "pgdrive": ("Apache-2.0 (pgdrive)", "pgdrive-0.1.2.dist-info/LICENSE.txt",
                {"ferra": f"{PGDRIVE}/ferra/scene.gltf", "130": f"{PGDRIVE}/new/130/scene.gltf",
                 "beetle": f"{PGDRIVE}/new/beetle/scene.gltf"}),
    "assimp-testmodels": ("BSD-3-clause (assimp-testmodels); readme: free for use however you like",
                          "usr/share/doc/assimp-testmodels/copyright",
                          {"jeep": "usr/share/assimp/models/MS3D/jeep1.obj"}),
}
SLUG = {"opencity-data": "oc", "pgdrive": "pgdrive", "assimp-testmodels": "assimp"}
NOTE = {"jeep": "jeep1.ms3d converted by assimp; 'Jeep designed, modelled and skinned by Psionic' (jeep1.readme.txt)"}


def copyright_files(assets: Path) -> dict[str, Path]:
    """package -> its copyright / licence file in the asset folder ``assets``."""
    return {pkg: Path(assets) / pkg / rel for pkg, (_, rel, _) in PACKAGES.items()}


def _load(path: Path) -> list[Part]:
    parts = ac3d_parts(path, [path.parent]) if path.suffix == ".ac" else trimesh_parts(path)
    return face_front(parts, str(path), "+z")


def _gltf_credit(path: Path) -> tuple[str, str] | None:
    """(licence, credit) from a glTF file's asset.extras (Sketchfab exports), or None when it names no licence."""
    extras = json.loads(path.read_text(encoding="utf-8")).get("asset", {}).get("extras", {})
    if not extras.get("license"):
        return None
    return extras["license"], f"'{extras.get('title', path.parent.name)}' by {extras.get('author', '?')} " \
                              f"({extras.get('source', 'no source given')})"


def more_cars(assets: Path = DEFAULT_ASSETS) -> list[ModelSource]:
    """The cars of these packages that are present in the asset folder (none when not extracted)."""
    out = []
    for pkg, (licence, _, files) in PACKAGES.items():
        for name, rel in files.items():
            path = Path(assets) / pkg / rel
            if not path.is_file():
                continue
            lic, credit = licence, f"{pkg} model {rel}" + (f" ({NOTE[name]})" if name in NOTE else "")
            own = _gltf_credit(path) if path.suffix == ".gltf" else None
            if own is not None:
                lic, credit = f"{own[0]} (the model's own licence)", f"{credit}: {own[1]}"
            elif path.suffix == ".gltf":
                credit += " (the file names no author; the package's licence applies)"
            out.append(ModelSource(slug(SLUG[pkg], name), name, pkg, lic, credit,
                                   lambda path=path: _load(path)))
    return out
