"""The depth floors: a constant plane at the training views' mean depth, and each image's plane at its ground-truth
mean (an oracle); both warp the source like gt_warp."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf
import torch

from nvs.core.errors import UserError
from nvs.data.synthetic import write_objects_root, write_scenes_root
from nvs.models.reference import GroundTruthWarp
from nvs.models.reference_planes import ConstantDepthWarp, GroundTruthPlaneWarp
from nvs.run.mean_depth import training_mean_depth
from tests.conftest import compose_train, fixture_batch
from tests.run_helpers import cli_in_process

TRAIN_DEPTHS = {"m0": 1.5, "m1": 2.5, "m2": 3.5}  # the test model m3 gets 100: the floor must never see it


def _objects(root: Path) -> Path:
    write_objects_root(root)
    half = np.zeros((64, 64), np.float32)
    half[:, 32:] = 1.0  # half of every view is background (0): only the other half counts
    for f in (root / "depth").glob("*.npy"):
        np.save(f, half * TRAIN_DEPTHS.get(f.stem.rsplit("_", 2)[0], 100.0))
    return root


def _data(cfg) -> dict:
    return OmegaConf.to_container(cfg.data, resolve=True)  # what conf/model/mean_depth.yaml passes: the data node


def test_training_mean_reads_the_training_views_only(tmp_path):
    root = _objects(tmp_path / "objects")
    cfg = compose_train(["data=chairs", f"data.root={root}"])
    from nvs.run.build import build_data

    train_models = build_data(cfg).fmt.split_models("train", cfg.data.loader.val_fraction, 0)
    assert 0 < len(train_models) <= 3  # validation is carved from the training list
    expected = sum(TRAIN_DEPTHS[m] for m in train_models) / len(train_models)
    assert training_mean_depth(_data(cfg)) == pytest.approx(expected)
    # data.train_fraction takes its seeded subset of the training models
    one = _data(cfg) | {"train_fraction": 1 / len(train_models)}
    assert training_mean_depth(one) in [pytest.approx(TRAIN_DEPTHS[m]) for m in train_models]


def test_training_mean_of_scenes_is_in_scaled_units(tmp_path):
    root = write_scenes_root(tmp_path / "scenes")  # constant depth 20 m
    cfg = compose_train(["data=drive", f"data.root={root}"])
    assert training_mean_depth(_data(cfg)) == pytest.approx(20.0 * cfg.data.translation_scale)


def test_training_mean_without_depth_is_one_clear_error(tmp_path):
    root = write_objects_root(tmp_path / "nodepth", depth=False)
    with pytest.raises(UserError, match="no depth/ files"):
        training_mean_depth(_data(compose_train(["data=chairs", f"data.root={root}"])))


def test_planes_warp_as_gt_warp_does_with_that_depth():
    batch = fixture_batch(B=2)
    gt = batch["depth_tgt"].clone()
    gt[0, :, :, :32] = 0.0  # background: left out of the mean
    gt[0, :, :, 32:] = 3.0
    gt[1] = 1.5
    batch["depth_tgt"] = gt
    out = GroundTruthPlaneWarp(image_size=64)(batch)
    assert torch.allclose(out["depth"][0], torch.full_like(gt[0], 3.0))
    assert torch.allclose(out["depth"][1], torch.full_like(gt[1], 1.5))
    # the same image as warping with ground truth that is that plane
    plane = dict(batch, depth_tgt=out["depth"])
    assert torch.allclose(out["rgb"], GroundTruthWarp(image_size=64)(plane)["rgb"])
    const = ConstantDepthWarp(depth=2.25, image_size=64)(batch)
    assert torch.all(const["depth"] == 2.25) and const["rgb"].shape == batch["src"].shape
    assert torch.allclose(const["rgb"], GroundTruthWarp(image_size=64)(dict(batch, depth_tgt=const["depth"]))["rgb"])
    # scenes (a sky disparity): pixels with no correspondence keep the source, as gt_warp's
    sky = ConstantDepthWarp(depth=2.25, image_size=64, sky_disparity=0.01)(batch)
    assert torch.allclose(sky["rgb"], GroundTruthWarp(image_size=64, sky_disparity=0.01)(
        dict(batch, depth_tgt=const["depth"]))["rgb"])
    with pytest.raises(ValueError, match="positive"):
        ConstantDepthWarp(depth=0.0)
    no_depth = dict(batch, depth_tgt=torch.zeros_like(gt))
    with pytest.raises(ValueError, match="no valid ground-truth depth"):
        GroundTruthPlaneWarp()(no_depth)


@pytest.mark.parametrize("model", ["mean_depth", "gt_plane"])
def test_the_reference_options_compose_for_every_dataset(model):
    for data in ("chairs", "cars", "drive"):
        cfg = compose_train([f"model={model}", f"data={data}"], config_name="evaluate")
        assert cfg.model.name == model and cfg.model.image_size == cfg.data.size
        if model == "mean_depth":
            assert cfg.model.data == cfg.data  # the run's own data node, read as the run reads it


def test_evaluating_the_floor_uses_no_test_ground_truth(tmp_path, monkeypatch):
    root = _objects(tmp_path / "objects")
    out = tmp_path / "eval"
    code, err = cli_in_process("evaluate", ["model=mean_depth", "data=chairs", f"data.root={root}",
                                            f"hydra.run.dir={out}", "+trainer.enable_progress_bar=false"], monkeypatch)
    assert code == 0, err[-3000:]
    metrics = json.loads((out / "metrics.json").read_text())
    mean = float(err.split("mean depth under")[1].split(":")[1].split()[0])
    assert 1.5 <= mean <= 3.5 and metrics["model"] == "mean_depth"
    # the test chair's depth is 100 everywhere it has any: the floor is 100 - mean off
    assert metrics["test"]["depth_l1"] == pytest.approx(100 - mean, rel=1e-4)
