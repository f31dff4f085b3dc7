"""The data contract of nvs.core.types holds for what the loaders yield and what every network returns."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from nvs.core.types import RGB_BRANCHES, Batch, Extras, Outputs
from nvs.run.build import build_data, build_module
from tests.conftest import compose_train, fixture_batch

EXTRAS = frozenset({Extras.DEPTH_FROM_TGT, Extras.DEPTH_SRC, Extras.WARPED_SRC})


def test_the_contract_names_the_keys_it_documents():
    assert Batch.__required_keys__ == {"src", "tgt", "K", "T_tgt_src", "pivot"}
    assert Batch.__optional_keys__ == {"depth_src", "depth_tgt", "id_src", "id_tgt", "index"}
    assert Outputs.__required_keys__ == {"rgb", "rgb_scales"}
    assert EXTRAS | {RGB_BRANCHES} <= Outputs.__optional_keys__


def _check_batch(batch: dict, B: int, S: int) -> None:
    assert Batch.__required_keys__ <= set(batch) <= Batch.__required_keys__ | Batch.__optional_keys__
    for key in ("src", "tgt"):
        assert batch[key].shape == (B, 3, S, S) and 0 <= batch[key].min() and batch[key].max() <= 1
    assert batch["K"].shape == (B, 3, 3) and batch["T_tgt_src"].shape == (B, 4, 4) and batch["pivot"].shape == (B, 3)
    for key in ("depth_src", "depth_tgt"):
        if key in batch:
            assert batch[key].shape == (B, 1, S, S)


def test_the_synthetic_batch_follows_the_contract():
    _check_batch(fixture_batch(B=3, S=32), 3, 32)


@pytest.mark.parametrize("data,root", [("chairs", "objects_root"), ("drive", "scenes_root")])
def test_each_data_format_yields_the_contract(data, root, request, tmp_path):
    cfg = compose_train([f"data={data}", f"data.root={request.getfixturevalue(root)}", f"paths.root_dir={tmp_path}",
                         "data.loader.batch_size=2"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    dm = build_data(cfg)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    _check_batch(batch, 2, cfg.data.size)
    assert len(batch["id_src"]) == 2 and len(batch["id_tgt"]) == 2


@pytest.mark.parametrize("model", ["nvs", "chen", "sun", "tatarchenko", "copy_source", "gt_warp"])
def test_every_network_returns_the_contract(model, tmp_path):
    """With every extra it can compute asked for (NVSNet: all; a baseline: its ``provides``; a reference: none)."""
    cfg = compose_train([f"model={model}", f"paths.root_dir={tmp_path}", "loss=[recon_final]"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    net = build_module(cfg).net.eval()
    asked = frozenset(getattr(net, "provides", EXTRAS if model == "nvs" else ()))
    with torch.no_grad():
        out = net(fixture_batch(), asked)
    assert Outputs.__required_keys__ <= set(out) <= Outputs.__required_keys__ | Outputs.__optional_keys__
    assert asked <= set(out)
    assert out["rgb"].shape == (2, 3, 64, 64) and 0 <= out["rgb"].min() and out["rgb"].max() <= 1
    assert len(out["rgb_scales"]) == getattr(net, "n_scales", 1) and out["rgb_scales"][-1].shape == (2, 3, 64, 64)
    torch.testing.assert_close(out["rgb_scales"][-1], out["rgb"] * 2 - 1, atol=1e-5, rtol=0)


@pytest.mark.parametrize("model", ["copy_source", "gt_warp"])
def test_training_a_reference_model_says_it_has_nothing_to_train(model, tmp_path):
    from nvs.core.errors import UserError

    cfg = compose_train([f"model={model}", f"paths.root_dir={tmp_path}"])  # the default loss list: recon at 4 scales
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    module = build_module(cfg)
    with pytest.raises(UserError, match=f"model '{model}' has no trainable parameters; evaluate it with nvs.evaluate"):
        module.on_fit_start()
