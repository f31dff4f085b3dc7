"""Experiments compose a method with a dataset (experiment=method/<m> data=<d>); the per-pair names stay as aliases."""

from __future__ import annotations

from pathlib import Path

import pytest

from nvs.sweep.jobs import config_fingerprint
from nvs.sweep.recorded import as_today
from tests.conftest import compose_train

CONF = Path(__file__).resolve().parents[1] / "conf" / "experiment"
PAIRS = sorted(p.stem for p in CONF.glob("*_*.yaml") if p.stem.split("_")[0] in {m.stem for m in (CONF / "method").glob("*.yaml")})


def test_every_method_has_its_pairs():
    assert len(PAIRS) == 12


@pytest.mark.parametrize("pair", PAIRS)
def test_a_pair_name_is_the_method_composed_with_the_data(pair):
    method, data = pair.split("_", 1)
    alias = compose_train([f"experiment={pair}"])
    composed = compose_train([f"experiment=method/{method}", f"data={data}"])
    assert config_fingerprint(alias) == config_fingerprint(composed)
    assert alias.model.name == method and alias.data.name == data and alias.task_name == pair
    # an alias states no fact of its own: two defaults and nothing else
    assert [ln for ln in (CONF / f"{pair}.yaml").read_text().splitlines() if not ln.startswith("#")] == [
        "defaults:", f"  - method/{method}", f"  - override /data: {data}"]


@pytest.mark.parametrize("data, padding", [("chairs", "border"), ("cars", "border"), ("drive", "zeros"),
                                           ("kitti", "zeros")])
def test_what_sun_reads_outside_the_source_is_the_datas(data, padding):
    assert compose_train(["model=sun", f"data={data}"]).model.padding_mode == padding


def test_mean_depth_reads_the_runs_data_node_and_the_old_mapping_reads_as_it():
    cfg = config_fingerprint(compose_train(["model=mean_depth", "data=drive"]))
    assert cfg["model"]["data"] == cfg["data"]
    old = {**cfg, "model": {**cfg["model"], "data": {
        "fmt": "scenes", "root": cfg["data"]["root"], "size": cfg["data"]["size"], "camera": cfg["data"]["camera"],
        "loader": cfg["data"]["loader"], "category": cfg["data"].get("category"),
        "translation_scale": cfg["data"]["translation_scale"], "max_delta_azimuth": cfg["data"]["max_delta_azimuth"],
        "train_fraction": cfg["data"].get("train_fraction", 1.0)}}}
    assert as_today(old) == cfg
    # a recorded mapping that disagrees with the data node (another root) is not read as it
    changed = {**old, "model": {**old["model"], "data": {**old["model"]["data"], "root": "/elsewhere"}}}
    assert as_today(changed)["model"]["data"]["root"] == "/elsewhere"
