"""Object sources: the MD2 reader (on files written here), front normalisation, geometry signatures and
deduplication; and, where scripts/install_object_assets.sh has run, every FlightGear / UFO:AI model loading."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from nvs.data.render.md2 import read_md2
from nvs.data.render.orient import face_front, facing, length_axis
from nvs.data.render.scene import Part


def _md2_bytes(verts_u8, scale, translate, tris, st, skin_wh=(64, 32), skins=("car",), magic=b"IDP2", version=8):
    """A one-frame MD2 in the documented layout (header, skins, uvs, triangles, frame)."""
    n_verts, n_st, n_tris = len(verts_u8), len(st), len(tris)
    frame_size = 40 + 4 * n_verts
    ofs_skins = 68
    ofs_st = ofs_skins + 64 * len(skins)
    ofs_tris = ofs_st + 4 * n_st
    ofs_frames = ofs_tris + 12 * n_tris
    ofs_end = ofs_frames + frame_size
    out = struct.pack("<4s16i", magic, version, skin_wh[0], skin_wh[1], frame_size, len(skins), n_verts, n_st,
                      n_tris, 0, 1, ofs_skins, ofs_st, ofs_tris, ofs_frames, ofs_end, ofs_end)
    out += b"".join(s.encode().ljust(64, b"\0") for s in skins)
    out += b"".join(struct.pack("<2h", *uv) for uv in st)
    out += b"".join(struct.pack("<6h", *t) for t in tris)
    out += struct.pack("<3f3f16s", *scale, *translate, b"frame0")
    out += b"".join(struct.pack("<4B", *v, 0) for v in verts_u8)
    return out


def test_md2_positions_uvs_and_skins(tmp_path):
    verts = [(0, 0, 0), (10, 0, 0), (0, 20, 5)]
    p = tmp_path / "tri.md2"
    p.write_bytes(_md2_bytes(verts, (0.5, 0.25, 2.0), (1.0, -1.0, 3.0), [(0, 1, 2, 0, 1, 2)],
                             [(0, 0), (64, 0), (32, 16)], skins=(".car", "other")))
    mesh = read_md2(p)
    # vertex = byte * scale + translate, per corner
    np.testing.assert_allclose(mesh.positions, [[1.0, -1.0, 3.0], [6.0, -1.0, 3.0], [1.0, 4.0, 13.0]])
    # uv = st / skin size, v flipped (MD2's t grows downwards)
    np.testing.assert_allclose(mesh.uvs, [[0.0, 1.0], [1.0, 1.0], [0.5, 0.5]])
    assert mesh.faces.tolist() == [[0, 1, 2]]
    assert mesh.skins == [".car", "other"]


@pytest.mark.parametrize("case, message", [
    ("magic", "not an MD2 v8 file"), ("version", "not an MD2 v8 file"), ("short", "too short"),
    ("index", "out of range"), ("truncated", "inconsistent MD2 header"),
])
def test_md2_bad_files_name_the_file(tmp_path, case, message):
    args = dict(verts_u8=[(0, 0, 0)] * 3, scale=(1, 1, 1), translate=(0, 0, 0), tris=[(0, 1, 2, 0, 0, 0)],
                st=[(0, 0)])
    if case == "magic":
        args["magic"] = b"IDP3"
    if case == "version":
        args["version"] = 15
    if case == "index":
        args["tris"] = [(0, 1, 7, 0, 0, 0)]
    data = _md2_bytes(**args)
    data = {"short": data[:20], "truncated": data[:-8]}.get(case, data)
    p = tmp_path / f"{case}.md2"
    p.write_bytes(data)
    with pytest.raises(ValueError, match=message) as err:
        read_md2(p)
    assert str(p) in str(err.value)


def _box(lx: float, ly: float, lz: float, shift=(0.0, 0.0, 0.0)) -> Part:
    import trimesh

    b = trimesh.creation.box(extents=(lx, ly, lz))
    return Part(np.asarray(b.vertices) + shift, np.asarray(b.faces), None, None, np.ones(4))


def test_facing_turns_the_named_front_to_plus_z():
    # A long box with a marker cube at its +x end: after facing('+x') the marker is at +z, y unchanged.
    parts = [_box(4.0, 1.0, 2.0), _box(0.2, 0.2, 0.2, shift=(2.5, 0.3, 0.0))]
    assert length_axis(parts) == "x"
    for front, expect in (("+x", 1.0), ("-x", -1.0)):
        turned = facing(parts, front)
        marker = turned[1].positions.mean(0)
        np.testing.assert_allclose(marker, [0.0, 0.3, 2.5 * expect], atol=1e-12)
        assert length_axis(turned) == "z"
        assert np.isclose(np.linalg.det(np.eye(3)), 1.0)
    np.testing.assert_allclose(facing(parts, "+z")[1].positions, parts[1].positions)
    np.testing.assert_allclose(facing(parts, "-z")[1].positions.mean(0), [-2.5, 0.3, 0.0], atol=1e-12)
    with pytest.raises(ValueError, match="front must be one of"):
        facing(parts, "up")


def test_face_front_takes_a_direction_or_a_default_per_length_axis():
    parts = [_box(4.0, 1.0, 2.0), _box(0.2, 0.2, 0.2, shift=(2.5, 0.3, 0.0))]  # long along x, marker at +x
    by_axis = {"x": "+x", "z": "-z"}
    np.testing.assert_allclose(face_front(parts, "m", by_axis)[1].positions.mean(0), [0.0, 0.3, 2.5], atol=1e-12)
    np.testing.assert_allclose(face_front(parts, "m", "-x")[1].positions.mean(0), [0.0, 0.3, -2.5], atol=1e-12)
    with pytest.raises(ValueError, match=r"^models/car\.ac: front 'up' is not one of"):
        face_front(parts, "models/car.ac", "up")


def test_geometry_signature_ignores_texture_not_shape():
    from PIL import Image

    from nvs.data.render.objects import geometry_signature, normalised

    plain = [_box(4.0, 1.5, 2.0)]
    textured = [Part(plain[0].positions, plain[0].faces, np.zeros((8, 2)), Image.new("RGBA", (4, 4)), np.ones(4))]
    # Same shape at another scale and place: normalisation makes the signatures equal.
    moved = [Part(plain[0].positions * 3 + 7, plain[0].faces, None, None, np.array([1, 0, 0, 1.0]))]
    other = [_box(4.0, 1.4, 2.0)]
    sig = geometry_signature(normalised(plain))
    assert sig == geometry_signature(normalised(textured)) == geometry_signature(normalised(moved))
    assert sig != geometry_signature(normalised(other))


@pytest.mark.render
def test_identical_geometry_is_rendered_once(tmp_path):
    """Three sources, two of them the same shape: two are rendered, the duplicate is listed in meta.json."""
    from nvs.data.render.objects import render_objects
    from nvs.data.render.sources import ModelSource

    shapes = {"box-a": (1.0, 0.6, 0.8), "box-b": (1.0, 0.6, 0.8), "box-c": (1.0, 0.3, 0.8), "box-d": (0.5, 1, 1)}
    loads: list[str] = []

    def loader(i, extents):
        return lambda: loads.append(i) or [_box(*extents)]

    sources = [ModelSource(i, i, "test", "CC0", "test", loader(i, e)) for i, e in shapes.items()]
    meta = render_objects("cars", tmp_path, size=16, supersample=1, progress=False, sources=sources,
                          pairs_per_model=2)
    assert sorted(loads) == sorted(shapes)  # a full render loads each model once
    used = [m["id"] for m in meta["models"]]
    # Of identical geometries the smallest id is kept, whatever the seeded order.
    assert used == ["box-a", "box-c", "box-d"]
    assert meta["duplicates"] == [{"id": "box-b", "same_geometry_as": "box-a"}]
    assert not list((tmp_path / "images").glob("box-b_*"))
    # A re-run reads the cached signatures: nothing is loaded or rendered again.
    calls = []
    again = [ModelSource(s.id, s.name, s.package, s.licence, s.credit, lambda: calls.append(1)) for s in sources]
    meta2 = render_objects("cars", tmp_path, size=16, supersample=1, progress=False, sources=again,
                           pairs_per_model=2)
    assert meta2["views_rendered"] == 0 and not calls and meta2["duplicates"] == meta["duplicates"]


_WORKER_SCRIPT = """
import sys
from pathlib import Path

import numpy as np
import trimesh

from nvs.data.render.objects import render_objects
from nvs.data.render.scene import Part
from nvs.data.render.sources import ModelSource

shapes = {"box-a": (1.0, 0.6, 0.8), "box-b": (1.0, 0.6, 0.8), "box-c": (1.0, 0.3, 0.8), "box-d": (0.5, 1, 1),
          "box-e": (0.7, 0.7, 0.2)}


def loader(extents):
    def load():
        b = trimesh.creation.box(extents=extents)
        return [Part(np.asarray(b.vertices), np.asarray(b.faces), None, None, np.ones(4))]
    return load


def broken():
    raise ValueError("corrupt mesh")


sources = [ModelSource(i, i, "test", "CC0", "test", loader(e)) for i, e in shapes.items()]
sources.append(ModelSource("box-x", "x", "test", "CC0", "test", broken))
out, workers = Path(sys.argv[1]), int(sys.argv[2])
render_objects("cars", out / "all", size=16, supersample=1, progress=False, sources=sources, pairs_per_model=2,
               workers=workers)
render_objects("cars", out / "few", size=16, supersample=1, progress=False, sources=sources, pairs_per_model=2,
               max_models=3, workers=workers)
"""


@pytest.mark.render
def test_worker_processes_write_the_same_dataset(tmp_path):
    """workers=2 (forked processes) writes the same files as workers=1: the duplicate a worker rendered ahead is
    removed, a broken model is named and skipped, a max_models sample is the same. Each render runs in a fresh
    process (a process that has rendered before cannot fork renderers; the next test covers that case)."""
    import filecmp
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = tmp_path / "render_boxes.py"
    script.write_text(_WORKER_SCRIPT)
    # the script lives outside the checkout: put this checkout on its path, whatever the installed nvs points at
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    for w in (1, 2):
        subprocess.run([sys.executable, str(script), str(tmp_path / f"w{w}"), str(w)], check=True, timeout=120,
                       capture_output=True, env=env)
    for part in ("all", "few"):
        a, b = tmp_path / "w1" / part, tmp_path / "w2" / part
        metas = [json.loads((d / "meta.json").read_text()) for d in (a, b)]
        for key in ("models", "duplicates", "failed"):
            assert metas[0][key] == metas[1][key], (part, key)
        files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
        assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
        for f in files:
            if f.name != "meta.json":  # render_seconds and views_rendered differ
                assert filecmp.cmp(a / f, b / f, shallow=False), f
    full = json.loads((tmp_path / "w2" / "all" / "meta.json").read_text())
    assert full["duplicates"] == [{"id": "box-b", "same_geometry_as": "box-a"}]
    assert [f["id"] for f in full["failed"]] == ["box-x"]
    assert not list((tmp_path / "w2" / "all" / "images").glob("box-b_*"))
    assert len(json.loads((tmp_path / "w2" / "few" / "meta.json").read_text())["models"]) == 3


@pytest.mark.render
def test_workers_in_a_process_that_has_rendered_run_in_process(tmp_path, monkeypatch, capsys):
    """Forking after an offscreen context was opened hangs Mesa, so such a process renders in-process and says so."""
    from nvs.data.render import object_jobs
    from nvs.data.render.objects import render_objects
    from nvs.data.render.sources import ModelSource

    monkeypatch.setattr(object_jobs, "contexts_opened", lambda: 1)
    shapes = {"box-a": (1.0, 0.6, 0.8), "box-c": (1.0, 0.3, 0.8), "box-d": (0.5, 1, 1)}
    sources = [ModelSource(i, i, "test", "CC0", "test", (lambda e=e: [_box(*e)])) for i, e in shapes.items()]
    meta = render_objects("cars", tmp_path, size=16, supersample=1, progress=False, sources=sources,
                          pairs_per_model=2, workers=2)
    assert [m["id"] for m in meta["models"]] == sorted(shapes)
    assert "rendering in-process" in capsys.readouterr().out


# the checkout's asset folder (scripts/install_object_assets.sh's default destination)
ASSETS = Path(__file__).resolve().parents[1] / "data" / "assets"


def _extracted_or_skip(module):
    if not module.root(ASSETS).is_dir():
        pytest.skip(f"{module.PACKAGE} not extracted: run scripts/install_object_assets.sh")


@pytest.mark.render
@pytest.mark.parametrize("source", ["flightgear", "ufoai"])
@pytest.mark.parametrize("kind", ["cars", "chairs"])
def test_extracted_models_load_textured_and_front_along_z(source, kind):
    """Every listed model of the extracted packages loads, has an image texture, and (cars) lies along z."""
    import importlib

    module = importlib.import_module(f"nvs.data.render.{source}")
    _extracted_or_skip(module)
    models = getattr(module, f"{source}_models")(kind, ASSETS)
    listed = module.CARS if kind == "cars" else module.CHAIRS
    # flightgear lists {folder: [names]}, ufoai {body: [wheel parts]}
    expected = sum(len(v) for v in listed.values()) if source == "flightgear" else len(listed)
    if expected == 0:
        assert models == []
        return
    assert len(models) == expected
    for m in models:
        parts = m.load()
        assert any(p.image is not None for p in parts), m.id
        if kind == "cars":
            assert length_axis(parts) == "z", m.id


def test_gltf_reads_through_trimesh_and_its_credit_from_asset_extras(tmp_path):
    """A glTF 2.0 file (trimesh's reader) gives its triangles; a Sketchfab-style asset.extras gives licence and author."""
    import json

    import trimesh

    from nvs.data.render.more_cars import _gltf_credit
    from nvs.data.render.sources import trimesh_parts

    box = trimesh.creation.box(extents=(1.0, 2.0, 4.0))
    box.export(tmp_path / "car.gltf")
    parts = trimesh_parts(tmp_path / "car.gltf")
    assert sum(len(p.faces) for p in parts) == 12
    np.testing.assert_allclose(np.ptp(np.concatenate([p.positions for p in parts]), axis=0), [1.0, 2.0, 4.0])
    assert length_axis(parts) == "z"
    assert _gltf_credit(tmp_path / "car.gltf") is None  # trimesh writes no licence
    doc = json.loads((tmp_path / "car.gltf").read_text())
    doc["asset"]["extras"] = {"author": "Someone (https://example/someone)", "license": "CC-BY-4.0 (url)",
                              "source": "https://example/car", "title": "Car"}
    (tmp_path / "car.gltf").write_text(json.dumps(doc))
    licence, credit = _gltf_credit(tmp_path / "car.gltf")
    assert licence == "CC-BY-4.0 (url)" and credit == "'Car' by Someone (https://example/someone) (https://example/car)"


@pytest.mark.render
def test_more_cars_load_along_z_with_their_licences():
    """The OpenCity, PGDrive and assimp cars that scripts/install_object_assets.sh extracted: every listed file is
    found, loads, lies along z and (but for OpenCity's untextured police car) is textured."""
    from nvs.data.render import more_cars

    present = [pkg for pkg in more_cars.PACKAGES if (ASSETS / pkg).is_dir()]
    if not present:
        pytest.skip("OpenCity / PGDrive / assimp models not extracted: run scripts/install_object_assets.sh")
    models = more_cars.more_cars(ASSETS)
    assert len(models) == sum(len(more_cars.PACKAGES[p][2]) for p in present)
    for m in models:
        parts = m.load()
        assert length_axis(parts) == "z", m.id
        assert m.id == "oc-police" or any(p.image is not None for p in parts), m.id
        assert more_cars.copyright_files(ASSETS)[m.package].is_file(), m.package
    by_id = {m.id: m for m in models}
    if "pgdrive-beetle" in by_id:
        assert by_id["pgdrive-beetle"].licence.startswith("CC-BY-4.0") and "soujagah" in by_id["pgdrive-beetle"].credit


def test_licence_per_file_from_the_debian_copyright_file():
    """DEP-5: the last Files paragraph with a matching pattern gives holders and licence; 'Files: *' is the default."""
    from nvs.data.render.sources import dep5_licence

    text = ("Format: https://example/copyright-format/1.0/\n\nFiles: *\nCopyright: 2002 The Team\nLicense: GPL-2+\n\n"
            "Files:\n data/library/stklib_a/*\n data/library/stklib_b/*\nCopyright:\n 2016 Someone\n 2017 Other\n"
            "License: CC-BY-SA-3.0\n\nFiles: data/library/stklib_c/*\nCopyright: 2014 Third\nLicense: CC0\n"
            " Some licence text.\n")
    assert dep5_licence(text, "data/library/stklib_b/b_main.spm") == ("2016 Someone 2017 Other", "CC-BY-SA-3.0")
    assert dep5_licence(text, "data/library/stklib_c/c.spm") == ("2014 Third", "CC0")
    assert dep5_licence(text, "data/other/x.png") == ("2002 The Team", "GPL-2+")
    assert dep5_licence("Format: x\n", "a/b") == ("see copyright", "see copyright")


def test_source_sheets_need_a_rendered_root(tmp_path, capsys):
    from nvs.data.render.__main__ import main

    with pytest.raises(SystemExit) as err:
        main(["sheets", f"root={tmp_path}", f"out={tmp_path / 'out'}"])
    assert err.value.code == 2
    assert str(tmp_path / "meta.json") in capsys.readouterr().err


# -- where the extracted asset packages are found -------------------------------------------------------------------
def test_the_asset_folder_is_the_option_then_the_environment_then_data_assets(tmp_path, monkeypatch):
    from nvs.core.errors import UserError
    from nvs.data.render.sources import asset_dir

    opt, env = tmp_path / "opt", tmp_path / "env"
    opt.mkdir()
    env.mkdir()
    monkeypatch.chdir(tmp_path)
    assert asset_dir(str(opt), str(env)) == opt
    assert asset_dir(None, str(env)) == env
    assert asset_dir() == tmp_path / "data" / "assets"  # under the working directory, present or not
    with pytest.raises(UserError, match=r"^assets=/no/such: no such directory"):
        asset_dir("/no/such", str(env))
    with pytest.raises(UserError, match=r"^NVS_ASSETS=/no/such: no such directory"):
        asset_dir(None, "/no/such")


def test_the_models_and_licences_come_from_the_asset_folder(tmp_path):
    import trimesh

    from nvs.data.render import more_cars
    from nvs.data.render.assets import category_models, copyright_files

    path = tmp_path / "assimp-testmodels" / more_cars.PACKAGES["assimp-testmodels"][2]["jeep"]
    path.parent.mkdir(parents=True)
    trimesh.creation.box(extents=(1.0, 1.0, 3.0)).export(path)
    assert [m.id for m in more_cars.more_cars(tmp_path)] == ["assimp-jeep"]
    assert "assimp-jeep" in {m.id for m in category_models("cars", tmp_path)}
    assert more_cars.more_cars(tmp_path / "empty") == []
    assert copyright_files(tmp_path)["flightgear-data-base"].is_relative_to(tmp_path)


def test_render_names_a_missing_asset_folder_before_rendering(tmp_path, monkeypatch, capsys):
    from nvs.data.render.__main__ import main

    out = tmp_path / "out"
    for argv, env, named in ((["chairs", f"assets={tmp_path / 'nope'}", f"out={out}"], None, "assets="),
                             (["cars", f"out={out}"], str(tmp_path / "gone"), "NVS_ASSETS=")):
        if env:
            monkeypatch.setenv("NVS_ASSETS", env)
        with pytest.raises(SystemExit) as code:
            main(argv)
        err = capsys.readouterr().err
        assert code.value.code == 2 and err.startswith(f"error: {named}") and "no such directory" in err, err
        assert "Traceback" not in err
    assert not out.exists()
