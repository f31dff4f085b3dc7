"""The interactive viewer: encode/render split, poses from the data modules' functions, uploads, the loopback-only
server, the load script, and a real browser (Debian's chromium driven by Playwright) dragging and uploading."""

import io
import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from nvs.core.errors import UserError
from nvs.core.types import Extras
from nvs.data.datamodule import build_datamodule
from nvs.data.kitti import ScenesFormat
from nvs.data.shapenet import ObjectsFormat
from nvs.viewer.controls import ObjectControls, SceneControls, build_controls
from nvs.viewer.images import decode_upload
from nvs.viewer.load import measure
from nvs.viewer.process import ViewerProcess
from nvs.viewer.address import check_address
from nvs.viewer.session import Source, ViewSession
from tests.conftest import fixture_batch
from tests.viewer_helpers import built_net, one_step_checkpoint

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")


_net = built_net


def _png(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


# -- the network split ---------------------------------------------------------------------------------------------
def test_render_of_encode_is_forward_exactly(tmp_path):
    net = _net(tmp_path)
    batch = fixture_batch()
    needs = frozenset({Extras.DEPTH_FROM_TGT, Extras.DEPTH_SRC, Extras.WARPED_SRC})
    with torch.no_grad():
        whole = net(batch, needs)
        split = net.render(net.encode(batch["src"]), batch, needs)
    assert set(whole) == set(split)
    for key in ("rgb", "depth", Extras.DEPTH_FROM_TGT, Extras.DEPTH_SRC, Extras.WARPED_SRC):
        assert torch.equal(whole[key], split[key]), key


# -- poses ---------------------------------------------------------------------------------------------------------
def test_object_pose_is_the_datasets_pose(objects_root):
    fmt = ObjectsFormat(objects_root, "chair")
    controls = ObjectControls(40, (0.0, 0.0, 2.0))
    meta = controls.source_meta("m3_40_0")
    assert torch.equal(controls.pose({"azimuth": 20, "elevation": 10}, meta), fmt.pose("m3_60_10", "m3_40_0"))
    assert torch.equal(controls.pose({"azimuth": -40, "elevation": 20}, meta), fmt.pose("m3_0_20", "m3_40_0"))
    assert torch.allclose(controls.pose(controls.initial(meta), meta), torch.eye(4), atol=1e-6)
    ranges = {ax.name: (ax.min, ax.max) for ax in controls.axes}
    assert ranges == {"azimuth": (-40.0, 40.0), "elevation": (0.0, 20.0)}


@pytest.mark.parametrize("values, message", [({"azimuth": 41, "elevation": 0}, "azimuth=41° is outside"),
                                             ({"azimuth": 0, "elevation": -10}, "elevation=-10° is outside"),
                                             ({"azimuth": float("nan"), "elevation": 0}, "azimuth=nan"),
                                             ({"azimuth": 0}, "missing pose value 'elevation'")])
def test_poses_outside_the_trained_range_are_one_clear_error(values, message):
    with pytest.raises(UserError, match=message):
        ObjectControls(40, (0.0, 0.0, 2.0)).pose(values, {"azimuth": 0.0, "elevation": 0.0})


def test_scene_ranges_come_from_the_training_pairs_and_forward_moves_the_camera(scenes_root):
    fmt = ScenesFormat(scenes_root, translation_scale=0.02)
    controls = SceneControls.from_pairs(fmt.poses, fmt.pairs("train", 0.1, 0), fmt.translation_scale)
    ranges = {ax.name: (ax.min, ax.max) for ax in controls.axes}
    # The fixture's frames are 1 m apart along the path, turning 0.01 rad per frame; pairs are consecutive frames.
    assert ranges["forward"] == (0.0, 1.0) and -0.1 <= ranges["sideways"][0] < 0.0 == ranges["sideways"][1]
    T = controls.pose({"forward": 1.0, "sideways": 0.0}, {})
    point = T @ torch.tensor([0.0, 0.0, 0.4, 1.0])  # 20 m ahead, in the data's scaled units
    assert torch.allclose(point, torch.tensor([0.0, 0.0, 0.38, 1.0]))  # 1 m closer after moving 1 m forward
    right = controls.pose({"forward": 0.0, "sideways": ranges["sideways"][0]}, {}) @ torch.tensor([0.0, 0, 0.4, 1])
    assert right[0] > 0  # the camera moved left: the point is now to its right


def test_each_data_format_gets_its_controls(objects_root, scenes_root):
    camera = {"fx": 480.0, "fy": 480.0, "cx": 128.0, "cy": 128.0, "size": 256, "pivot": [0.0, 0.0, 2.0]}
    objects = build_datamodule("objects", str(objects_root), 64, camera, {}, category="chair", max_delta_azimuth=20)
    assert isinstance(build_controls("objects", objects), ObjectControls)
    assert build_controls("objects", objects).axes[0].max == 20.0
    scenes = build_datamodule("scenes", str(scenes_root), 64, {**camera, "pivot": [0.0, 0.0, 0.0]}, {},
                              translation_scale=0.02)
    assert [ax.name for ax in build_controls("scenes", scenes).axes] == ["sideways", "forward"]
    with pytest.raises(UserError, match="controls for 'objects' and 'scenes'"):
        build_controls("meshes", scenes)


# -- uploads -------------------------------------------------------------------------------------------------------
def test_upload_is_centre_cropped_resized_and_alpha_on_white():
    img = np.zeros((200, 300, 3), np.uint8)
    img[:] = (0, 0, 255)
    img[:, 40:260] = (255, 0, 0)  # the centre square is columns 50..250; the resampling filter reaches a little beyond
    out = decode_upload(_png(img), 64)
    assert out.shape == (3, 64, 64) and out.dtype == torch.uint8
    assert (out[0] > 250).all() and (out[2] < 5).all()  # only the red centre is left
    rgba = np.zeros((32, 32, 4), np.uint8)  # fully transparent
    assert (decode_upload(_png(rgba), 64) == 255).all()


@pytest.mark.parametrize("data, message", [(b"just some text", "notes.txt is not an image"),
                                           (b"", "notes.txt: the file is empty"),
                                           (_png(np.random.default_rng(0).integers(0, 255, (64, 64, 3), np.uint8))
                                            [:2000], "notes.txt: the image cannot be read")])
def test_a_file_that_is_not_an_image_is_one_clear_error(data, message):
    with pytest.raises(UserError, match=message):
        decode_upload(data, 64, "notes.txt")


# -- the session -----------------------------------------------------------------------------------------------------
def _session(net, autocast=torch.bfloat16, compiled=False) -> ViewSession:
    batch = fixture_batch(B=2)
    gallery = [Source(f"g{i}", f"m_{40 * i}_0", (batch["src"][i] * 255).to(torch.uint8), {"azimuth": 40.0 * i,
                                                                                          "elevation": 0.0})
               for i in range(2)]
    return ViewSession(net, 64, batch["K"][0], batch["pivot"][0], ObjectControls(40, (0.0, 0.0, 2.0)), gallery,
                       autocast, compiled=compiled)


def _views(session, azimuths=(0.0, 15.0, 30.0)):
    return [session.view("g0", {"azimuth": a, "elevation": 0.0}) for a in azimuths]


def test_a_compile_that_fails_stays_eager_with_one_line(tmp_path, monkeypatch, capsys):
    net = _net(tmp_path)
    eager = _views(_session(net, None))

    def broken(fn, **kwargs):
        def run(*args, **kw):
            raise RuntimeError("no C++ compiler")
        return run

    monkeypatch.setattr(torch, "compile", broken)
    session = _session(net, None, compiled=True)
    assert session.compiled
    views = _views(session)
    assert not session.compiled and capsys.readouterr().out.count("torch.compile failed (RuntimeError") == 1
    assert all(np.array_equal(a.rgb, b.rgb) for a, b in zip(views, eager))
    assert not _session(_net(tmp_path, "model=tatarchenko"), None, compiled=True).compiled  # not split: whole net


@pytest.mark.slow  # ~1 min: inductor compiles the pose step
def test_the_compiled_pose_step_renders_the_eager_views(tmp_path):
    net = _net(tmp_path)
    eager = _views(_session(net, None))
    session = _session(net, None, compiled=True)
    views = _views(session)
    assert session.compiled
    for a, b in zip(views, eager):  # float32; constant folding reorders sums: within one grey level
        assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max() <= 1
        assert np.abs(a.depth_values - b.depth_values).max() <= 1e-3 * np.abs(b.depth_values).max()


@pytest.mark.parametrize("autocast", [torch.bfloat16, None])
def test_the_encoder_runs_once_per_source(tmp_path, autocast):
    session = _session(_net(tmp_path), autocast)
    views = [session.view("g0", {"azimuth": a, "elevation": 0.0}) for a in (0.0, 20.0, 40.0)]
    assert session.encoder_runs == 1 and [v.encoded for v in views] == [True, False, False]
    assert views[0].rgb.shape == (64, 64, 3) and views[0].depth.shape == (64, 64)
    assert not np.array_equal(views[0].rgb, views[2].rgb)  # the pose changes the view
    session.view("g1", {"azimuth": 0.0, "elevation": 10.0})
    session.view("g0", {"azimuth": -10.0, "elevation": 10.0})
    assert session.encoder_runs == 2
    with torch.no_grad():  # the split view is the whole network's forward (float32: exact up to rounding to uint8)
        if autocast is None:
            T = session.controls.pose({"azimuth": 20.0, "elevation": 0.0}, session.gallery["g0"].meta)[None]
            batch = {"src": session.gallery["g0"].image[None].float() / 255, "K": session.K, "T_tgt_src": T,
                     "pivot": session.pivot}
            ref = (session.net(batch)["rgb"][0].clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0)
            assert np.abs(ref.numpy().astype(int) - views[1].rgb.astype(int)).max() <= 1


def test_uploads_and_networks_that_do_not_split(tmp_path):
    session = _session(_net(tmp_path, "model=tatarchenko"))
    assert not session.splits
    img = np.full((90, 120, 3), 200, np.uint8)
    source = session.add_upload(_png(img), "photo.png")
    assert session.add_upload(_png(img), "photo.png").key == source.key  # same bytes, same source
    view = session.view(source.key, {"azimuth": 10.0, "elevation": 0.0})
    assert view.rgb.shape == (64, 64, 3) and view.depth is None and session.encoder_runs == 0
    with pytest.raises(UserError, match="unknown source 'nope'"):
        session.view("nope", {"azimuth": 0.0, "elevation": 0.0})


# -- server start-up -----------------------------------------------------------------------------------------------
def test_loopback_only_and_a_taken_port_is_one_clear_error(tmp_path):
    with pytest.raises(UserError, match="loopback address only"):
        check_address("0.0.0.0", 8765)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(UserError, match=f"port {port} on 127.0.0.1 is already in use"):
            check_address("127.0.0.1", port)
        # python -m nvs.viewer, reporting which heavy libraries it had loaded when it exited
        code = ("import runpy, sys; sys.argv = sys.argv[1:]\n"
                "try:\n    runpy.run_module('nvs.viewer', run_name='__main__')\n"
                "except SystemExit as e:\n"
                "    print('exit', e.code, [m for m in ('torch', 'lightning', 'aiohttp') if m in sys.modules])")
        res = subprocess.run([sys.executable, "-c", code, "nvs.viewer", "ckpt_path=any.ckpt", f"port={port}",
                              f"hydra.run.dir={tmp_path}"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert "already in use" in res.stderr and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert res.stdout.strip().splitlines()[-1] == "exit 2 []"  # said before the model and its libraries load


# -- a real server: the load script and a real browser -------------------------------------------------------------
@pytest.fixture(scope="module")
def viewer_url(objects_root, tmp_path_factory):
    """A checkpoint trained for one step in this test, served by ``python -m nvs.viewer`` on a free port."""
    out = tmp_path_factory.mktemp("viewer_run")
    ckpt = one_step_checkpoint(objects_root, out, "channels_last=true")
    with ViewerProcess([f"ckpt_path={ckpt}", f"hydra.run.dir={out / 'viewer'}", "gallery=3"], cwd=REPO) as url:
        yield url


def test_load_script_measures_views_through_the_endpoint(viewer_url):
    result = measure(viewer_url, requests=4, warmup=1)
    assert result["image_size"] == 64 and result["requests"] == 4 and result["views_per_s"] > 0
    assert result["encoder_reruns"] == 0 and result["switch_median_ms"] is not None
    assert result["model_median_ms"] <= result["server_median_ms"] <= result["median_ms"]


def test_point_cloud_and_video_endpoints(viewer_url, tmp_path):
    import base64
    import urllib.error
    import urllib.request

    import imageio_ffmpeg

    from nvs.report.pointcloud import read_ply

    with urllib.request.urlopen(f"{viewer_url}api/ply?source=g1&azimuth=20&elevation=10", timeout=60) as r:
        assert r.headers["Content-Disposition"].startswith('attachment; filename="') and ".ply" in \
            r.headers["Content-Disposition"]
        xyz, rgb = read_ply(io.BytesIO(r.read()))
    # every pixel but those rendered as the white background (an object model's cloud leaves them out)
    assert 0 < len(xyz) <= 64 * 64 and rgb.shape == xyz.shape and (xyz[:, 2] > 0).all()
    assert (rgb.min(axis=1) < 245).all()
    with urllib.request.urlopen(f"{viewer_url}api/video?source=g0&path=orbit&frames=5&fps=10", timeout=120) as r:
        clip = json.loads(r.read())
    assert clip["frames"] == 5
    gif = base64.b64decode(clip["gif"].split(",", 1)[1])
    with Image.open(io.BytesIO(gif)) as im:
        assert im.n_frames == 5 and im.size == (256, 128)  # view | depth, 64² upscaled 2x
    mp4 = tmp_path / "v.mp4"
    mp4.write_bytes(base64.b64decode(clip["mp4"].split(",", 1)[1]))
    assert imageio_ffmpeg.count_frames_and_secs(str(mp4))[0] == 5
    with pytest.raises(urllib.error.HTTPError) as err:  # objects have no forward path: one clear error
        urllib.request.urlopen(f"{viewer_url}api/video?source=g0&path=forward&frames=5", timeout=60)
    assert err.value.code == 400 and "path=forward" in json.loads(err.value.read())["error"]


@pytest.mark.skipif(not CHROMIUM.is_file(), reason="needs Debian's chromium at /usr/bin/chromium "
                                                    "(scripts/install_assets.sh installs it)")
def test_browser_drag_changes_the_view_and_a_bad_upload_shows_an_error(viewer_url):
    from playwright.sync_api import expect, sync_playwright

    idle = "document.body.dataset.busy === 'false' && +document.body.dataset.views >= {}"
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True)
        page = browser.new_page()
        page_errors = []
        page.on("pageerror", lambda err: page_errors.append(str(err)))
        page.goto(viewer_url)
        page.wait_for_function(idle.format(1), timeout=30_000)
        expect(page.locator("#controls")).to_contain_text("trained range -40° … 40°")
        before = page.get_attribute("#synth", "src")
        views = int(page.get_attribute("body", "data-views"))
        assert before.startswith("data:image/png") and page.get_attribute("#depth", "src").startswith("data:image")

        box = page.locator("#drag").bounding_box()
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        page.mouse.move(x, y)
        page.mouse.down()
        page.mouse.move(x + box["width"] / 3, y - box["height"] / 3, steps=8)
        page.mouse.up()
        page.wait_for_function(idle.format(views + 1), timeout=30_000)
        assert page.get_attribute("#synth", "src") != before
        assert float(page.input_value("#axis-azimuth")) > 20 and float(page.input_value("#axis-elevation")) > 0
        expect(page.locator("#error")).to_be_hidden()
        expect(page.locator("#stats")).to_contain_text("ms end to end")

        page.set_input_files("#upload", files=[{"name": "notes.txt", "mimeType": "text/plain",
                                                 "buffer": b"not an image"}])
        expect(page.locator("#error")).to_contain_text("Upload failed: notes.txt is not an image")

        # The server kept running: a real upload becomes the source and renders.
        views = int(page.get_attribute("body", "data-views"))
        photo = np.zeros((48, 80, 3), np.uint8)
        photo[:, 20:60] = (30, 160, 60)
        page.set_input_files("#upload", files=[{"name": "photo.png", "mimeType": "image/png", "buffer": _png(photo)}])
        page.wait_for_function(idle.format(views + 1), timeout=30_000)
        expect(page.locator("#source-label")).to_have_text("photo.png")
        expect(page.locator("#error")).to_be_hidden()

        # Export: the point-cloud button downloads a PLY of this view; the video button shows the clip.
        with page.expect_download(timeout=30_000) as download:
            page.click("#ply-button")
        assert download.value.suggested_filename.startswith("photo_") and \
            download.value.suggested_filename.endswith(".ply")
        page.fill("#video-frames", "4")
        page.click("#video-button")
        page.wait_for_function("document.body.dataset.video === 'done'", timeout=60_000)
        expect(page.locator("#video-figure")).to_be_visible()
        expect(page.locator("#video-note")).to_contain_text("4 frames")
        assert page.get_attribute("#video", "src").startswith("data:image/gif")
        assert page.get_attribute("#video-mp4", "href").startswith("data:video/mp4")
        expect(page.locator("#error")).to_be_hidden()
        browser.close()
    assert not page_errors
