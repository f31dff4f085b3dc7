"""The real 3-D models the renderer uses, found in the installed Debian packages (see scripts/install_assets.sh).

Every source loads into `Part`s in one canonical model frame: y up, the model's front facing +z, any scale.
"""

from __future__ import annotations

import re
import tempfile
import zipfile
from pathlib import Path
from typing import Callable

import numpy as np

from nvs.data.render import flightgear, more_cars, stk_objects, ufoai
from nvs.data.render.scene import Part
from nvs.data.render.sources import (DEFAULT_ASSETS, ModelSource, ac3d_parts, read_texture, slug,  # noqa: F401
                                     trimesh_parts)

SH3D_DIR = Path("/usr/share/sweethome3d/furniture")
# Sweet Home 3D's own default catalog (package sweethome3d, extracted by scripts/install_object_assets.sh): a path in
# the asset folder (nvs.data.render.sources.asset_dir)
SH3D_JAR = Path("sweethome3d") / "usr/share/sweethome3d/sweethome3d.jar"
SH3D_DEFAULT_CATALOG = "com/eteks/sweethome3d/io/DefaultFurnitureCatalog.properties"
TORCS_DIR = Path("/usr/share/games/torcs")
TRIGGER_ZIP = Path("/usr/share/games/trigger-rally/data.zip")
INSTALL_HINT = "install the asset packages with scripts/install_assets.sh"

# ShapeNet's chair class holds chairs, armchairs, stools and lounge chairs; sofas and benches are other classes.
_SEAT = re.compile(r"chair|stool|\bseat\b", re.I)
_NOT_SEAT = re.compile(r"wheelchair", re.I)
# ShapeNet's car class: cars, SUVs, vans; not trucks, buses, toys.
_NOT_CAR = re.compile(r"truck|bus\b|model", re.I)


# --- Sweet Home 3D catalogs -------------------------------------------------------------------------------------

def _properties(z: zipfile.ZipFile, name: str = "PluginFurnitureCatalog.properties") -> dict[str, str]:
    props = {}
    for line in z.read(name).decode("latin-1").splitlines():
        line = line.strip()
        if line and not line.startswith("#") and "=" in line:
            k, v = line.split("=", 1)
            props[k.strip()] = v.strip()
    return props


def _sh3d_loader(catalog: Path, model_path: str, rotation: np.ndarray) -> Callable[[], list[Part]]:
    def load() -> list[Part]:
        folder = model_path.lstrip("/").rsplit("/", 1)[0] + "/"
        with zipfile.ZipFile(catalog) as z, tempfile.TemporaryDirectory(prefix="nvs-sh3d-") as tmp:
            for member in z.namelist():
                if member.startswith(folder) and not member.endswith("/"):
                    z.extract(member, tmp)
            parts = trimesh_parts(Path(tmp) / model_path.lstrip("/"))
            for p in parts:
                if p.image is not None:
                    p.image.load()  # read the texture before the temp dir goes away
        # SH3D's modelRotation turns the file's axes into SH3D's (y up, front towards +z): v' = M v.
        return [Part(p.positions @ rotation.T, p.faces, p.uvs, p.image, p.color) for p in parts]

    return load


def copyright_files(assets: Path = DEFAULT_ASSETS) -> dict[str, Path]:
    """package -> its copyright file: the installed Debian packages' and those extracted in the asset folder."""
    files = {p: Path(f"/usr/share/doc/{p}/copyright")
             for p in ("sweethome3d-furniture", "torcs-data", "trigger-rally-data")}
    files.update({"sweethome3d": Path(assets) / "sweethome3d" / "usr/share/doc/sweethome3d/copyright",
                  flightgear.PACKAGE: flightgear.copyright_file(assets), ufoai.PACKAGE: ufoai.copyright_file(assets),
                  stk_objects.PACKAGE: stk_objects.COPYRIGHT, **more_cars.copyright_files(assets)})
    return files


def sh3d_models(kind: str, assets: Path = DEFAULT_ASSETS) -> list[ModelSource]:
    """Seats ('chairs') or cars ('cars') of the Sweet Home 3D furniture catalogs (and of its default catalog,
    when extracted in the asset folder)."""
    out = []
    catalogs = [(c, "sweethome3d-furniture", "PluginFurnitureCatalog.properties")
                for c in sorted(SH3D_DIR.glob("*.sh3f"))]
    jar = Path(assets) / SH3D_JAR
    if jar.is_file():
        catalogs.append((jar, "sweethome3d", SH3D_DEFAULT_CATALOG))
    for catalog, package, props_name in catalogs:
        with zipfile.ZipFile(catalog) as z:
            props = _properties(z, props_name)
        default_licence = "GPL-2+ (sweethome3d copyright)" if package == "sweethome3d" else "see copyright"
        licence = props.get("license", default_licence)
        ids = sorted({int(k.split("#")[1]) for k in props if k.startswith("name#")})
        for i in ids:
            name, cat = props.get(f"name#{i}", ""), props.get(f"category#{i}", "")
            tags = props.get(f"tags#{i}", "")
            if kind == "chairs":
                ok = bool(_SEAT.search(name)) and not _NOT_SEAT.search(name) and cat != "Vehicles"
            else:
                ok = (cat == "Vehicles" and re.search(r"\bcar\b", f"{name}, {tags}", re.I) is not None
                      and not _NOT_CAR.search(name))
            if not ok:
                continue
            model = props[f"model#{i}"]
            rot = props.get(f"modelRotation#{i}")
            R = np.array([float(v) for v in rot.split()]).reshape(3, 3) if rot else np.eye(3)
            # Plugin catalogs hold one folder per model; the default catalog keeps all models in one folder.
            folder = Path(model).stem if package == "sweethome3d" else model.lstrip("/").split("/")[-2]
            mid = slug("sh3d", catalog.stem, folder)
            creator = props.get(f"creator#{i}", "")
            out.append(ModelSource(mid, name, package, licence,
                                   f"'{name}' by {creator}, {catalog.name}", _sh3d_loader(catalog, model, R)))
    if len({m.id for m in out}) != len(out):
        raise RuntimeError("duplicated Sweet Home 3D model ids")
    return out


# --- TORCS cars (AC3D) ------------------------------------------------------------------------------------------

# TORCS car files are y up with the car's front towards +x: rotate +x to +z (x' = -z, z' = x).
_TORCS_TO_CANON = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])


def _torcs_attnum(xml: str, section: str, name: str) -> float:
    block = re.search(r'<section name="' + re.escape(section) + r'">(.*?)</section>', xml, re.S)
    if block is None:
        raise ValueError(f"no section {section!r}")
    m = re.search(r'<attnum name="' + re.escape(name) + r'"[^>]*val="([^"]+)"', block.group(1))
    if m is None:
        raise ValueError(f"no {name!r} in section {section!r}")
    return float(m.group(1))


def _cylinder(radius: float, width: float, centre: np.ndarray, grey: float) -> Part:
    """A closed cylinder along z (AC3D's lateral axis), as an untextured part."""
    import trimesh

    c = trimesh.creation.cylinder(radius=radius, height=width, sections=24)
    return Part(np.asarray(c.vertices) + centre, np.asarray(c.faces), None, None, np.array([grey, grey, grey, 1.0]))


def torcs_wheels(xml: str) -> list[Part]:
    """Tyres and hubs from the car's physics description (TORCS attaches wheel models at run time).

    TORCS' car frame is x forward, y left, z up; its AC3D files are x forward, y up, z right (= -y).
    """
    parts = []
    for axle, side in (("Front Axle", "Front Right Wheel"), ("Front Axle", "Front Left Wheel"),
                       ("Rear Axle", "Rear Right Wheel"), ("Rear Axle", "Rear Left Wheel")):
        x = _torcs_attnum(xml, axle, "xpos")
        y = _torcs_attnum(xml, side, "ypos")
        rim = _torcs_attnum(xml, side, "rim diameter") * 0.0254
        width = _torcs_attnum(xml, side, "tire width") / 1000.0
        ratio = _torcs_attnum(xml, side, "tire height-width ratio")
        radius = rim / 2 + width * ratio
        centre = np.array([x, radius, -y])  # the body's y = 0 is the ground
        parts.append(_cylinder(radius, width, centre, 0.06))
        parts.append(_cylinder(rim / 2 * 0.9, width + 0.01, centre, 0.55))
    return parts


def torcs_models() -> list[ModelSource]:
    out = []
    for d in sorted((TORCS_DIR / "cars").iterdir()) if (TORCS_DIR / "cars").is_dir() else []:
        acc = d / f"{d.name}.acc"
        if not acc.is_file():
            continue

        def load(acc=acc, d=d) -> list[Part]:
            parts = ac3d_parts(acc, [d, TORCS_DIR / "data" / "textures"],
                               keep=lambda o: not o.name.lower().startswith("shadow"))
            parts += torcs_wheels((d / f"{d.name}.xml").read_text(errors="replace"))
            return [Part(p.positions @ _TORCS_TO_CANON.T, p.faces, p.uvs, p.image, p.color) for p in parts]

        out.append(ModelSource(slug("torcs", d.name), d.name, "torcs-data", "GPL-2+ / Free Art License (torcs-data)",
                               f"TORCS car '{d.name}' (cars/{d.name}/readme.txt)", load))
    return out


# --- Trigger Rally cars (OBJ + wheels) --------------------------------------------------------------------------

# Trigger vehicle files are z up with the front towards +y: (x, y, z) -> (-x, z, y).
_TRIGGER_TO_CANON = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])


def _attr_vec(xml: str, tag_attr: str) -> list[np.ndarray]:
    return [np.array([float(v) for v in m.split(",")]) for m in re.findall(tag_attr + r'="([^"]+)"', xml)]


def _trigger_loader(name: str) -> Callable[[], list[Part]]:
    def load() -> list[Part]:
        with zipfile.ZipFile(TRIGGER_ZIP) as z, tempfile.TemporaryDirectory(prefix="nvs-trigger-") as tmp:
            folder = f"vehicles/{name}/"
            for member in z.namelist():
                if member.startswith(folder) and not member.endswith("/"):
                    z.extract(member, tmp)
            xml = (Path(tmp) / folder / f"{name}.vehicle").read_text()
            body = trimesh_parts(Path(tmp) / folder / f"{name}.obj")
            wheel_obj = re.search(r'wheelmodel="([^"]+)"', xml).group(1)
            wheel = trimesh_parts(Path(tmp) / folder / wheel_obj)
            for p in body + wheel:
                if p.image is not None:
                    p.image.load()
        body_scale = float(re.search(r'<part[^>]*scale="([^"]+)"', xml, re.S).group(1))
        wheel_scale = float(re.search(r'wheelscale="([^"]+)"', xml).group(1))
        parts = list(body)
        # Wheels: positions in metres in the body frame; the wheel model is scaled by radius * wheelscale.
        wheel_xml = re.findall(r"<wheel\b[^>]*>", xml)
        for w in wheel_xml:
            pos = np.array([float(v) for v in re.search(r'pos="([^"]+)"', w).group(1).split(",")])
            radius = float(re.search(r'radius="([^"]+)"', w).group(1))
            s = radius * wheel_scale / body_scale
            flip = np.diag([-1.0, 1.0, -1.0]) if pos[0] < 0 else np.eye(3)  # mirror side: turn about z
            for p in wheel:
                parts.append(Part((p.positions * s) @ flip.T + pos / body_scale, p.faces, p.uvs, p.image, p.color))
        return [Part(p.positions @ _TRIGGER_TO_CANON.T, p.faces, p.uvs, p.image, p.color) for p in parts]

    return load


def trigger_models() -> list[ModelSource]:
    if not TRIGGER_ZIP.is_file():
        return []
    with zipfile.ZipFile(TRIGGER_ZIP) as z:
        names = sorted({n.split("/")[1] for n in z.namelist()
                        if n.startswith("vehicles/") and n.endswith(".vehicle")})
    return [ModelSource(slug("trigger", n), n, "trigger-rally-data", "GPL-2+ (trigger-rally-data)",
                        f"Trigger Rally vehicle '{n}' (data.zip)", _trigger_loader(n)) for n in names]


def category_models(category: str, assets: Path = DEFAULT_ASSETS) -> list[ModelSource]:
    """All candidate models of 'chairs' or 'cars' whose packages are present, sorted by id.

    FlightGear, UFO:AI, OpenCity, PGDrive and assimp's models are there only after scripts/install_object_assets.sh
    has extracted them into the asset folder ``assets`` (nvs.data.render.sources.asset_dir), SuperTuxKart's after
    scripts/install_drive_assets.sh (the full sets).
    """
    if category == "chairs":
        models = sh3d_models("chairs", assets)
    elif category == "cars":
        models = sh3d_models("cars", assets) + torcs_models() + trigger_models() + more_cars.more_cars(assets)
    else:
        raise ValueError(f"unknown object category {category!r}")
    models += (flightgear.flightgear_models(category, assets) + ufoai.ufoai_models(category, assets)
               + stk_objects.stk_models(category))
    return sorted(models, key=lambda m: m.id)
