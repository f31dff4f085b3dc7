"""Drive data: the .spm reader, SuperTuxKart scene parsing, sequence planning, and the camera/depth-head contract.

The contract that matters: the drive data config's depth head can express the rendered depths. It is checked
twice: on the committed statistics of the full render (docs/drive_depth_stats.json, written by the renderer as
depth_stats.json) and on a small render made here (marked `render`: needs the TORCS package and software EGL).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from nvs.data.render import depth_stats, drive, drive_plan, drive_rig, drive_sources
from nvs.data.render.spm import SpmError, read_spm
from nvs.data.render.stk import StkError, driveline, hpr_matrix, read_quads

REPO = Path(__file__).resolve().parents[1]
CONF_DATA = REPO / "conf" / "data"
STATS = REPO / "docs" / "drive_depth_stats.json"
SHARE = 0.99  # of valid ground-truth depths the head must be able to express


def _head_range_m(config: str) -> tuple[float, float]:
    """(min, max) depth in METRES the data config's head can output: its range in scaled units / scale."""
    from nvs.models.depth_head import DisparityDepth

    cfg = _data_config(config)
    head = cfg.depth_head
    assert head._target_ == "nvs.models.depth_head.DisparityDepth"
    h = DisparityDepth(head.max_disparity, head.min_disparity)
    return h.min_depth / cfg.translation_scale, h.max_depth / cfg.translation_scale


def _data_config(config: str):
    """A data config file on its own, merged over drive.yaml when it lists drive in its defaults."""
    cfg = OmegaConf.load(CONF_DATA / f"{config}.yaml")
    if "drive" in cfg.get("defaults", []):
        cfg = OmegaConf.merge(OmegaConf.load(CONF_DATA / "drive.yaml"), cfg)
    return cfg


def _camera(config: str) -> dict:
    return OmegaConf.to_container(_data_config(config).camera)


# --- camera and head -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("config, camera", [("drive", "kitti"), ("drive_wide", "wide")])
def test_data_config_camera_is_the_renderers(config, camera):
    cam, K = _camera(config), drive_rig.camera_K(camera)
    assert cam["size"] == 256
    assert (cam["fx"], cam["fy"], cam["cx"], cam["cy"]) == (K[0, 0], K[1, 1], K[0, 2], K[1, 2])


def test_drive_uses_the_papers_kitti_camera():
    cam = _camera("drive")
    assert (cam["fx"], cam["cx"]) == (718.9, 128.0)  # the paper's code, models/base_model.py


def test_head_range_in_metres():
    lo, hi = _head_range_m("drive")
    assert lo == pytest.approx(1 / 10.01 / 0.02) and hi == pytest.approx(5000.0)  # 4.995 m .. 5000 m
    lo_wide, _ = _head_range_m("drive_wide")
    assert lo_wide == pytest.approx(1 / 100.01 / 0.02)  # ~0.5 m


def test_representable_fraction_by_hand():
    counts = np.zeros(len(depth_stats.DEPTH_BINS) + 1, dtype=np.int64)
    counts[0] = 1000  # sky does not count
    k3 = np.searchsorted(depth_stats.DEPTH_BINS, 3.0) - 1  # a bin around 3 m: below a 5 m head minimum
    k20 = np.searchsorted(depth_stats.DEPTH_BINS, 20.0) - 1
    counts[1 + k3], counts[1 + k20] = 1, 99
    assert depth_stats.representable_fraction(counts, 5.0, 5000.0) == pytest.approx(0.99)
    assert depth_stats.representable_fraction(counts, 1.0, 5000.0) == pytest.approx(1.0)
    assert depth_stats.representable_fraction(counts, 50.0, 5000.0) == 0.0
    # A bin straddling the limit does not count (the answer errs low).
    edge = depth_stats.DEPTH_BINS[k20] * 1.001
    assert depth_stats.representable_fraction(counts, edge, 5000.0) == pytest.approx(0.0)


def test_committed_render_depths_fit_the_head():
    """The full drive render's depths (docs/drive_depth_stats.json) lie inside conf/data/drive.yaml's head."""
    stats = json.loads(STATS.read_text())
    assert stats["camera"] == "kitti"
    assert np.allclose(stats["bins_m"], depth_stats.DEPTH_BINS)
    lo, hi = _head_range_m("drive")
    K = np.array(stats["K"])
    cam = _camera("drive")
    assert K[0, 0] == pytest.approx(cam["fx"] * stats["size"] / cam["size"])
    total = np.sum([c for c in stats["counts"].values()], axis=0)
    assert stats["sequences"] >= 30 and stats["frames"] >= 200
    assert len(stats["counts"]) >= 2  # scenes from at least two games
    share = depth_stats.representable_fraction(total, lo, hi)
    print(f"representable share of valid depths: {share:.4%} (head {lo:.2f} m .. {hi:.0f} m)")
    assert share >= SHARE
    for source, counts in stats["counts"].items():
        assert depth_stats.representable_fraction(counts, lo, hi) >= SHARE, source


# --- .spm reader -----------------------------------------------------------------------------------------------

def _spm(path: Path, colours: bool, tex: str = "wall.png", skinned: bool = False, truncate: int = 0) -> Path:
    """A one-triangle .spm (vertex colours optional) written by hand from the format description."""
    flags = 1 | (2 if colours else 0)
    out = b"SP" + bytes([(1 << 3) | (1 if skinned else 2), flags]) + struct.pack("<6f", 0, 0, 0, 1, 1, 0)
    out += struct.pack("<H", 1) + bytes([len(tex)]) + tex.encode() + bytes([0])
    out += struct.pack("<H", 1) + struct.pack("<H", 1) + struct.pack("<IIH", 3, 3, 0)
    verts = [((0.0, 0.0, 0.0), (0.0, 0.0), None), ((1.0, 0.0, 0.0), (1.0, 0.0), (255, 0, 0)),
             ((0.0, 1.0, 0.0), (0.0, 1.0), None)]
    for pos, uv, rgb in verts:
        out += struct.pack("<3f", *pos) + struct.pack("<I", 0)
        if colours:
            out += bytes([128]) if rgb is None else bytes([255, *rgb])
        if tex:
            out += np.array(uv, dtype="<f2").tobytes()
        if skinned:
            out += struct.pack("<4h", -1, 0, 0, 0) + np.zeros(4, dtype="<f2").tobytes()
    out += bytes([0, 1, 2])
    path.write_bytes(out[:len(out) - truncate] if truncate else out)
    return path


@pytest.mark.parametrize("colours", [False, True])
def test_spm_reads_a_hand_written_triangle(tmp_path, colours):
    (buf,) = read_spm(_spm(tmp_path / "t.spm", colours))
    assert buf.texture == "wall.png" and buf.texture2 == ""
    assert np.array_equal(buf.positions, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    assert np.array_equal(buf.faces, [[0, 1, 2]])
    assert np.array_equal(buf.uvs, [[0, 0], [1, 0], [0, 1]])
    expected = [[1, 1, 1], [1, 0, 0], [1, 1, 1]] if colours else np.ones((3, 3))
    assert np.allclose(buf.colors, expected)


def test_spm_skinned_and_untextured(tmp_path):
    (buf,) = read_spm(_spm(tmp_path / "s.spm", True, tex="", skinned=True))
    assert buf.uvs is None and len(buf.faces) == 1


@pytest.mark.parametrize("damage, message", [("magic", "not an .spm"), ("truncate", "truncated"),
                                             ("extra", "bytes left")])
def test_spm_errors_name_the_file(tmp_path, damage, message):
    p = _spm(tmp_path / "bad.spm", False, truncate=2 if damage == "truncate" else 0)
    if damage == "magic":
        p.write_bytes(b"XX" + p.read_bytes()[2:])
    if damage == "extra":
        p.write_bytes(p.read_bytes() + b"\0\0")
    with pytest.raises(SpmError, match=message) as err:
        read_spm(p)
    assert "bad.spm" in str(err.value)


# --- SuperTuxKart scene parsing ----------------------------------------------------------------------------------

def test_hpr_is_irrlichts_rotation():
    """hpr = (x, y, z) degrees; y is the heading about the up axis: +90 turns +x into -z (Irrlicht's Ry)."""
    assert np.allclose(hpr_matrix(np.array([0.0, 90.0, 0.0])) @ [1, 0, 0], [0, 0, -1])
    assert np.allclose(hpr_matrix(np.array([90.0, 0.0, 0.0])) @ [0, 1, 0], [0, 0, 1])
    # Rz Ry Rx order: x first, then y.
    R = hpr_matrix(np.array([90.0, 90.0, 0.0]))
    assert np.allclose(R @ [0, 1, 0], hpr_matrix(np.array([0.0, 90.0, 0.0])) @ [0, 0, 1])


def test_quads_references_and_driveline(tmp_path):
    """'i:j' corners resolve; centres are corner means (z mirrored); a jump starts a new run."""
    q = ['<quad p0="0 0 0" p1="4 0 0" p2="4 0 2" p3="0 0 2"/>',
         '<quad p0="0:3" p1="0:2" p2="4 0 4" p3="0 0 4"/>',
         '<quad p0="1:3" p1="1:2" p2="4 0 6" p3="0 0 6"/>',
         '<quad p0="100 0 100" p1="104 0 100" p2="104 0 102" p3="100 0 102"/>',
         '<quad p0="3:3" p1="3:2" p2="104 0 104" p3="100 0 104"/>']
    (tmp_path / "quads.xml").write_text("<quads>" + "".join(q) + "</quads>")
    corners = read_quads(tmp_path / "quads.xml")
    assert np.array_equal(corners[1, 0], [0, 0, 2]) and np.array_equal(corners[1, 1], [4, 0, 2])
    runs = driveline(tmp_path)
    assert [len(c) for c, _ in runs] == [3, 2]
    assert np.allclose(runs[0][0][0], [2, 0, -1]) and np.allclose(runs[0][1], 4.0)


def test_quads_bad_reference_names_the_file(tmp_path):
    (tmp_path / "quads.xml").write_text('<quads><quad p0="5:1" p1="0 0 0" p2="1 0 0" p3="1 0 1"/></quads>')
    with pytest.raises(StkError, match="quads.xml: quad 0"):
        read_quads(tmp_path / "quads.xml")


# --- planning ----------------------------------------------------------------------------------------------------

def _fake_source(src: str, name: str, length: float) -> drive_sources.SceneSource:
    pts = np.stack([np.zeros(int(length) + 1), np.zeros(int(length) + 1), np.arange(int(length) + 1.0)], axis=1)
    return drive_sources.SceneSource(src, name, lambda: [(pts, np.full(len(pts), 8.0))], lambda: None, "pkg", "lic", "c")


def test_plan_weights_windows_and_scene_splits():
    sources = {"a": [_fake_source("a", f"a{i}", 700) for i in range(5)],
               "b": [_fake_source("b", f"b{i}", 300) for i in range(5)]}
    failed: list[str] = []
    plan = drive_plan.plan_sequences(sources, 12, 200, seed=0, failed=failed, weights={"a": 2, "b": 1})
    assert [p.scene.source for p in plan[:6]] == ["a", "a", "b", "a", "a", "b"]
    # Windows of one scene are disjoint (210 m each, 20 m apart) and inside the centre line.
    for name in {p.scene.name for p in plan}:
        starts = sorted(p.start for p in plan if p.scene.name == name)
        assert all(b - a >= 210 for a, b in zip(starts, starts[1:]))
        assert all(s + 200 < 700 for s in starts)
    split = drive_plan.split_scenes(plan, seed=0)
    scene_of = {p.seq: (p.scene.source, p.scene.name) for p in plan}
    sets = {k: {scene_of[s] for s in v} for k, v in split.items()}
    assert sets["test"] and sets["train"] and not (sets["test"] & sets["train"] or sets["val"] & sets["train"])
    assert {s for s, _ in sets["test"]} == {"a", "b"}  # each source has test scenes
    assert not failed


def test_plan_too_few_windows_is_one_clear_error():
    with pytest.raises(RuntimeError, match="only 1 windows of 200 m"):
        drive_plan.plan_sequences({"a": [_fake_source("a", "a0", 300)]}, 3, 200, seed=0, failed=[])


@pytest.mark.parametrize("bad, message", [("stk,nope", "unknown drive source 'nope'"), ("stk:x", "integer"),
                                          ("stk,stk", "twice"), ("stk:0", ">= 1")])
def test_sources_option_errors(bad, message):
    with pytest.raises(ValueError, match=message):
        drive_sources.parse_sources(bad)


# --- a small render (CI: TORCS is in the setup's packages) --------------------------------------------------------

def _torcs_or_skip():
    from nvs.data.render.assets import TORCS_DIR

    if not (TORCS_DIR / "tracks").is_dir():
        pytest.skip("torcs-data missing: run scripts/install_assets.sh")


@pytest.mark.render
def test_small_render_depths_fit_the_head_and_warp(tmp_path):
    """A small kitti-camera render: its depth statistics file agrees with its depth maps, >= 99% of valid depths
    are inside the data config's head range, and sequences of one scene never cross splits."""
    _torcs_or_skip()
    out = tmp_path / "drive"
    meta = drive.render_drive(out, size=32, supersample=1, sequences=3, frames=20, sources="torcs",
                              progress=False)
    stats = json.loads((out / "depth_stats.json").read_text())
    depths = np.concatenate([np.load(p).ravel() for p in sorted((out / "depth").glob("*.npy"))])
    counts = np.asarray(stats["counts"]["torcs"])
    assert counts.sum() == depths.size and counts[0] == int((depths <= 0).sum())
    lo, hi = _head_range_m("drive")
    share = depth_stats.representable_fraction(counts, lo, hi)
    exact = float(((depths > lo) & (depths < hi)).sum() / (depths > 0).sum())
    print(f"small render: {share:.4%} of valid depths inside {lo:.2f}..{hi:.0f} m (exact {exact:.4%})")
    assert share <= exact + 1e-9 and share >= SHARE
    # The wide camera sees the road 2 m ahead: the kitti head could not express it, the wide head can.
    wide = drive.render_drive(tmp_path / "wide", size=32, supersample=1, sequences=3, frames=20,
                              sources="torcs", camera="wide", progress=False)
    wstats = json.loads((tmp_path / "wide" / "depth_stats.json").read_text())["counts"]["torcs"]
    assert depth_stats.representable_fraction(wstats, lo, hi) < SHARE
    assert depth_stats.representable_fraction(wstats, *_head_range_m("drive_wide")) >= SHARE
    assert wide["K"][0][0] < meta["K"][0][0]
    scenes = {s["seq"]: s["scene"] for s in meta["sequences"]}
    where = {scenes[int(q)]: k for k, v in meta["split"].items() for q in v}
    assert len(where) == len(set(scenes.values()))


@pytest.mark.render
def test_stk_track_loads_with_placed_objects():
    """One SuperTuxKart track: scene.xml's placements add surfaces beyond the track mesh; textures resolve."""
    from nvs.data.render import stk, stk_scene

    d = stk.STK_DIR / "tracks" / "hacienda"
    if not d.is_dir():
        pytest.skip("supertuxkart-data not extracted: run scripts/install_drive_assets.sh")
    parts, missing = stk_scene.load_scene(d)
    track_only = sum(len(b.faces) for b in read_spm(d / "hacienda_track.spm"))
    assert sum(len(p.faces) for p in parts) > 1.2 * track_only
    assert sum(p.image is not None for p in parts) >= 0.9 * len(parts)
    assert not missing
    runs = stk.driveline(d)
    length = max(float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum()) for c, _ in runs)
    assert 500 < length < 3000 and 4 < np.median(np.concatenate([w for _, w in runs])) < 20


@pytest.mark.render
def test_rerun_resumes_and_a_changed_plan_is_refused(tmp_path):
    _torcs_or_skip()
    kw = dict(size=16, supersample=1, sequences=3, frames=5, sources="torcs", progress=False)
    drive.render_drive(tmp_path / "d", **kw)
    png = tmp_path / "d" / "images" / "00_000000.png"
    before = png.stat().st_mtime_ns
    assert drive.render_drive(tmp_path / "d", **kw)["frames_rendered"] == 0
    assert png.stat().st_mtime_ns == before
    with pytest.raises(ValueError, match=r"plan.json: .* \(camera differ\)"):
        drive.render_drive(tmp_path / "d", **{**kw, "camera": "wide"})
