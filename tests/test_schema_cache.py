"""Component schemas kept across processes (nvs.run.component_schema): a kept schema is the one the target's code
gives, another source state is never read, a target outside the kept packages is never kept, and a command line whose
config is wrong stops before torch or Lightning is imported."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys

import pytest

from nvs.run import component_schema as cs
from nvs.run.compose import CONF_DIR


def _targets() -> set[str]:
    import yaml

    found: set[str] = set()

    def walk(node):
        if isinstance(node, dict):
            target = node.get("_target_")
            if isinstance(target, str) and "${" not in target:
                found.add(target)
            for v in node.values():
                walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    for path in CONF_DIR.rglob("*.yaml"):
        walk(yaml.safe_load(path.read_text()))
    return found


def _fields(schema) -> list[tuple[str, object]]:
    return [(f.name, f.type) for f in dataclasses.fields(schema.schema)]


@pytest.fixture
def fresh_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NVS_CACHE_DIR", str(tmp_path))
    cs.component_schema.cache_clear()
    yield tmp_path / "component_schemas.json"
    cs.component_schema.cache_clear()


def test_a_kept_schema_is_the_one_the_code_gives_for_every_configured_target(fresh_cache):
    targets = sorted(_targets())
    assert len(targets) > 20
    computed = {t: cs.component_schema(t) for t in targets}  # read from the code, and kept
    kept = json.loads(fresh_cache.read_text())["schemas"]
    assert set(kept) <= set(targets) and len(kept) >= 0.8 * len([s for s in computed.values() if s is not None])
    cs.component_schema.cache_clear()
    for target in targets:
        again = cs.component_schema(target)  # from the file where it is kept
        if computed[target] is None:
            assert again is None, target
            continue
        assert _fields(again) == _fields(computed[target]) and again.open == computed[target].open, target
        assert again.schema.__name__ == computed[target].schema.__name__


def test_another_source_state_is_not_read_and_other_packages_are_not_kept(fresh_cache, monkeypatch):
    cs.component_schema("nvs.models.net.NVSNet")
    data = json.loads(fresh_cache.read_text())
    data["schemas"]["nvs.models.net.NVSNet"]["arguments"] = [["bogus", "int"]]
    fresh_cache.write_text(json.dumps(data))
    cs.component_schema.cache_clear()
    assert "bogus" in cs.component_schema("nvs.models.net.NVSNet").names  # the file is read while the state holds
    monkeypatch.setattr(cs, "source_state", lambda: "another")  # an nvs file edited, a package upgraded
    cs.component_schema.cache_clear()
    assert "bogus" not in cs.component_schema("nvs.models.net.NVSNet").names
    assert "n_points" in cs.component_schema("nvs.models.net.NVSNet").names
    cs.component_schema("collections.OrderedDict")  # a package the state does not follow: read each time
    assert "collections.OrderedDict" not in json.loads(fresh_cache.read_text())["schemas"]
    fresh_cache.write_text("{not json")  # a broken file costs time only
    cs.component_schema.cache_clear()
    assert "n_points" in cs.component_schema("nvs.models.net.NVSNet").names


def test_a_wrong_config_stops_before_torch_and_lightning(fresh_cache):
    from nvs.run.compose import compose
    from nvs.run.config_check import check_config
    from nvs.run.overrides import trainer_arguments

    trainer_arguments(["trainer.max_steps=1"])
    for name in ("train", "evaluate"):  # this process reads the targets' code and keeps their schemas
        check_config(name, compose(name))
    code = ("import runpy, sys; sys.argv = sys.argv[1:]\n"
            "try:\n    runpy.run_module(sys.argv[0], run_name='__main__')\n"
            "except SystemExit as e:\n"
            "    print('exit', e.code, [m for m in ('torch', 'lightning') if m in sys.modules])")
    for cmd in (["nvs.train", "trainer.max_steps=abc"], ["nvs.evaluate", "seed=abc"]):
        res = subprocess.run([sys.executable, "-c", code, *cmd], cwd=fresh_cache.parent, env=dict(os.environ),
                             capture_output=True, text=True, timeout=300)
        assert "expected an integer, got 'abc'" in res.stderr, res.stderr[-2000:]
        assert res.stdout.strip().splitlines()[-1] == "exit 2 []", (cmd, res.stdout)
