"""`data.train_fraction`: a seeded, nested subset of the training models; validation and test sets unchanged."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from conftest import compose_train, make_objects_root
from nvs.core.errors import UserError
from nvs.data.datamodule import train_subset
from nvs.data.shapenet import parse_stem
from nvs.run.build import build_data

MODELS = tuple(f"m{i}" for i in range(11))  # 10 listed for training (1 of them carved for validation), 1 test


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return make_objects_root(tmp_path_factory.mktemp("fraction"), models=MODELS, size=16, depth=False)


def _datamodule(root, fraction, seed=0):
    cfg = compose_train(["data=chairs", f"data.root={root}", "data.size=16", f"seed={seed}",
                         f"data.train_fraction={fraction}"])
    return build_data(cfg)


def _train_models(dm) -> set[str]:
    return {parse_stem(s)[0] for s in dm.dataset("train").sources}


def test_data_configs_default_to_all_models():
    for name in ("chairs", "cars"):
        assert OmegaConf.load(f"conf/data/{name}.yaml").train_fraction == 1.0


def test_fraction_subsets_train_only(root):
    full, half = _datamodule(root, 1.0), _datamodule(root, 0.5)
    all_train = _train_models(full)
    assert len(all_train) == 9
    sub = _train_models(half)
    assert len(sub) == round(0.5 * 9) and sub < all_train
    assert half.dataset("test").pairs == full.dataset("test").pairs
    assert half.dataset("val").pairs == full.dataset("val").pairs


def test_subsets_are_seeded_and_nested():
    models = [f"m{i:02d}" for i in range(40)]
    a, b = train_subset(models, 0.25, seed=0), train_subset(models, 0.25, seed=0)
    assert a == b and len(a) == 10
    assert set(a) < set(train_subset(models, 0.5, seed=0))
    assert train_subset(models, 0.25, seed=1) != a
    assert train_subset(models, 0.001, seed=0) and len(train_subset(models, 0.001, seed=0)) == 1
    assert train_subset(models, 1.0, seed=0) == models


@pytest.mark.parametrize("bad", [0, 1.5, -0.1, "'half'"])
def test_bad_fraction_is_one_clear_error(root, bad):
    with pytest.raises(UserError, match="data.train_fraction"):
        _datamodule(root, bad)


def test_fraction_is_for_objects_only(scenes_root):
    cfg = compose_train(["data=drive", f"data.root={scenes_root}", "data.size=64", "++data.train_fraction=0.5"])
    with pytest.raises(UserError, match="data.train_fraction"):
        build_data(cfg)
