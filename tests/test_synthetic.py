"""nvs.data.synthetic: the one synthetic batch follows the data contract and the data configs' cameras."""

import pytest
import torch
from omegaconf import OmegaConf

from nvs.core.geometry import inverse_warp
from nvs.data.synthetic import CAMERAS, blob_images, synthetic_batch, write_objects_root, write_scenes_root
from nvs.run.compose import CONF_DIR


@pytest.mark.parametrize("kind,config", [("objects", "chairs"), ("scenes", "drive")])
def test_cameras_are_the_data_configs(kind, config):
    cam = OmegaConf.load(CONF_DIR / "data" / f"{config}.yaml").camera
    f, c, size, pivot = CAMERAS[kind]
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.size, tuple(cam.pivot)) == (f, f, c, c, size, pivot)


@pytest.mark.parametrize("kind", ["objects", "scenes"])
@pytest.mark.parametrize("images", ["random", "blobs"])
def test_batch_follows_the_contract(kind, images):
    b = synthetic_batch(3, 32, kind, images)
    assert b["src"].shape == b["tgt"].shape == (3, 3, 32, 32)
    assert b["K"].shape == (3, 3, 3) and b["T_tgt_src"].shape == (3, 4, 4) and b["pivot"].shape == (3, 3)
    assert b["depth_src"].shape == b["depth_tgt"].shape == (3, 1, 32, 32)
    assert b["id_src"] == ["a0", "a1", "a2"] and b["id_tgt"] == ["b0", "b1", "b2"]
    for key in ("src", "tgt"):
        assert b[key].min() >= 0 and b[key].max() <= 1
    torch.testing.assert_close(b["T_tgt_src"][:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(3, 4))


def test_objects_defaults_by_hand():
    """64^2: f = 480 / 4, c = (128 + 0.5) / 4 - 0.5; the pose turns 20° about the object centre, which stays put."""
    b = synthetic_batch()
    torch.testing.assert_close(b["K"][0], torch.tensor([[120.0, 0, 31.625], [0, 120.0, 31.625], [0, 0, 1]]))
    centre = torch.tensor([0.0, 0.0, 2.0, 1.0])
    torch.testing.assert_close(b["T_tgt_src"][0] @ centre, centre)
    angle = torch.rad2deg(torch.acos(b["T_tgt_src"][0, 0, 0]))
    assert float(angle) == pytest.approx(20.0, abs=1e-4) and float(b["T_tgt_src"][0, 0, 2]) > 0
    assert torch.equal(b["depth_tgt"], torch.full((2, 1, 64, 64), 2.0))
    assert b["K"][0, 0, 0] == synthetic_batch(S=128)["K"][0, 0, 0] / 2  # K is at the batch's resolution


def test_scenes_defaults_drive_forward():
    b = synthetic_batch(kind="scenes")
    torch.testing.assert_close(b["T_tgt_src"][0, :3, 3], torch.tensor([0.0, 0.0, -0.02]))
    assert torch.equal(b["pivot"], torch.zeros(2, 3)) and float(b["depth_src"].max()) == pytest.approx(0.4)


def test_seeds_overrides_and_errors():
    a, b, c = synthetic_batch(seed=0), synthetic_batch(seed=0), synthetic_batch(seed=1)
    assert torch.equal(a["src"], b["src"]) and not torch.equal(a["src"], c["src"])
    assert not torch.equal(a["src"], a["tgt"])
    r = synthetic_batch(depth=(1.5, 2.5), focal=7.0, centre=3.0)
    assert 1.5 <= float(r["depth_tgt"].min()) and float(r["depth_tgt"].max()) < 2.5
    assert not torch.equal(r["depth_src"], r["depth_tgt"])
    assert r["K"][0, 0, 0] == 7.0 and r["K"][0, 1, 2] == 3.0
    own = synthetic_batch(1, 8, images=(torch.zeros(1, 3, 8, 8), torch.ones(1, 3, 8, 8)), pose=torch.eye(4))
    assert own["tgt"].min() == 1 and torch.equal(own["T_tgt_src"][0], torch.eye(4))
    with pytest.raises(ValueError, match="images must both have shape"):
        synthetic_batch(2, 8, images=(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 8)))
    with pytest.raises(ValueError, match="kind must be one of"):
        synthetic_batch(kind="indoor")
    with pytest.raises(ValueError, match="images must be one of"):
        synthetic_batch(images="noise")


def test_blobs_are_flat_rectangles_on_white():
    img = blob_images(2, 32)
    assert float(img.max()) == 1.0 and (img == 1).float().mean() > 0.2  # white background
    assert len(torch.unique(img[0, 0])) <= 5  # white plus at most four flat colours


def test_identity_pose_reproduces_the_source():
    b = synthetic_batch(pose=torch.eye(4))
    warped, valid = inverse_warp(b["src"], b["depth_tgt"], b["K"], b["T_tgt_src"])
    assert valid.min() == 1
    torch.testing.assert_close(warped, b["src"], atol=1e-5, rtol=0)


def test_fixture_writers_write_both_formats(tmp_path):
    objects = write_objects_root(tmp_path / "o", models=("a", "b"), size=16)
    assert len(list((objects / "images").glob("*.png"))) == 2 * 18 * 3 == len(list((objects / "depth").glob("*")))
    assert (objects / "id_train.txt").read_text() == "a\n"
    assert (objects / "eval_chair_40.txt").read_text().splitlines()[0] == "b_0_0 b_20_10"
    scenes = write_scenes_root(tmp_path / "s", n_seq=2, n_frames=3, size=16, depth=False)
    assert len((scenes / "poses.txt").read_text().splitlines()) == 6 and not (scenes / "depth").exists()
    assert (scenes / "eval_kitti.txt").read_text().splitlines() == ["01_000000 01_000001", "01_000001 01_000002"]
