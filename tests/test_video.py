"""Videos along camera paths and point clouds of predicted depth: the paths stay in the trained range, the files read
back with the frame and vertex counts asked for, and the CLIs run end to end on a checkpoint trained here."""

from __future__ import annotations

import json
from pathlib import Path

import imageio_ffmpeg
import numpy as np
import pytest
import torch
from PIL import Image

from nvs.core.errors import UserError
from nvs.report.pointcloud import depth_to_points, read_ply, write_ply
from nvs.viewer.controls import ObjectControls, SceneControls, check_values
from nvs.viewer.paths import camera_path
from nvs.viewer.session import Source, ViewSession
from nvs.viewer.video import compose_frames, render_views, write_video
from tests.conftest import compose_train, fixture_batch
from tests.run_helpers import cli_in_process
from tests.viewer_helpers import built_net, one_step_checkpoint

OBJECTS = ObjectControls(40, (0.0, 0.0, 2.0))
SCENES = SceneControls((-0.4, 0.2), (0.0, 1.5), 0.02)


def _read_counts(mp4, gif) -> tuple[int, int]:
    frames_mp4, _ = imageio_ffmpeg.count_frames_and_secs(str(mp4))
    with Image.open(gif) as im:
        return frames_mp4, im.n_frames


# -- camera paths ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("controls, meta", [(OBJECTS, {"azimuth": 40.0, "elevation": 10.0}),
                                            (OBJECTS, {"azimuth": 0.0, "elevation": 20.0}), (SCENES, {})])
def test_orbit_starts_at_the_source_view_and_stays_in_the_trained_range(controls, meta):
    path = camera_path("orbit", controls, meta, 36)
    assert len(path) == 36 and path[0] == controls.initial(meta)
    for values in path:
        check_values(controls.axes, values)  # raises outside the range
    for ax in controls.axes:  # the orbit uses the range, not a sliver of it
        seen = [v[ax.name] for v in path]
        assert max(seen) - min(seen) >= 0.5 * (ax.max - ax.min), ax.name
    if controls is OBJECTS:
        assert max(v["azimuth"] for v in path) == pytest.approx(40.0, abs=0.1)


def test_forward_drives_straight_ahead_to_the_farthest_trained_motion():
    path = camera_path("forward", SCENES, {}, 10)
    forward = [v["forward"] for v in path]
    assert forward[0] == 0.0 and forward[-1] == pytest.approx(1.5) and np.all(np.diff(forward) > 0)
    assert all(v["sideways"] == 0.0 for v in path)
    # the pose moves the camera toward a point ahead: it comes closer frame by frame
    z = [float((SCENES.pose(v, {}) @ torch.tensor([0.0, 0.0, 0.4, 1.0]))[2]) for v in path]
    assert np.all(np.diff(z) < 0)
    with pytest.raises(UserError, match="path=forward drives the camera forward"):
        camera_path("forward", OBJECTS, {"azimuth": 0.0, "elevation": 0.0}, 10)


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_custom_path_interpolates_keyframes_from_yaml_or_json(tmp_path, suffix):
    keys = [{"azimuth": -20, "elevation": 0}, {"azimuth": 20, "elevation": 20}]
    f = tmp_path / f"poses{suffix}"
    f.write_text(json.dumps({"poses": keys}) if suffix == ".json" else
                 "poses:\n" + "".join(f"  - {{azimuth: {k['azimuth']}, elevation: {k['elevation']}}}\n" for k in keys))
    path = camera_path("custom", OBJECTS, {}, 5, custom=f)
    assert [v["azimuth"] for v in path] == [-20.0, -10.0, 0.0, 10.0, 20.0]
    assert [v["elevation"] for v in path] == [0.0, 5.0, 10.0, 15.0, 20.0]
    assert camera_path("custom", OBJECTS, {}, None, custom=f) == [{k: float(v) for k, v in p.items()} for p in keys]


def test_bad_custom_paths_are_one_clear_error(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("poses:\n  - {azimuth: 10}\n")
    with pytest.raises(UserError, match="each pose gives exactly azimuth, elevation"):
        camera_path("custom", OBJECTS, {}, 4, custom=f)
    with pytest.raises(UserError, match="no such file"):
        camera_path("custom", OBJECTS, {}, 4, custom=tmp_path / "missing.yaml")
    with pytest.raises(UserError, match="expected one of orbit, forward, custom"):
        camera_path("spiral", OBJECTS, {}, 4)
    f.write_text("poses:\n  - {azimuth: 0, elevation: 0}\n  - {azimuth: 90, elevation: 0}\n")
    with pytest.raises(UserError, match="p.yaml: pose 1: azimuth=90° is outside the range the model was trained on"):
        camera_path("custom", OBJECTS, {}, 3, custom=f)  # the keyframe itself, before any frame is rendered


# -- frames, files -------------------------------------------------------------------------------------------------
def _session(tmp_path) -> ViewSession:
    net = built_net(tmp_path)
    batch = fixture_batch(B=1)
    gallery = [Source("g0", "m_40_10", (batch["src"][0] * 255).to(torch.uint8), {"azimuth": 40.0, "elevation": 10.0})]
    return ViewSession(net, 64, batch["K"][0], batch["pivot"][0], OBJECTS, gallery, torch.bfloat16)


def test_video_frames_show_view_and_depth_and_read_back_with_their_count(tmp_path):
    session = _session(tmp_path)
    path = camera_path("orbit", session.controls, session.gallery["g0"].meta, 9)
    views = render_views(session, "g0", path, progress=False)
    frames = compose_frames(views, scale=2)
    assert len(frames) == 9 and frames[0].shape == (128, 256, 3) and frames[0].dtype == np.uint8
    assert np.array_equal(frames[0][::2, :128:2], views[0].rgb)  # left: the view, upscaled
    depth_panel = frames[0][::2, 128::2]
    assert np.array_equal(depth_panel[..., 0], depth_panel[..., 2])  # right: grey depth
    # one near/far range for the whole video: the nearest pixel of all frames is white, the farthest black
    stack = np.stack([f[::2, 128::2, 0] for f in frames])
    assert stack.max() == 255 and stack.min() == 0
    mp4, gif = write_video(tmp_path / "out" / "orbit", frames, fps=12, formats=["mp4", "gif"])
    assert mp4.name == "orbit.mp4" and gif.name == "orbit.gif"
    assert _read_counts(mp4, gif) == (9, 9)
    with Image.open(gif) as im:
        assert im.size == (256, 128) and abs(im.info["duration"] - 1000 / 12) <= 10  # GIF stores 1/100 s


def test_point_cloud_is_the_depth_lifted_through_K_and_round_trips_through_ply(tmp_path):
    depth = np.full((4, 5), 2.0, np.float32)
    depth[0, 0], depth[1, 1], depth[3, 4] = 0.0, np.nan, 50.0  # no data, no data, far (sky)
    K = np.array([[10.0, 0.0, 2.0], [0.0, 10.0, 1.5], [0.0, 0.0, 1.0]], np.float32)
    rgb = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    xyz, colours = depth_to_points(depth, K, rgb)
    assert len(xyz) == 18  # 20 pixels, two without depth
    # pixel (u=1, v=0) at depth 2: x = (1 - 2) * 2 / 10, y = (0 - 1.5) * 2 / 10 (pixel centres at integers)
    assert np.allclose(xyz[0], [-0.2, -0.3, 2.0]) and np.array_equal(colours[0], rgb[0, 1])
    assert np.allclose(xyz[-1], [(4 - 2) * 50 / 10, (3 - 1.5) * 50 / 10, 50.0])
    near, _ = depth_to_points(depth, K, rgb, max_depth=10.0)
    assert len(near) == 17
    out = write_ply(tmp_path / "c.ply", xyz, colours, ("test cloud",))
    back_xyz, back_rgb = read_ply(out)
    assert np.array_equal(back_xyz, xyz) and np.array_equal(back_rgb, colours)
    assert b"comment test cloud" in out.read_bytes()[:300]


# -- the CLIs on a trained checkpoint ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def checkpoint(objects_root, tmp_path_factory):
    return one_step_checkpoint(objects_root, tmp_path_factory.mktemp("video_run"), "logger=[]")


def _cli_cfg(name: str, tmp_path, ckpt, *overrides):
    cfg = compose_train([f"ckpt_path={ckpt}", f"paths.output_dir={tmp_path}", *overrides], config_name=name)
    return cfg


def test_render_video_cli_writes_mp4_and_gif_with_the_frames_asked_for(checkpoint, tmp_path):
    from nvs.render_video import render

    written = render(_cli_cfg("render_video", tmp_path, checkpoint, "path=orbit", "frames=7", "fps=10",
                              f"out_dir={tmp_path}", "progress=false", "source=m3_40_0"))
    mp4, gif = written
    assert mp4.name == "orbit_m3_40_0.mp4" and _read_counts(mp4, gif) == (7, 7)
    with pytest.raises(UserError, match="path=forward drives the camera forward"):
        render(_cli_cfg("render_video", tmp_path, checkpoint, "path=forward", f"out_dir={tmp_path}"))


def test_render_video_refuses_an_out_of_range_keyframe_before_rendering(checkpoint, tmp_path, monkeypatch):
    import nvs.render_video as rv

    monkeypatch.setattr(rv, "render_views", lambda *a, **k: pytest.fail("rendering started"))
    poses = tmp_path / "poses.yaml"
    poses.write_text("poses:\n  - {azimuth: 0, elevation: 0}\n  - {azimuth: 60, elevation: 10}\n")
    with pytest.raises(UserError, match="poses.yaml: pose 1: azimuth=60° is outside the range"):
        rv.render(_cli_cfg("render_video", tmp_path, checkpoint, "path=custom", f"custom={poses}", "frames=4"))


def test_render_video_writes_beside_the_checkpoint_by_default(checkpoint, tmp_path):
    from nvs.render_video import render, videos_dir

    written = render(_cli_cfg("render_video", tmp_path, checkpoint, "path=orbit", "frames=3", "formats=[gif]",
                              "progress=false", "source=m3_40_0"))
    assert videos_dir(checkpoint) == checkpoint.parent.parent / "videos"
    assert [p.parent for p in written] == [checkpoint.parent.parent / "videos"] and written[0].is_file()
    assert videos_dir("elsewhere/model.ckpt") == Path("elsewhere/videos")


def test_a_refused_render_video_leaves_no_run_folder(checkpoint, tmp_path, monkeypatch):
    code, err = cli_in_process("render_video", [f"ckpt_path={checkpoint}", "path=forward",
                                                f"paths.log_dir={tmp_path / 'runs'}"], monkeypatch)
    assert code == 2 and "path=forward drives the camera forward" in err, err[-2000:]
    assert "Traceback" not in err
    assert not (tmp_path / "runs" / "render_video").exists() or not any((tmp_path / "runs" / "render_video").iterdir())


def test_object_point_clouds_leave_out_the_white_background(tmp_path):
    from types import SimpleNamespace

    from nvs.viewer.cloud import view_points

    rgb = np.full((4, 4, 3), 255, np.uint8)
    rgb[:2] = (200, 30, 30)  # the object: the top half
    rgb[3, 3] = (250, 250, 240)  # not white in every channel: kept
    view = SimpleNamespace(depth_values=np.full((4, 4), 2.0, np.float32), rgb=rgb)
    session = SimpleNamespace(view=lambda key, values: view, K=torch.eye(3)[None], controls=OBJECTS,
                              source=lambda key: SimpleNamespace(label="m_0_0"))
    xyz, colours, _ = view_points(session, "k", {"azimuth": 0.0, "elevation": 0.0})
    assert len(xyz) == 9 and (colours.min(axis=1) < 245).all()
    assert len(view_points(session, "k", {}, keep_background=True)[0]) == 16
    session.controls = SCENES  # a scene has no background: every pixel is a point
    assert len(view_points(session, "k", {})[0]) == 16


def test_export_ply_cli_writes_one_vertex_per_pixel(checkpoint, tmp_path):
    from nvs.export_ply import export

    out = export(_cli_cfg("export_ply", tmp_path, checkpoint, "source=1", "pose={azimuth:20}",
                          f"out={tmp_path / 'v.ply'}", "keep_background=true"))
    xyz, rgb = read_ply(out)
    assert xyz.shape == (64 * 64, 3) and rgb.shape == (64 * 64, 3) and (xyz[:, 2] > 0).all()
    assert b"at azimuth=20, elevation=" in out.read_bytes()[:400]
    with pytest.raises(UserError, match="unknown control"):
        export(_cli_cfg("export_ply", tmp_path, checkpoint, "pose={forward:1}", f"out={tmp_path / 'x.ply'}"))
