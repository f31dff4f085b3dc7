"""Loaders read both on-disk formats and fail with one clear error naming the file (and line)."""

import numpy as np
import pytest
import torch

from nvs.core.errors import DataError
from nvs.data.datamodule import Camera, LoaderSettings, NVSDataModule
from nvs.data.kitti import ScenesFormat
from nvs.data.shapenet import ObjectsFormat, parse_stem
from tests.conftest import make_objects_root, make_scenes_root

CAM_OBJ = Camera(fx=480, fy=480, cx=128, cy=128, size=256, pivot=(0.0, 0.0, 2.0))
CAM_SCN = Camera(fx=160, fy=160, cx=128, cy=128, size=256)


def _dm(fmt, cam, **kw):
    return NVSDataModule(fmt, cam, 64, LoaderSettings(batch_size=2, eval_batch_size=2, **kw), seed=0)


def test_objects_batch_contract(objects_root):
    dm = _dm(ObjectsFormat(objects_root, "chair"), CAM_OBJ)
    batch = next(iter(dm.train_dataloader()))
    assert batch["src"].shape == (2, 3, 64, 64) and batch["src"].dtype == torch.float32
    assert 0 <= batch["src"].min() and batch["src"].max() <= 1
    assert batch["K"].shape == (2, 3, 3) and batch["K"][0, 0, 0] == 120.0
    assert batch["T_tgt_src"].shape == (2, 4, 4) and batch["depth_tgt"].shape == (2, 1, 64, 64)
    for s, t in zip(batch["id_src"], batch["id_tgt"]):
        ms, azs, _ = parse_stem(s)
        mt, azt, _ = parse_stem(t)
        assert ms == mt and s != t and min(abs(azs - azt) % 360, 360 - abs(azs - azt) % 360) <= 40


def test_objects_splits_are_disjoint_and_val_carved(objects_root):
    fmt = ObjectsFormat(objects_root, "chair")
    train, val = fmt.split_models("train", 0.34, 0), fmt.split_models("val", 0.34, 0)
    assert set(train).isdisjoint(val) and len(val) == 1 and len(train) == 2
    assert fmt.split_models("val", 0.34, 0) == val  # deterministic
    test = _dm(fmt, CAM_OBJ).dataset("test")
    assert len(test) == 4 and test[0]["id_src"] == "m3_0_0"


def test_object_pose_direction_matches_paper_formula(objects_root):
    fmt = ObjectsFormat(objects_root, "chair")
    T = fmt.pose("m0_20_0", "m0_0_0").double()
    c = torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
    # The object centre is fixed by every object-centric relative pose.
    torch.testing.assert_close(T[:3, :3] @ c + T[:3, 3], c)
    torch.testing.assert_close(fmt.pose("m0_0_0", "m0_0_0"), torch.eye(4))


def test_scenes_batch_and_pose_scale(scenes_root):
    fmt = ScenesFormat(scenes_root, translation_scale=0.02)
    dm = _dm(fmt, CAM_SCN)
    item = dm.dataset("test")[0]
    # frame f is at z = f metres; target = next frame: source points move 1 m * 0.02 closer.
    assert item["T_tgt_src"][2, 3] == pytest.approx(-0.02, abs=1e-4)  # small yaw between frames
    assert item["depth_tgt"].max() == pytest.approx(20.0 * 0.02)
    assert item["K"][0, 0] == 40.0
    assert set(dm.dataset("train").pairs).isdisjoint(dm.dataset("val").pairs)


def test_trailing_separator_in_poses_is_accepted(tmp_path):
    root = make_scenes_root(tmp_path / "d", n_seq=1, n_frames=3)
    text = (root / "poses.txt").read_text().replace("\n", " \n")
    (root / "poses.txt").write_text(text)
    assert len(ScenesFormat(root).poses) == 3


@pytest.mark.parametrize("line, msg", [
    ("00_000001 0 0 0 0 0", "7 fields"),
    ("00_000001 0 0 nan 0 0 1", "not finite"),
    ("00_000001 0 0 x 0 0 1", "not a number"),
    ("00_000000 0 0 0 0 0 1", "duplicated frame id"),
])
def test_malformed_pose_line_names_file_and_line(tmp_path, line, msg):
    root = make_scenes_root(tmp_path / "d", n_seq=1, n_frames=3)
    lines = (root / "poses.txt").read_text().splitlines()
    lines[1] = line
    (root / "poses.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=rf"poses.txt:2: .*{msg}"):
        ScenesFormat(root)


def test_unknown_and_duplicated_pair_ids(tmp_path):
    root = make_scenes_root(tmp_path / "d", n_seq=1, n_frames=3)
    (root / "eval_kitti.txt").write_text("00_000000 00_000001\n00_000000 99_000001\n")
    with pytest.raises(DataError, match=r"eval_kitti.txt:2: unknown id '99_000001'"):
        ScenesFormat(root).pairs("test", 0.1, 0)
    (root / "eval_kitti.txt").write_text("00_000000 00_000001\n00_000000 00_000001\n")
    with pytest.raises(DataError, match=r"eval_kitti.txt:2: duplicated pair"):
        ScenesFormat(root).pairs("test", 0.1, 0)


def test_empty_split(tmp_path):
    root = make_objects_root(tmp_path / "c", models=("m0", "m1"))
    (root / "id_train.txt").write_text("\n")
    with pytest.raises(DataError, match=r"id_train.txt: no ids: the split is empty"):
        ObjectsFormat(root, "chair").split_models("train", 0.1, 0)


def test_missing_corrupt_and_wrong_mode_images(tmp_path):
    root = make_objects_root(tmp_path / "c", models=("m0", "m1"))
    fmt = ObjectsFormat(root, "chair")
    (root / "images" / "m0_0_0.png").unlink()
    with pytest.raises(DataError, match=r"m0_0_0.png: image file is missing"):
        fmt.read("m0_0_0", 64, False)
    data = (root / "images" / "m0_20_0.png").read_bytes()
    (root / "images" / "m0_20_0.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match=r"m0_20_0.png: cannot read image"):
        fmt.read("m0_20_0", 64, False)
    from PIL import Image

    Image.fromarray(np.zeros((64, 64), np.uint16)).save(root / "images" / "m0_40_0.png")
    with pytest.raises(DataError, match=r"m0_40_0.png: unsupported image mode"):
        fmt.read("m0_40_0", 64, False)
    Image.fromarray(np.zeros((64, 32, 3), np.uint8)).save(root / "images" / "m0_60_0.png")
    with pytest.raises(DataError, match=r"m0_60_0.png: image is 32x64; expected a square"):
        fmt.read("m0_60_0", 64, False)


def test_resize_and_depth_downsampling(objects_root):
    img, depth = ObjectsFormat(objects_root, "chair").read("m0_0_0", 32, True)
    assert img.shape == (3, 32, 32) and img.dtype == torch.uint8 and depth.shape == (1, 32, 32)


def test_mirrored_pair_warps_to_the_mirrored_warp():
    """Warping a mirrored pair equals mirroring the warped pair: K, pose and pivot are mirrored consistently."""
    from nvs.core.geometry import inverse_warp
    from nvs.data.datamodule import mirror_pair

    g = torch.Generator().manual_seed(0)
    H = W = 32
    K = torch.tensor([[40.0, 0.0, 13.7], [0.0, 40.0, 16.2], [0.0, 0.0, 1.0]])
    a, b = 0.1, -0.05
    Ry = torch.tensor([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]], dtype=torch.float32)
    Rx = torch.tensor([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]], dtype=torch.float32)
    T = torch.eye(4)
    T[:3, :3], T[:3, 3] = Ry @ Rx, torch.tensor([0.1, -0.05, 0.1])
    item = {"src": torch.rand(3, H, W, generator=g), "tgt": torch.rand(3, H, W, generator=g),
            "depth_src": 2 + torch.rand(1, H, W, generator=g), "depth_tgt": 2 + torch.rand(1, H, W, generator=g),
            "K": K, "T_tgt_src": T, "pivot": torch.tensor([0.5, 0.0, 2.0])}
    m = mirror_pair(item)
    warped, valid = inverse_warp(item["src"][None], item["depth_tgt"][None], K[None], T[None])
    warped_m, valid_m = inverse_warp(m["src"][None], m["depth_tgt"][None], m["K"][None], m["T_tgt_src"][None])
    assert valid.sum() > 0.5 * H * W
    torch.testing.assert_close(valid_m, valid.flip(-1))
    torch.testing.assert_close(warped_m * valid_m, (warped * valid).flip(-1), atol=1e-4, rtol=0)
    assert m["pivot"].tolist() == [-0.5, 0.0, 2.0]
    assert mirror_pair(m)["T_tgt_src"].allclose(T) and mirror_pair(m)["K"].allclose(K)


def test_augmentation_treats_both_views_alike_and_only_in_training(objects_root):
    from nvs.data.datamodule import PairDataset, ViewCache

    fmt = ObjectsFormat(objects_root, "chair")
    cache = ViewCache(fmt, 64, True, True)
    fid = "m0_0_0"
    ds = PairDataset(cache, CAM_OBJ, pairs=[(fid, fid)] * 40, augment={"mirror": True, "permute_rgb": True})
    plain = PairDataset(cache, CAM_OBJ, pairs=[(fid, fid)])[0]["src"]
    torch.manual_seed(0)
    changed = 0
    for i in range(len(ds)):
        item = ds[i]
        assert torch.equal(item["src"], item["tgt"]) and torch.equal(item["depth_src"], item["depth_tgt"])
        changed += not torch.equal(item["src"], plain)
    assert 20 < changed < 40  # identity permutation and no flip together: 1 in 12
    dm = _dm(fmt, CAM_OBJ, augment={"mirror": True})
    assert dm.dataset("train").augment and not dm.dataset("test").augment


def test_unknown_augmentation_key_is_named():
    with pytest.raises(Exception, match="data.loader.augment.*'flip'"):
        LoaderSettings(augment={"flip": True})
