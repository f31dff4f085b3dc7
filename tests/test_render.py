"""Renderer tests on real models (marked `render`: need the Debian asset packages and Mesa's software EGL).

The convention test is the one that matters: a rendered source view, warped into the target view with the
rendered target depth and the K and pose THE LOADERS return, must reproduce the rendered target. It pins the
renderer's camera (including pyrender's half-pixel principal-point offset), the formats, the loaders' pose
direction and nvs.core.geometry against each other.
"""

from __future__ import annotations

import filecmp
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

pytestmark = pytest.mark.render

CONF_DATA = Path(__file__).resolve().parents[1] / "conf" / "data"
CHAIRS = ["sh3d-blendswap-cc-by-plaidchair", "sh3d-scopia-bar-chair", "sh3d-scopia-chair4"]
CARS = ["sh3d-katorlegaz-vw-new-beetle", "torcs-car1-ow1", "trigger-cordo-wrc"]
SIZE = 64


def _assets_or_skip():
    from nvs.data.render.assets import SH3D_DIR, TORCS_DIR

    if not SH3D_DIR.is_dir() or not (TORCS_DIR / "tracks").is_dir():
        pytest.skip("asset packages missing: run scripts/install_assets.sh")


def _sources(category: str, ids: list[str]):
    from nvs.data.render.assets import category_models

    by_id = {m.id: m for m in category_models(category)}
    return [by_id[i] for i in ids]


def _broken():
    from nvs.data.render.assets import ModelSource

    def load():
        raise ValueError("corrupt mesh")

    return ModelSource("broken-model", "Broken", "none", "none", "none", load)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Two object roots (3 real models each; chairs also get a broken model) and a small drive root, at 64^2."""
    _assets_or_skip()
    from nvs.data.render.drive import render_drive
    from nvs.data.render.objects import render_objects

    base = tmp_path_factory.mktemp("render")
    metas = {
        "chairs": render_objects("chairs", base / "chairs", size=SIZE, max_models=3, progress=False,
                                 sources=_sources("chairs", CHAIRS) + [_broken()]),
        "cars": render_objects("cars", base / "cars", size=SIZE, max_models=3, progress=False,
                               sources=_sources("cars", CARS)),
        "drive": render_drive(base / "drive", size=SIZE, sequences=3, frames=12, sources="torcs", progress=False),
    }
    return base, metas


def _datamodule(name: str, root: Path):
    """The loaders as training uses them: data config's camera facts -> build_datamodule."""
    from nvs.data.datamodule import build_datamodule

    cfg = OmegaConf.load(CONF_DATA / f"{name}.yaml")
    return build_datamodule(cfg.format, str(root), SIZE, OmegaConf.to_container(cfg.camera),
                            {"cache": False, "with_depth": True}, seed=0, category=cfg.category,
                            translation_scale=cfg.translation_scale)


def _warp_error(dm, split: str, limit: int | None = None, transpose_pose: bool = False,
                shift_cx: float = 0.0) -> tuple[float, float]:
    """Mean L1 (on [0,1]) of the warped source vs the target over co-visible pixels, and their fraction."""
    from nvs.core.geometry import inverse_warp, project_to_source, sample_at

    ds = dm.dataset(split)
    items = [ds[i] for i in range(len(ds) if limit is None else min(limit, len(ds)))]
    batch = {k: torch.stack([it[k] for it in items]) for k in ("src", "tgt", "K", "T_tgt_src", "depth_src",
                                                                "depth_tgt")}
    T = batch["T_tgt_src"]
    if transpose_pose:
        from nvs.core.geometry import invert_pose

        T = invert_pose(T)
    K = batch["K"].clone()
    K[:, 0, 2] += shift_cx
    warped, valid = inverse_warp(batch["src"], batch["depth_tgt"], K, T)
    # Source visibility: the target point must be the surface the source camera sees at that pixel
    # (its z in the source camera matches the source depth there), else it is occluded in the source.
    uv, z_src, in_front = project_to_source(batch["depth_tgt"], K, T)
    d_src_at = sample_at(batch["depth_src"], uv, in_front)[:, 0]
    visible = (d_src_at > 0) & ((d_src_at - z_src).abs() < 0.03 * z_src.abs())
    mask = (valid[:, 0] > 0) & (batch["depth_tgt"][:, 0] > 0) & visible
    err = (warped - batch["tgt"]).abs().mean(1)
    return float(err[mask].mean()), float(mask.float().mean())


# Bounds from measurement (64^2, supersample 3, seed 0): the correct conventions give mean L1 0.030 (chairs),
# 0.029 (cars) and 0.0105 (drive) on co-visible pixels. The residual is bilinear resampling of antialiased
# pixels whose texture detail is below the pixel size (the plaid chair dominates) plus the weak specular term;
# an inverted pose gives several times more (control below). Half a pixel of principal-point error barely moves
# this average, so the renderer's projection is pinned separately to 0.1 px (test_renderer_projects_with_K).
OBJECT_BOUND = 0.04
DRIVE_BOUND = 0.02


@pytest.mark.parametrize("name", ["chairs", "cars"])
def test_object_warp_reproduces_target(rendered, name):
    base, _ = rendered
    err, frac = _warp_error(_datamodule(name, base / name), "test")
    print(f"{name}: co-visible L1 {err:.4f} on {frac:.1%} of pixels")
    assert frac > 0.05
    assert err < OBJECT_BOUND


def test_drive_warp_reproduces_target(rendered):
    base, _ = rendered
    err, frac = _warp_error(_datamodule("drive", base / "drive"), "test")
    print(f"drive: co-visible L1 {err:.4f} on {frac:.1%} of pixels")
    assert frac > 0.3
    assert err < DRIVE_BOUND


def test_inverted_pose_fails_the_warp(rendered):
    """Control: the warp check can fail; the inverse of the loader's pose (T_src_tgt) is far off."""
    base, _ = rendered
    for name in ("chairs", "drive"):
        dm = _datamodule(name, base / name)
        good, _ = _warp_error(dm, "test")
        inverted, _ = _warp_error(dm, "test", transpose_pose=True)
        print(f"{name}: correct {good:.4f}, inverted pose {inverted:.4f}")
        # Measured: chairs 0.030 -> 0.083, drive 0.0105 -> 0.0159 (frames <= 7 m apart, mostly distant scenery).
        assert inverted > (2.0 if name == "chairs" else 1.3) * good


def test_renderer_projects_with_K():
    """A small dark sphere at X renders centred on K X to 0.1 px (pyrender's principal point is edge-based)."""
    _assets_or_skip()
    import numpy as np
    import trimesh

    from nvs.data.render.objects import K256
    from nvs.data.render.scene import Part, Renderer, scaled_K, supersampled, to_pyrender

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.04)
    for X in (np.array([0.25, -0.15, 2.0]), np.array([-0.3, 0.2, 2.2])):
        r = Renderer(SIZE * 3, scaled_K(K256, SIZE * 3), znear=0.5, zfar=4.0, lit=False)
        r.set_mesh(to_pyrender([Part(np.asarray(sphere.vertices) + X, np.asarray(sphere.faces), None, None,
                                     np.array([0.0, 0.0, 0.0, 1.0]))]))
        rgb, depth = supersampled(r, np.eye(4), 3)
        r.close()
        w = 1.0 - rgb.astype(np.float64).mean(-1) / 255.0
        v, u = np.mgrid[0:SIZE, 0:SIZE]
        centroid = np.array([(w * u).sum(), (w * v).sum()]) / w.sum()
        p = scaled_K(K256, SIZE) @ X
        expected = p[:2] / p[2]
        assert np.abs(centroid - expected).max() < 0.1, (centroid, expected)
        # Depth is z along the optical axis: the sphere's nearest point.
        assert abs(depth[depth > 0].min() - (X[2] - 0.04)) < 0.01


def test_broken_model_is_reported_and_skipped(rendered, capsys):
    base, metas = rendered
    meta = metas["chairs"]
    assert [f["id"] for f in meta["failed"]] == ["broken-model"]
    assert "corrupt mesh" in meta["failed"][0]["error"]
    ids = [line for split in ("train", "val", "test") for line in (base / "chairs" / f"id_{split}.txt").read_text().split()]
    assert sorted(ids) == sorted(CHAIRS)
    assert not list((base / "chairs" / "images").glob("broken-model_*"))


def test_rerun_skips_finished_models(rendered):
    from nvs.data.render.objects import render_objects

    base, _ = rendered
    png = base / "cars" / "images" / f"{CARS[0]}_0_0.png"
    before = png.stat().st_mtime_ns
    meta = render_objects("cars", base / "cars", size=SIZE, max_models=3, progress=False,
                          sources=_sources("cars", CARS))
    assert meta["views_rendered"] == 0
    assert png.stat().st_mtime_ns == before
    assert not list((base / "cars").rglob("*.tmp"))


def test_splits_and_pairs_are_deterministic(tmp_path):
    """Two renders with the same seed give byte-identical split, pair and pose files; model splits are disjoint."""
    _assets_or_skip()
    from nvs.data.render.drive import render_drive
    from nvs.data.render.objects import render_objects

    for d in ("a", "b"):
        render_objects("chairs", tmp_path / d / "chairs", size=16, supersample=1, max_models=3, progress=False,
                       sources=_sources("chairs", CHAIRS))
        render_drive(tmp_path / d / "drive", size=16, supersample=1, sequences=3, frames=9, sources="torcs",
                     progress=False)
    files = ["chairs/id_train.txt", "chairs/id_val.txt", "chairs/id_test.txt", "chairs/eval_chair_40.txt",
             "drive/poses.txt", "drive/pairs_train.txt", "drive/pairs_val.txt", "drive/eval_kitti.txt"]
    for f in files:
        assert filecmp.cmp(tmp_path / "a" / f, tmp_path / "b" / f, shallow=False), f
    splits = [set((tmp_path / "a" / f"chairs/id_{s}.txt").read_text().split()) for s in ("train", "val", "test")]
    assert all(splits) and not (splits[0] & splits[1] or splits[0] & splits[2] or splits[1] & splits[2])
    # Drive pairs stay within a sequence, at most 7 frames apart; sequences do not cross splits.
    seqs = {}
    for f in ("pairs_train.txt", "pairs_val.txt", "eval_kitti.txt"):
        for line in (tmp_path / "a" / "drive" / f).read_text().splitlines():
            a, b = line.split()
            assert a.split("_")[0] == b.split("_")[0] and 0 < abs(int(a[3:]) - int(b[3:])) <= 7
            seqs.setdefault(a.split("_")[0], set()).add(f)
    assert all(len(v) == 1 for v in seqs.values())
