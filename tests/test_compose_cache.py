"""compose() keeps each composition for the process: a copy per caller, and an edited config file is seen at once."""

from __future__ import annotations

import shutil

import pytest

from nvs.core.errors import UserError
from nvs.run import compose as compose_mod


@pytest.fixture()
def conf_copy(tmp_path, monkeypatch):
    conf = tmp_path / "conf"
    shutil.copytree(compose_mod.CONF_DIR, conf)
    monkeypatch.setattr(compose_mod, "CONF_DIR", conf)
    monkeypatch.setattr(compose_mod, "_COMPOSED", {})
    return conf


def test_a_callers_edit_changes_no_other_callers_config(conf_copy):
    first = compose_mod.compose("train", ["data.size=32"])
    first.data.size = 5
    first.optim.lr = -1.0
    again = compose_mod.compose("train", ["data.size=32"])
    assert again.data.size == 32 and again.optim.lr > 0
    assert len(compose_mod._COMPOSED) == 1


def test_an_edited_added_or_removed_config_file_is_composed_anew(conf_copy):
    assert compose_mod.compose("train", []).optim.lr == pytest.approx(1e-4)
    target = conf_copy / "optim" / "adam.yaml"
    text = target.read_text()
    target.write_text(text.replace("lr: 1.0e-4", "lr: 0.123"))
    option = "adam"
    assert compose_mod.compose("train", [f"optim={option}"]).optim.lr == pytest.approx(0.123)
    (conf_copy / "optim" / "cached_probe.yaml").write_text(text.replace("lr: 1.0e-4", "lr: 0.5"))
    assert compose_mod.compose("train", ["optim=cached_probe"]).optim.lr == pytest.approx(0.5)
    (conf_copy / "optim" / "cached_probe.yaml").unlink()
    with pytest.raises(UserError, match="optim=cached_probe"):
        compose_mod.compose("train", ["optim=cached_probe"])
