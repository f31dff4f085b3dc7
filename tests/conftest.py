"""Shared fixtures: tiny datasets in both on-disk formats, and the real Hydra config composed and shrunk."""

from __future__ import annotations

import os
import random
import zlib
from pathlib import Path

import pytest
import torch

from nvs.data.synthetic import synthetic_batch, write_objects_root, write_scenes_root
from nvs.run.compose import CONF_DIR as _CONF_DIR
from nvs.run.compose import compose

CONF_DIR = str(_CONF_DIR)
# The fixture writers and the batch builder live in the package (nvs.stress uses them too); the test-facing names stay.
make_objects_root = write_objects_root
make_scenes_root = write_scenes_root


def pytest_configure(config):
    # `make test` runs three pytest-xdist workers on two cores: each computes with one thread (and so do the command
    # lines it starts), so that the cores are shared by whole workers, never by thread pools fighting inside one.
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = "1"
        torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _seeded_per_test(request):
    """Each test draws from its own seed, taken from its id: an unseeded draw gives the same numbers whichever worker
    runs the test and whatever ran before it, so a tolerance that fails does so every time, not one CI run in many."""
    seed = zlib.crc32(request.node.nodeid.encode())
    random.seed(seed)
    torch.manual_seed(seed)
    yield


@pytest.fixture(scope="session")
def objects_root(tmp_path_factory) -> Path:
    return make_objects_root(tmp_path_factory.mktemp("chairs_64"))


@pytest.fixture(scope="session")
def scenes_root(tmp_path_factory) -> Path:
    return make_scenes_root(tmp_path_factory.mktemp("drive_64"))


def compose_train(overrides=(), config_name: str = "train"):
    """The real train.yaml with overrides, composed outside a Hydra run (hydra.* interpolations left unresolved)."""
    return compose(config_name, list(overrides))


def fixture_batch(B: int = 2, S: int = 64, seed: int = 0) -> dict:
    """An objects batch: random images, the chairs camera at S^2, 20 degrees of azimuth about (0,0,2), depth 2."""
    return synthetic_batch(B, S, "objects", "random", seed)
