"""The flat layout of nvs 0.1 read as today's folders: moved modules, recorded ``_target_`` strings, committed jobs."""

from __future__ import annotations

import importlib
import importlib.util
import json
import shutil
from pathlib import Path

import pytest
from hydra.utils import get_object

from nvs.core import legacy
from nvs.core.legacy import MOVED, SAME_BEHAVIOUR, current_target, upgrade_targets

REPO = Path(__file__).resolve().parents[1]
JOBS = sorted((REPO / "results" / "jobs").glob("*/*/sweep_job.json"))


def _targets(node) -> list[str]:
    if isinstance(node, dict):
        own = [node["_target_"]] if isinstance(node.get("_target_"), str) else []
        return own + [t for v in node.values() for t in _targets(v)]
    if isinstance(node, list):
        return [t for v in node for t in _targets(v)]
    return []


@pytest.mark.parametrize("old", sorted(MOVED))
def test_each_moved_module_is_at_its_new_place_and_gone_from_the_old(old):
    assert importlib.util.find_spec(MOVED[old]) is not None, f"{MOVED[old]} does not exist"
    # the old name is gone (a package of the same name, e.g. nvs.losses, is not the old module)
    spec = importlib.util.find_spec(old)
    assert spec is None or spec.submodule_search_locations is not None, f"{old} still exists as a module"


def test_current_target_maps_the_module_not_the_name():
    assert current_target("nvs.losses.ReconLoss") == "nvs.losses.terms.ReconLoss"
    assert current_target("nvs.checkpoints.ModelCheckpoint") == "nvs.run.checkpoints.ModelCheckpoint"
    # already current, or never moved: unchanged
    assert current_target("nvs.losses.terms.ReconLoss") == "nvs.losses.terms.ReconLoss"
    assert current_target("nvs.models.net.NVSNet") == "nvs.models.net.NVSNet"
    assert current_target("torch.optim.Adam") == "torch.optim.Adam"


def test_upgrade_targets_walks_dicts_and_lists_and_leaves_other_keys():
    cfg = {"loss": {"recon": {"_target_": "nvs.losses.ReconLoss", "weight": 10.0}},
           "callbacks": [{"_target_": "nvs.convergence.Convergence", "name": "nvs.losses.ReconLoss"}]}
    up = upgrade_targets(cfg)
    assert up["loss"]["recon"] == {"_target_": "nvs.losses.terms.ReconLoss", "weight": 10.0}
    assert up["callbacks"][0] == {"_target_": "nvs.run.convergence.Convergence", "name": "nvs.losses.ReconLoss"}
    assert cfg["loss"]["recon"]["_target_"] == "nvs.losses.ReconLoss"  # a copy: the record is not changed


def test_every_target_recorded_in_a_committed_job_resolves_after_the_upgrade():
    assert JOBS, "no committed job files under results/jobs"
    recorded = {t for path in JOBS for t in _targets(json.loads(path.read_text()).get("config"))}
    assert any(t.startswith("nvs.losses.") and t.count(".") == 2 for t in recorded), "expected flat-layout targets"
    unresolved = []
    for target in sorted(recorded):
        try:
            get_object(current_target(target))
        except Exception as err:  # noqa: BLE001 - report every target that does not resolve
            unresolved.append(f"{target}: {err.__class__.__name__}")
    assert not unresolved, "\n".join(unresolved)


def test_a_committed_study_stays_done_and_would_go_stale_without_the_map(monkeypatch, tmp_path):
    from nvs.sweep import jobs as sweep_jobs
    from nvs.sweep.export import export_root
    from nvs.sweep.jobs import Status, plan
    from nvs.sweep.study import load_study

    study = load_study(REPO / "sweeps" / "depth.yaml")
    exported = export_root(REPO / "results", study.scale)
    # every job of the study that has committed files (a row whose seeds are still to run has none yet)
    committed = {d.name for d in exported.iterdir() if d.is_dir()}
    jobs = [j for j in plan(study, tmp_path / "runs", (), exported) if j.dir.name in committed]
    assert len(jobs) >= 10 and all(j.status == Status.DONE for j in jobs), [(j.dir.name, j.status) for j in jobs]
    # the guard can fail: read the recorded configs as they are, and each job that recorded a moved module is stale
    flat = {j.dir.name for j in jobs if any(t.rpartition(".")[0] in MOVED for t in _targets(
        json.loads((j.dir / "sweep_job.json").read_text())["config"]))}
    assert flat, "no job of the study recorded a flat-layout target"
    monkeypatch.setattr(sweep_jobs, "as_today", lambda node: node)
    done = {j.dir.name for j in plan(study, tmp_path / "runs", (), exported) if j.status == Status.DONE}
    assert not done & flat


def test_renamed_defaults_are_listed_once():
    assert ("precision", None, "auto") in SAME_BEHAVIOUR
    assert legacy.SAME_BEHAVIOUR is __import__("nvs.sweep.jobs", fromlist=["SAME_BEHAVIOUR"]).SAME_BEHAVIOUR


@pytest.mark.slow
def test_collect_only_rebuilds_every_committed_csv_byte_for_byte(tmp_path, monkeypatch):
    # What a fresh clone does: only the committed job files, no runs/; every study's CSV must come out identical.
    # Run from a copy of the results tree, since the CSV names each job's directory relative to the working directory.
    from nvs import sweep

    shutil.copytree(REPO / "results" / "jobs", tmp_path / "results" / "jobs")
    monkeypatch.chdir(tmp_path)
    # precision: its jobs are not committed (a table of runs/ on the machine that ran them)
    rebuilt = [p for p in sorted((REPO / "results").glob("*.csv")) if p.stem != "precision"]
    assert len(rebuilt) >= 8
    for csv in rebuilt:
        sweep.run([str(REPO / "sweeps" / f"{csv.stem}.yaml"), "--collect-only", "--results", "results"])
        assert (tmp_path / "results" / csv.name).read_bytes() == csv.read_bytes(), f"{csv.name} differs when rebuilt"
