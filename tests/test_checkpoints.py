"""nvs.run.checkpoints' restore: the one way evaluate, the viewer and the figures rebuild a run from its checkpoint."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from nvs.core.errors import UserError
from nvs.run.build import build_module
from nvs.run.checkpoints import restore_module, restore_run_config
from nvs.run.compose import compose
from tests.conftest import compose_train, fixture_batch


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A tatarchenko checkpoint as training writes it (weights + resolved config), without training."""
    tmp = tmp_path_factory.mktemp("restore")
    cfg = compose_train(["experiment=tatarchenko_chairs", f"paths.root_dir={tmp}"])
    cfg.paths.output_dir = str(tmp)
    OmegaConf.resolve(cfg)
    torch.manual_seed(3)
    module = build_module(cfg)
    path = tmp / "t.ckpt"
    torch.save({"state_dict": module.state_dict(), "nvs_config": module.run_config}, path)
    return path, module


def _eval_cfg(tmp_path, *overrides):
    cfg = compose("evaluate", [f"paths.root_dir={tmp_path}", *overrides])
    cfg.paths.output_dir = str(tmp_path)
    cfg.out_dir = str(tmp_path)
    return cfg


def test_a_restored_module_has_the_saved_weights_and_is_in_eval_mode(saved, tmp_path):
    path, module = saved
    run, ckpt = restore_run_config(_eval_cfg(tmp_path, f"ckpt_path={path}", "limit=3", "seed=5"))
    assert run.model.name == "tatarchenko" and run.seed == 5 and run.data.loader.limit_test_pairs == 3
    assert ckpt["path"] == str(path)
    restored = restore_module(run, ckpt)
    assert not restored.training and not restored.net.training
    batch = fixture_batch()
    with torch.no_grad():
        torch.testing.assert_close(restored.net(batch)["rgb"], module.eval().net(batch)["rgb"], rtol=0, atol=0)


def test_data_from_the_command_line_keeps_the_checkpoints_size(saved, tmp_path):
    path, _ = saved
    run, _ = restore_run_config(_eval_cfg(tmp_path, f"ckpt_path={path}", "data=cars", "data.size=128"))
    assert run.data.name == "cars" and run.data.size == 64
    run, _ = restore_run_config(_eval_cfg(tmp_path, f"ckpt_path={path}", "data.root=/elsewhere"))
    assert run.data.name == "chairs" and run.data.root == "/elsewhere"


@pytest.mark.parametrize("edit,message", [
    (lambda sd: sd.pop(next(iter(sd))), r"1 missing and 0 unexpected weights \(e\.g\. net\."),
    (lambda sd: sd.__setitem__("net.extra.weight", torch.zeros(1)), r"0 missing and 1 unexpected weights"),
    (lambda sd: sd.__setitem__("net.out.weight", torch.zeros(3, 1, 1, 1)), r"size mismatch for net\.out\.weight"),
])
def test_a_checkpoint_that_does_not_fit_names_the_file_and_a_weight(saved, tmp_path, edit, message):
    path, _ = saved
    ckpt = torch.load(path, weights_only=False)
    edit(ckpt["state_dict"])
    bad = tmp_path / "bad.ckpt"
    torch.save(ckpt, bad)
    run, loaded = restore_run_config(_eval_cfg(tmp_path, f"ckpt_path={bad}"))
    with pytest.raises(UserError, match=f"{bad} does not fit model 'tatarchenko': {message}"):
        restore_module(run, loaded)


def test_another_model_than_the_checkpoints_is_refused(saved, tmp_path):
    path, _ = saved
    with pytest.raises(UserError, match="holds model 'tatarchenko', not 'nvs'"):
        restore_run_config(_eval_cfg(tmp_path, f"ckpt_path={path}", "model=nvs"))


def test_files_that_are_no_checkpoint_are_one_clear_error(tmp_path):
    with pytest.raises(UserError, match="no such checkpoint"):
        restore_run_config(_eval_cfg(tmp_path, f"ckpt_path={tmp_path / 'none.ckpt'}"))
    (tmp_path / "junk.ckpt").write_bytes(b"not a zip")
    with pytest.raises(UserError, match="not a readable checkpoint"):
        restore_run_config(_eval_cfg(tmp_path, f"ckpt_path={tmp_path / 'junk.ckpt'}"))
    torch.save({"state_dict": {}}, tmp_path / "other.ckpt")
    with pytest.raises(UserError, match="not an nvs checkpoint"):
        restore_run_config(_eval_cfg(tmp_path, f"ckpt_path={tmp_path / 'other.ckpt'}"))


def test_a_reference_model_is_built_from_the_command_line_without_weights(tmp_path):
    run, ckpt = restore_run_config(_eval_cfg(tmp_path, "model=copy_source", "data=chairs"))
    assert ckpt is None and dict(run.loss) == {}
    module = restore_module(run, ckpt)
    batch = fixture_batch()
    assert not module.training and torch.equal(module.net(batch)["rgb"], batch["src"])
    with pytest.raises(UserError, match="give data="):
        restore_run_config(_eval_cfg(tmp_path, "model=copy_source"))
    with pytest.raises(UserError, match="give ckpt_path="):
        restore_run_config(_eval_cfg(tmp_path))


def test_a_checkpoint_of_the_flat_layout_restores(saved, tmp_path):
    # A checkpoint written before the layer folders names nvs.losses.ReconLoss, nvs.models...: its config is read as
    # today's (nvs.core.legacy), and the network comes back with the same weights.
    from nvs.core.legacy import MOVED

    path, module = saved
    ckpt = torch.load(path, weights_only=False)
    old = {new: old for old, new in MOVED.items()}

    def flat(node):
        if isinstance(node, dict):
            return {k: (old.get(v.rpartition(".")[0], v.rpartition(".")[0]) + "." + v.rpartition(".")[2]
                        if k == "_target_" and isinstance(v, str) and v.startswith("nvs.") else flat(v))
                    for k, v in node.items()}
        return [flat(v) for v in node] if isinstance(node, list) else node

    ckpt["nvs_config"] = flat(ckpt["nvs_config"])
    assert ckpt["nvs_config"]["loss"]["recon"]["_target_"] == "nvs.losses.ReconLoss"
    legacy_path = tmp_path / "flat.ckpt"
    torch.save(ckpt, legacy_path)
    run, loaded = restore_run_config(_eval_cfg(tmp_path, f"ckpt_path={legacy_path}"))
    restored = restore_module(run, loaded)
    assert run.loss.recon._target_ == "nvs.losses.terms.ReconLoss"
    for (k, a), (_, b) in zip(module.net.state_dict().items(), restored.net.state_dict().items()):
        assert torch.equal(a, b), k
