"""Scale-out that gives the same numbers (issue 22): evaluation under 2-process DDP on CPU (gloo) covers every test
pair once and writes what one process writes; a tiny study runs through the submitit launcher.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from tests.conftest import compose_train, make_objects_root
from tests.test_reliability import _cli

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def odd_root(tmp_path_factory) -> Path:
    """The fixture chairs with 5 test pairs: 2 ranks get 3 each, one of them a DistributedSampler padding repeat."""
    root = make_objects_root(tmp_path_factory.mktemp("odd") / "chairs")
    with open(root / "eval_chair_40.txt", "a") as f:
        f.write("m3_160_0 m3_180_10\n")
    return root


@pytest.fixture(scope="module")
def checkpoint(odd_root, tmp_path_factory) -> Path:
    """The full model's checkpoint as nvs.train leaves it (untrained: equality is what is tested, not quality)."""
    from nvs.run.build import build_module

    out = tmp_path_factory.mktemp("ckpt")
    # batches of 2: each rank's 3 pairs in two batches, the padding repeat in the last one
    cfg = compose_train([f"data.root={odd_root}", f"paths.root_dir={out}", "loss=[recon]",
                         "data.loader.eval_batch_size=2"])
    cfg.paths.output_dir = str(out)
    OmegaConf.resolve(cfg)
    module = build_module(cfg)
    path = out / "model.ckpt"
    torch.save({"state_dict": module.state_dict(), "nvs_config": module.run_config, "global_step": 0}, path)
    return path


def _evaluate(checkpoint: Path, out: Path, monkeypatch, *placement: str) -> tuple[dict, list[dict]]:
    args = [f"ckpt_path={checkpoint}", "precision=32-true", "trainer.accelerator=cpu", f"out_dir={out}",
            f"hydra.run.dir={out}", *placement]
    if placement:  # DDP: Lightning launches rank 1 as a copy of this command line, so it must be a real one
        res = subprocess.run([sys.executable, "-m", "nvs.evaluate", *args], cwd=REPO, capture_output=True, text=True,
                             timeout=600)
        code, stderr = res.returncode, res.stderr
    else:
        code, stderr = _cli("evaluate", args, monkeypatch)
    assert code == 0, stderr[-4000:]
    with open(out / "test_per_image.csv") as f:
        rows = list(csv.DictReader(f))
    return json.loads((out / "metrics.json").read_text()), rows


def test_ddp_evaluation_equals_one_process(checkpoint, tmp_path, monkeypatch):
    one, rows_one = _evaluate(checkpoint, tmp_path / "one", monkeypatch)
    two, rows_two = _evaluate(checkpoint, tmp_path / "two", monkeypatch, "trainer.devices=2", "trainer.strategy=ddp")
    assert one["test"]["n_pairs"] == two["test"]["n_pairs"] == 5
    # the same pairs, once each, in the test list's order
    assert [(r["id_src"], r["id_tgt"]) for r in rows_two] == [(r["id_src"], r["id_tgt"]) for r in rows_one]
    assert len({(r["id_src"], r["id_tgt"]) for r in rows_two}) == 5 and rows_one[0]["id_src"] == "m3_0_0"
    assert list(rows_two[0]) == list(rows_one[0])  # the same columns
    for a, b in zip(rows_one, rows_two):
        for key in a:
            if key not in ("id_src", "id_tgt"):
                assert float(b[key]) == pytest.approx(float(a[key]), rel=1e-5, abs=1e-6, nan_ok=True), key
    for key, value in one["test"].items():
        assert two["test"][key] == pytest.approx(value, rel=1e-5, abs=1e-7, nan_ok=True), key
    # one writer: no per-rank copies of the results beside the two files
    assert sorted(p.name for p in (tmp_path / "two").iterdir() if p.suffix in (".json", ".csv")) == [
        "metrics.json", "test_per_image.csv"]


@pytest.mark.slow
def test_ddp_training_validates_and_tests_on_every_pair(odd_root, tmp_path):
    """2-process DDP training: val/l1 reduced over the ranks (both ranks pick the same best checkpoint), the test
    after training covers the 5 pairs once, metrics.json written once."""
    out = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "nvs.train", f"data.root={odd_root}", f"hydra.run.dir={out}",
                          "trainer.max_steps=2", "trainer.val_check_interval=2", "data.loader.batch_size=2",
                          "data.loader.eval_batch_size=2", "loss=[recon]", "trainer.enable_progress_bar=false",
                          "trainer.precision=32-true", "trainer.accelerator=cpu", "trainer.devices=2",
                          "trainer.strategy=ddp"], cwd=REPO, capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-4000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["test"]["n_pairs"] == 5 and metrics["checkpoint"].endswith("best-2.ckpt")
    with open(out / "test_per_image.csv") as f:
        assert len(list(csv.DictReader(f))) == 5
    logged = [r for r in csv.DictReader(open(out / "csv" / "metrics.csv")) if r.get("val/l1")]
    assert len(logged) == 1


# -- the submitit launcher -------------------------------------------------------------------------------------------
@pytest.mark.slow  # ~55 s: a study through submitit-local end to end (make test-all)
def test_a_tiny_study_runs_through_submitit_local(objects_root, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="pip install -e '.[cluster]'")
    study = tmp_path / "tiny.yaml"
    study.write_text(json.dumps({
        "name": "tiny", "seeds": [0, 1], "size": 64, "steps": 2,
        "overrides": [f"data.root={objects_root}"],
        # reference rows train nothing (one seed each): two jobs, each a submitit job of its own
        "rows": [{"name": "copy", "reference": "copy_source", "data": "chairs"},
                 {"name": "gtwarp", "reference": "gt_warp", "data": "chairs"}]}))
    res = subprocess.run([sys.executable, "-m", "nvs.sweep", str(study), "hydra/launcher=submitit_local",
                          f"hydra.launcher.submitit_folder={tmp_path / 'submitit'}", "--runs", str(tmp_path / "runs"),
                          "--results", str(tmp_path / "results")],
                         cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-4000:]
    assert "submitit" in res.stderr.lower()  # the launcher that ran the jobs
    assert any((tmp_path / "submitit").rglob("*_result.pkl"))  # submitit's own record of each job
    md = (tmp_path / "results" / "tiny.md").read_text()
    assert "| copy (reference) | 1/1 |" in md and "| gtwarp (reference) | 1/1 |" in md
    rows = list(csv.DictReader(open(tmp_path / "results" / "tiny.csv")))
    assert [(r["row"], r["status"]) for r in rows] == [("copy", "done"), ("gtwarp", "done")]
    assert all(float(r["l1"]) > 0 and r["n_pairs"] == "4" for r in rows)
    assert len(list((tmp_path / "submitit").rglob("*_result.pkl"))) == 2


def test_gathered_rows_are_each_pair_once_in_dataset_order():
    from nvs.module.gather import gather_rows

    # what two ranks hold for 5 items: rank 0 reads 0, 2, 4; rank 1 reads 1, 3 and the padding repeat of 0
    rank0 = [{"index": i, "l1": float(i)} for i in (0, 2, 4)]
    rank1 = [{"index": i, "l1": float(i)} for i in (1, 3, 0)]
    assert gather_rows(rank0 + rank1) == [{"l1": float(i)} for i in range(5)]
