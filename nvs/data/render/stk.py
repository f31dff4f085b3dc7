"""SuperTuxKart race tracks: the installed tracks, the game's frame and node transforms, the driveline. The surfaces
and the sky of a track's scene.xml are read by nvs.data.render.stk_scene.

Files (under STK_DIR, extracted by scripts/install_drive_assets.sh)::

    tracks/<name>/track.xml    name, designer; arena / soccer / cutscene / internal tracks are not race tracks
    tracks/<name>/quads.xml    driveline quads p0..p3 ('x y z' or 'i:j' = corner j of quad i), in driving order
    tracks/<name>/scene.xml    <track model=...> plus static-object / object / library placements (xyz, hpr
                               in degrees, scale), <lod> groups instanced by lod_instance, <sky-box>/<sky-color>
    library/<name>/node.xml    a placed library node: the same elements, relative to the node
    textures/                  shared textures (looked up by file name, after the model's and track's folders)

The game's frame is Irrlicht's: left-handed, y up, units ~ metres. Everything here is returned mirrored
(z -> -z) into a right-handed frame, so images are not mirrored. Irrlicht's rotation from hpr = (x, y, z)
degrees is Rz(z) Ry(y) Rx(x) on column vectors, and a node's transform is translate * rotate * scale.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

STK_DIR = Path("/usr/share/games/supertuxkart/data")
STK_COPYRIGHT = Path("/usr/share/doc/supertuxkart-data/copyright")
MIRROR = np.diag([1.0, 1.0, -1.0])
_NOT_RACE = ("arena", "soccer", "cutscene", "internal", "ctf")


class StkError(ValueError):
    """A track file STK's layout does not explain; the message names the file."""


def xml_floats(text: str | None, n: int, where: str, default=None) -> np.ndarray:
    """(n,) floats of an attribute ('x y z' or 'x,y,z'); `default` when the attribute is absent."""
    if text is None:
        if default is None:
            raise StkError(f"{where}: missing attribute")
        return np.asarray(default, dtype=np.float64)
    vals = [float(v) for v in text.replace(",", " ").split()]
    if len(vals) != n:
        raise StkError(f"{where}: expected {n} numbers, got {text!r}")
    return np.asarray(vals, dtype=np.float64)


def hpr_matrix(hpr_deg: np.ndarray) -> np.ndarray:
    """Irrlicht's rotation (3,3) of an 'hpr' attribute (x, y, z degrees): Rz Ry Rx on column vectors."""
    x, y, z = np.radians(hpr_deg)
    cx, sx, cy, sy, cz, sz = np.cos(x), np.sin(x), np.cos(y), np.sin(y), np.cos(z), np.sin(z)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def node_transform(el: ET.Element, where: str) -> np.ndarray:
    """(4,4) translate * rotate * scale of an element's xyz / hpr / scale attributes (game frame)."""
    T = np.eye(4)
    R = hpr_matrix(xml_floats(el.get("hpr"), 3, f"{where} hpr", (0, 0, 0)))
    S = np.diag(xml_floats(el.get("scale"), 3, f"{where} scale", (1, 1, 1)))
    T[:3, :3] = R @ S
    T[:3, 3] = xml_floats(el.get("xyz"), 3, f"{where} xyz", (0, 0, 0))
    return T


def is_race_track(d: Path) -> bool:
    xml = d / "track.xml"
    if not (xml.is_file() and (d / "quads.xml").is_file() and (d / "scene.xml").is_file()):
        return False
    root = ET.parse(xml).getroot()
    return not any(root.get(k, "N").strip().upper() == "Y" for k in _NOT_RACE)


def race_tracks() -> list[Path]:
    """Folders of the installed race tracks, sorted by name (empty when STK's data is not installed)."""
    base = STK_DIR / "tracks"
    return sorted(d for d in base.iterdir() if is_race_track(d)) if base.is_dir() else []


def track_info(d: Path) -> dict:
    root = ET.parse(d / "track.xml").getroot()
    return {"name": root.get("name", d.name).strip(), "designer": root.get("designer", "").strip()}


# --- driveline --------------------------------------------------------------------------------------------------

def read_quads(path: Path) -> np.ndarray:
    """quads.xml -> corners (n,4,3) in the game frame, resolving 'i:j' references."""
    root = ET.parse(path).getroot()
    quads: list[np.ndarray] = []
    for k, q in enumerate(root.iter("quad")):
        corners = []
        for c in ("p0", "p1", "p2", "p3"):
            text = q.get(c)
            if text is None:
                raise StkError(f"{path}: quad {k} has no {c}")
            m = re.fullmatch(r"\s*(\d+)\s*:\s*(\d)\s*", text)
            if m:
                i, j = int(m.group(1)), int(m.group(2))
                if i >= len(quads) or j > 3:
                    raise StkError(f"{path}: quad {k} {c}={text!r} refers to a quad not yet defined")
                corners.append(quads[i][j])
            else:
                corners.append(xml_floats(text, 3, f"{path}: quad {k} {c}"))
        quads.append(np.stack(corners))
    if not quads:
        raise StkError(f"{path}: no quads")
    return np.stack(quads)


def driveline(d: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """Runs of consecutive quads (file order = driving order): [(centres (n,3), widths (n,))], mirrored frame.

    The centre of a quad is the mean of its 4 corners; its width the mean of the p0-p1 and p3-p2 edges. A run
    breaks where the next quad's centre jumps (an alternative route or a separate driveline follows).
    """
    q = read_quads(d / "quads.xml") @ MIRROR
    centres = q.mean(axis=1)
    widths = (np.linalg.norm(q[:, 0] - q[:, 1], axis=1) + np.linalg.norm(q[:, 3] - q[:, 2], axis=1)) / 2
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    limit = 3.0 * float(np.median(steps)) + 1.0 if len(steps) else 0.0
    cuts = [0] + [i + 1 for i, s in enumerate(steps) if s > limit] + [len(centres)]
    return [(centres[a:b], widths[a:b]) for a, b in zip(cuts[:-1], cuts[1:]) if b - a >= 2]
