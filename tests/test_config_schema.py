"""The typed schema of the configs (nvs.run.config_schema, nvs.run.component_schema): a wrong type or an unknown key,
on the command line or in a YAML file, is one error naming the key and where it was set; the composed config itself
is never changed by the check."""

from __future__ import annotations

import dataclasses
import re
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Union

import pytest
from omegaconf import OmegaConf

from nvs.core.errors import UserError
from nvs.core.fidelity import SWITCHES
from nvs.data import datamodule
from nvs.run import compose as compose_module
from nvs.run import config_check, config_schema
from nvs.run.build import datamodule_arguments
from nvs.run.component_schema import component_schema, omegaconf_type
from nvs.run.config_check import check_config, set_where
from nvs.train import check_composes
from tests.conftest import CONF_DIR, compose_train


def _error(config_name: str, overrides: list[str]) -> str:
    with pytest.raises(UserError) as err:
        check_config(config_name, compose_train(overrides, config_name=config_name), overrides)
    return str(err.value)


# -- types of the component arguments ---------------------------------------------------------------------------------
@pytest.mark.parametrize("annotation, expected", [
    (int, int), (Optional[int], Optional[int]), (int | None, Optional[int]), (Union[int, float], float),
    (Sequence[str], List[str]), (tuple[float, float], List[float]), (tuple[float, ...], List[float]),
    (list, List[Any]), (Mapping[str, int], Dict[str, Any]), (dict, Dict[str, Any]), (Path, str),
    (Literal["a", "b"], Any), (Union[str, int], Any), (object, Any), ("a string annotation", Any),
])
def test_an_annotation_becomes_the_type_omegaconf_checks(annotation, expected):
    assert omegaconf_type(annotation) == expected


def test_a_component_is_typed_by_its_targets_arguments():
    net = component_schema("nvs.models.net.NVSNet")
    kinds = {f.name: f.type for f in dataclasses.fields(net.schema)}
    assert not net.open and kinds["n_points"] is int and kinds["image_size"] is int and kinds["skips"] is Any
    assert kinds["_target_"] is str and "name" not in kinds
    assert "name" in component_schema("nvs.models.net.NVSNet", (("name", str),)).names
    # a subclass passing **kwargs on: its own arguments and its base's, closed where the base is
    checkpoint = component_schema("nvs.run.checkpoints.ModelCheckpoint")
    assert not checkpoint.open and {"last_every_n_steps", "dirpath", "save_top_k", "monitor"} <= set(checkpoint.names)
    # **kwargs all the way up (W&B's init arguments): any other key; a module without __init__ takes none
    assert component_schema("nvs.run.loggers.QuietWandbLogger").open
    noskips = component_schema("nvs.models.skips.NoSkips")
    assert not noskips.open and set(noskips.names) == {"_target_", "_partial_", "_recursive_", "_convert_", "_args_"}
    assert component_schema("nvs.no_such_module.Thing") is None


# -- the schema mirrors what reads the config -------------------------------------------------------------------------
def _names(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def test_the_data_schema_has_the_fields_the_datamodule_reads():
    assert _names(config_schema.Camera) == _names(datamodule.Camera)
    assert _names(config_schema.Loader) == _names(datamodule.LoaderSettings)
    assert _names(config_schema.Fidelity) == set(SWITCHES)
    read = datamodule_arguments({"format": "objects", "root": "r", "size": 64, "camera": {}, "loader": {}})
    assert {"fmt" if k == "format" else k for k in _names(config_schema.Data)} >= set(read)


@pytest.mark.parametrize("config_name, overrides", [
    ("evaluate", []), ("evaluate", ["model=copy_source", "data=chairs"]), ("evaluate", ["model=mean_depth", "data=drive"]),
    ("viewer", []), ("viewer", ["data=cars"]), ("render_video", []), ("render_video", ["data=kitti"]),
    ("export_ply", []), ("export_ply", ["data=drive", "pose={azimuth:20,elevation:10}"]),
    ("train", ["callbacks=convergence", "logger=[csv,tensorboard,wandb]", "scheduler=onecycle", "fidelity=corrected"]),
    ("train", ["debug=fast_dev_run", "model=gt_plane", "data=drive_wide"]),
])
def test_every_command_config_passes_its_schema(config_name, overrides):
    check_config(config_name, compose_train(overrides, config_name=config_name), overrides)


def test_the_check_leaves_the_composed_config_as_hydra_made_it():
    cfg = compose_train(["experiment=demo", "+optim.weight_decay=0.1"])
    before = OmegaConf.to_container(cfg, resolve=False)
    check_config("train", cfg)
    assert OmegaConf.to_container(cfg, resolve=False) == before
    assert before["data"]["camera"]["size"] == 256 and isinstance(before["data"]["camera"]["size"], int)


# -- errors: the key, what its field takes, and where it was set ------------------------------------------------------
@pytest.mark.parametrize("overrides, message", [
    (["+model.n_pionts=3"], "config 'model.n_pionts': not an argument of nvs.models.net.NVSNet; did you mean "
                            "model.n_points? (on the command line: +model.n_pionts=3)"),
    (["+loss.recon.foo=3"], "config 'loss.recon.foo': not an argument of nvs.losses.terms.ReconLoss "
                            "(on the command line: +loss.recon.foo=3)"),
    (["+data.sise=3"], "config 'data.sise': no such key; did you mean data.size? (on the command line: +data.sise=3)"),
    (["fidelity.warp_align=exactly"], "config 'fidelity.warp_align': expected one of code, exact, got 'exactly'"),
    (["nonfinite=go"], "config 'nonfinite': expected one of stop, skip, got 'go'"),
    (["data.format=images"], "config 'data.format': expected one of objects, scenes, got 'images'"),
    (["loss.recon=3"], "config 'loss.recon': expected a component (a mapping with _target_), got 3"),
    (["data.name=null"], "config 'data.name': expected a string, got null"),
    (["data.camera.pivot=[0,0,'2']"], "config 'data.camera.pivot[2]': expected a number, got '2'"),
    (["experiment=sun_chairs", "model.lstm_blocks=x"], "config 'model.lstm_blocks': expected an integer, got 'x'"),
    (["model/skips=adaptive", "model.skips.threshold_px=x"], "config 'model.skips.threshold_px': expected a number"),
    (["data=drive", "data.depth_head.max_disparity=far"], "config 'data.depth_head.max_disparity': expected a number"),
    (["model/depth=plane", "model.depth.hidden=1.5"], "config 'model.depth.hidden': expected an integer, got 1.5"),
    (["callbacks.progress_bar.refresh_rate=fast"], "config 'callbacks.progress_bar.refresh_rate': expected an integer"),
])
def test_a_wrong_key_or_type_on_the_command_line_is_one_error_naming_it(overrides, message):
    assert message in _error("train", overrides)


@pytest.mark.parametrize("config_name, overrides, message", [
    ("evaluate", ["seed=abc"], "config 'seed': expected an integer, got 'abc' (on the command line: seed=abc)"),
    ("evaluate", ["+trainer.devises=2"], "config 'trainer.devises': not an argument of lightning.pytorch.Trainer; "
                                         "did you mean trainer.devices?"),
    ("export_ply", ["pose={azimuth:left}"], "config 'pose.azimuth': expected a number, got 'left'"),
    ("render_video", ["progress=maybe"], "config 'progress': expected true or false, got 'maybe'"),
    ("viewer", ["port=http"], "config 'port': expected an integer, got 'http'"),
])
def test_every_commands_config_is_typed(config_name, overrides, message):
    assert message in _error(config_name, overrides)


def test_an_unknown_key_without_plus_gets_the_schemas_reason_or_how_to_add_it():
    with pytest.raises(UserError, match=r"^config 'model.n_pionts': not an argument of nvs.models.net.NVSNet; "
                                        r"did you mean model.n_points\? \(on the command line: model.n_pionts=3\)$"):
        check_composes(["model.n_pionts=3"])
    # an argument of the target that the YAML does not list: Hydra's own way of adding it
    with pytest.raises(UserError, match=r"^config 'callbacks.model_checkpoint.every_n_train_steps': no such key in "
                                        r"conf/train.yaml \(a new key is added with "
                                        r"\+callbacks.model_checkpoint.every_n_train_steps=2\)$"):
        check_composes(["callbacks.model_checkpoint.every_n_train_steps=2"])


def test_an_unknown_target_is_left_to_instantiate():
    check_config("train", compose_train(["model._target_=nvs.models.no_such.Net"]))


@pytest.mark.parametrize("overrides, key, where", [
    ([], "data.camera.fx", "conf/data/chairs.yaml"),
    ([], "model.skips.levels", "conf/model/skips/warped.yaml"),
    ([], "trainer.max_steps", "conf/trainer/default.yaml"),
    ([], "seed", "conf/train.yaml"),
    (["experiment=demo"], "trainer.max_steps", "conf/experiment/demo.yaml"),
    (["experiment=demo"], "data.loader.augment.mirror", "conf/experiment/demo.yaml"),
    (["experiment=sun_chairs"], "optim.lr", "conf/experiment/method/sun.yaml"),
    (["data=kitti"], "data.size", "conf/data/kitti.yaml"),
    (["data=kitti"], "data.loader.batch_size", "conf/data/drive.yaml"),  # kitti.yaml builds on drive.yaml
    (["data=kitti", "data.size=128"], "data.size", "the command line: data.size=128"),
])
def test_where_a_key_was_set(overrides, key, where):
    said = set_where("train", overrides, [key])[key]
    assert said == (f" (on {where})" if where.startswith("the command line") else f" (in {where})")


def test_a_wrong_type_or_unknown_key_in_a_yaml_file_names_the_file(tmp_path, monkeypatch):
    conf = tmp_path / "conf"
    shutil.copytree(CONF_DIR, conf)
    chairs = conf / "data" / "chairs.yaml"
    chairs.write_text(chairs.read_text().replace("fx: 480.0", "fx: wide") + "sise: 64\n")
    warped = conf / "model" / "skips" / "warped.yaml"
    warped.write_text(warped.read_text() + "treshold_px: 0.5\n")
    monkeypatch.setattr(compose_module, "CONF_DIR", conf)
    monkeypatch.setattr(config_check, "CONF_DIR", conf)
    with pytest.raises(UserError) as err:
        check_config("train", compose_module.compose("train"))
    assert sorted(re.split(r"; (?=config ')", str(err.value))) == [
        "config 'data.camera.fx': expected a number, got 'wide' (in conf/data/chairs.yaml)",
        "config 'data.sise': no such key; did you mean data.size? (in conf/data/chairs.yaml)",
        "config 'model.skips.treshold_px': not an argument of nvs.models.skips.WarpedSkips (in "
        "conf/model/skips/warped.yaml)"]
