"""Evaluation rows of a study (``evaluates: <trained row>``): schema, planning, waiting, command, key, export, tables.

No training: the trained jobs are fabricated job directories (metrics.json naming a fake checkpoint file), and the
sweep's launch is replaced by a function that writes what nvs.train / nvs.evaluate would.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest

import nvs.sweep.__main__ as sweep_main
from nvs import sweep
from nvs.core.errors import UserError
from nvs.sweep.collect import CSV_COLUMNS, collect, render_csv
from nvs.sweep import eval_rows
from nvs.sweep.eval_rows import WAITING
from nvs.sweep.jobs import JOB_RECORD, Status, job_key, plan, prepare_job_dir, to_launch
from nvs.sweep.launch import Launch, multirun_command
from nvs.sweep.tables import render_markdown

REPO = Path(__file__).resolve().parents[1]
VIEWS = [f"m{k // 3}_{20 * (k % 3)}_0" for k in range(12)]  # 4 test models, 3 pairs each
STUDY = {
    "name": "ev", "seeds": [0, 1], "size": 64, "steps": 10, "table": "cost", "group_by": "data",
    "metrics": ["l1", "ssim", "ssim_paper"], "overrides": ["trainer.enable_progress_bar=false"],
    "rows": [
        {"name": "full", "label": "Full model", "experiment": "nvs_chairs"},
        {"name": "routed", "label": "Routed", "evaluates": "full", "overrides": ["route=fit"]},
        {"name": "copy", "reference": "copy_source", "data": "chairs"},
    ],
}


def _study(tmp_path, **changes) -> sweep.Study:
    path = tmp_path / "ev.yaml"
    path.write_text(json.dumps({**STUDY, **changes}))
    return sweep.load_study(path)


def _jobs(study, root, exported=None) -> dict:
    return {(j.row.name, j.seed): j for j in plan(study, root, exported=exported)}


def _per_image(job_dir: Path, l1: list[float]) -> None:
    lines = ["index,id_src,id_tgt,l1,ssim,ssim_paper"]
    lines += [f"{k},{v}s,{v},{x},{1 - x},{1 - x}" for k, (v, x) in enumerate(zip(VIEWS, l1))]
    (job_dir / "test_per_image.csv").write_text("\n".join(lines) + "\n")


def _source_l1(seed: int) -> list[float]:
    return [0.1 + 0.01 * (k % 4) + 0.002 * seed for k in range(12)]


def _write_result(job, l1: list[float], checkpoint: Path | None = None, **extra) -> None:
    """What nvs.train (a checkpoint) or nvs.evaluate (routes, timings, the rule) leaves in a job directory."""
    test = {"l1": sum(l1) / len(l1), "ssim": 0.8, "ssim_paper": 0.9, "n_pairs": len(l1), **extra.pop("test", {})}
    if checkpoint is not None:
        checkpoint.parent.mkdir(parents=True, exist_ok=True)
        checkpoint.write_bytes(b"weights")
    (job.dir / "metrics.json").write_text(json.dumps({
        "data": "chairs", "image_size": 64, "seed": job.seed, "precision": "32-true", "device": "cpu: Fake",
        "git_sha": "abc", "eval_ms_per_image": 5.0, "eval_forward_ms_per_image": 4.0, "train_step_ms": 100.0,
        "checkpoint": str(checkpoint.resolve()) if checkpoint else None, "test": test, **extra}))
    _per_image(job.dir, l1)


def _train(job, root) -> Path:
    prepare_job_dir(job, root)
    ckpt = job.dir / "checkpoints" / "best-10.ckpt"
    _write_result(job, _source_l1(job.seed), ckpt)
    return ckpt


TIMING = {"64": {"network_ms_per_image": 5.1, "routed_ms_per_image": 2.9, "speedup": 1.76,
                 "routes_ms_per_image": {"copy": 0.02, "warp": 2.6, "full": 5.3}},
          "256": {"network_ms_per_image": 80.0, "routed_ms_per_image": 50.0, "speedup": 1.6,
                  "routes_ms_per_image": {"copy": 0.3, "warp": 40.0, "full": 82.0}}}


def _evaluate(job) -> None:
    """An evaluation with route=fit and time_sizes=[64,256]: routed L1 a little above the source's on every pair."""
    l1 = [x + 0.002 + 0.001 * (k % 2) for k, x in enumerate(_source_l1(job.seed))]
    _write_result(job, l1, test={"route_share_copy": 0.0, "route_share_warp": 0.93, "route_share_full": 0.07},
                  timing_by_size=TIMING)
    (job.dir / "route_rule.json").write_text(json.dumps({"kind": "nvs-route-rule", "version": 1}))


# -- the schema ------------------------------------------------------------------------------------------------------
def _rows(*extra):
    return [{"name": "a", "experiment": "nvs_chairs"}, {"name": "c", "reference": "copy_source", "data": "chairs"},
            *extra]


@pytest.mark.parametrize("rows, message", [
    (_rows({"name": "e", "evaluates": "x"}),
     r"s.yaml:\d+: rows\[2\].evaluates: 'x' is not a row of the study; an evaluation row evaluates one of: a$"),
    (_rows({"name": "e", "evaluates": "c"}), r"rows\[2\].evaluates: 'c' is a reference row, not a trained one"),
    (_rows({"name": "e", "evaluates": "a"}, {"name": "f", "evaluates": "e"}),
     r"rows\[3\].evaluates: 'e' is an evaluation row, not a trained one"),
    (_rows({"name": "e", "evaluates": "e"}), r"rows\[2\].evaluates: 'e' is an evaluation row"),
    (_rows({"name": "e", "evaluates": "a", "experiment": "nvs_chairs"}),
     r"rows\[2\].experiment: an evaluation row \(evaluates: a\) has no 'experiment'"),
    (_rows({"name": "e", "evaluates": "a", "seeds": 2}), r"rows\[2\].seeds: .* has no 'seeds' \(its seeds are"),
    (_rows({"name": "e", "evaluates": "a", "data": "cars"}), r"rows\[2\].data: .* has no 'data'"),
    (_rows({"name": "e", "evaluates": "a", "reference": "copy_source"}), r"rows\[2\].reference: .* has no 'reference'"),
    (_rows({"name": "e", "evaluates": "a", "paper": {"l1": 0.1}}), r"rows\[2\].paper: .* has no 'paper'"),
    (_rows({"name": "e", "evaluates": "a", "overrides": ["ckpt_path=x.ckpt"]}),
     r"rows\[2\].overrides\[0\]: 'ckpt_path=x.ckpt': the checkpoint is the evaluated job's \('a'\)"),
    (_rows({"name": "e", "evaluates": "a", "overrides": ["seed=3"]}), r"'seed=3' is set by the study"),
    (_rows({"name": "e", "evaluates": ["a"]}), r"rows\[2\].evaluates must be a string or null"),
])
def test_a_malformed_evaluation_row_is_one_clear_error(tmp_path, rows, message):
    path = tmp_path / "s.yaml"
    path.write_text(json.dumps({"size": 64, "steps": 2, "rows": rows}))
    with pytest.raises(UserError, match=message):
        sweep.load_study(path)


def test_the_error_names_the_line_of_the_key_and_against_names_no_evaluation_row(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("size: 64\nsteps: 2\nrows:\n  - name: a\n    experiment: nvs_chairs\n  - name: e\n"
                    "    evaluates: a\n    experiment: nvs_chairs\n")
    with pytest.raises(UserError, match=r"s.yaml:8: rows\[1\].experiment: an evaluation row"):
        sweep.load_study(path)
    path.write_text(json.dumps({"size": 64, "steps": 2, "against": ["e"],
                                "rows": _rows({"name": "e", "evaluates": "a"})}))
    with pytest.raises(UserError, match=r"against\[0\]: 'e' is not a trained row of the study; trained rows: a$"):
        sweep.load_study(path)


def test_an_evaluation_row_is_its_own_kind_with_the_evaluated_rows_seeds(tmp_path):
    study = _study(tmp_path, rows=[{"name": "full", "experiment": "nvs_chairs", "seeds": [1, 2]},
                                   {"name": "routed", "evaluates": "full", "overrides": ["route=fit"]}])
    kinds = {r.name: r.kind for r in study.rows}
    assert kinds == {"full": "train", "routed": "evaluate"}
    assert sweep.row_seeds(study, study.rows[1]) == (1, 2)
    assert sweep.row_seeds(sweep.load_study(study.path, seeds=[0]), study.rows[1]) == (0,)


# -- planning, waiting, the command ---------------------------------------------------------------------------------
def test_an_evaluation_job_waits_for_its_trained_jobs_checkpoint(tmp_path):
    study = _study(tmp_path)
    root = tmp_path / "runs" / study.scale
    jobs = _jobs(study, root)
    routed = jobs["routed", 0]
    assert routed.dir == root / "routed_s0" and routed.source is jobs["full", 0] and routed.data == "chairs"
    assert routed.waiting == WAITING.format(root / "full_s0")
    assert "waiting: needs" in routed.waiting and "committed jobs carry no weights" in routed.waiting
    assert {(j.row.name, j.seed) for j in to_launch(list(jobs.values()))} == {
        ("full", 0), ("full", 1), ("copy", 0)}
    assert all(not j.waiting for j in to_launch(list(jobs.values()), force=True))

    ckpt = _train(jobs["full", 0], root)
    jobs = _jobs(study, root)
    assert jobs["routed", 0].waiting == "" and eval_rows.tested_checkpoint(jobs["full", 0].dir) == ckpt.resolve()
    assert jobs["routed", 1].waiting  # seed 1 is not trained yet
    cmd = multirun_command(study, jobs["routed", 0].row, [0], root, Launch(), (), jobs["routed", 0].source)
    assert cmd[1:6] == ["-m", "nvs.evaluate", "-m", f"ckpt_path={ckpt.resolve()}", "route=fit"]
    assert "seed=0" in cmd and f"hydra.sweep.dir={root.resolve()}" in cmd
    assert "hydra.sweep.subdir=routed_s${seed}" in cmd and not any(c.startswith("data") for c in cmd)
    with pytest.raises(ValueError, match="runs alone"):  # two seeds are two checkpoints: never one command
        multirun_command(study, jobs["routed", 0].row, [0, 1], root, Launch(), (), jobs["routed", 0].source)

    ckpt.unlink()  # a done trained job whose checkpoint is not on this machine (committed files only)
    assert _jobs(study, root)["routed", 0].waiting == WAITING.format(root / "full_s0")


def test_the_key_hashes_the_evaluated_jobs_key_and_a_retrained_source_makes_it_stale(tmp_path):
    study = _study(tmp_path)
    root = tmp_path / "runs" / study.scale
    jobs = _jobs(study, root)
    routed = jobs["routed", 0]
    assert routed.key == job_key("evaluate", ["route=fit"], 0, jobs["full", 0].key)
    assert routed.key != job_key("evaluate", ["route=fit"], 0) != jobs["routed", 1].key
    # every other job's key is what it always was: kind, overrides and seed only
    full = jobs["full", 0]
    kept = [o for o in full.overrides if not o.startswith("trainer.enable_progress_bar")]  # a neutral key
    blob = json.dumps({"kind": "train", "overrides": kept, "seed": 0})
    assert full.key == hashlib.sha256(blob.encode()).hexdigest()[:16]
    # another trained row (its overrides changed): another trained job, so another evaluation
    other = _study(tmp_path, rows=[{**STUDY["rows"][0], "overrides": ["model/skips=none"]}, *STUDY["rows"][1:]])
    moved = _jobs(other, root)
    assert moved["full", 0].key != full.key and moved["routed", 0].key != routed.key
    # other evaluate settings: another evaluation
    fitted = _study(tmp_path, rows=[STUDY["rows"][0], {**STUDY["rows"][1], "overrides": ["route=off"]}])
    assert _jobs(fitted, root)["routed", 0].key != routed.key
    assert routed.fingerprint["route"] == "fit" and routed.fingerprint["evaluates"]["key"] == full.key

    _train(full, root)
    routed = _jobs(study, root)["routed", 0]
    prepare_job_dir(routed, root)
    _evaluate(routed)
    assert _jobs(study, root)["routed", 0].status == Status.DONE
    # the trained job done again under another config: its record (and digest) changes, the evaluation is stale
    record = json.loads((full.dir / JOB_RECORD).read_text())
    config = {**record["config"], "optim": {**record["config"]["optim"], "lr": 0.123}}
    (full.dir / JOB_RECORD).write_text(json.dumps({**record, "digest": "0123456789abcdef", "config": config}))
    again = _jobs(study, root)["routed", 0]
    assert again.status == Status.STALE and "evaluates.trained" in sweep.stale_error(again)


def test_an_evaluation_of_a_retrain_stays_done_beside_the_committed_record_of_the_same_config(tmp_path):
    """A fresh clone has the trained job's committed record in an older spelling (another digest, a key added since
    at its default) and the evaluation of a retrain of the same config, stamped with that retrain's digest."""
    study = _study(tmp_path)
    root = tmp_path / "runs" / study.scale
    full = _jobs(study, root)["full", 0]
    _train(full, root)
    routed = _jobs(study, root)["routed", 0]
    prepare_job_dir(routed, root)
    _evaluate(routed)
    exported = tmp_path / "exported"
    for job in (full, routed):
        (exported / job.dir.name).mkdir(parents=True)
        for name in (JOB_RECORD, "metrics.json", "test_per_image.csv"):
            (exported / job.dir.name / name).write_bytes((job.dir / name).read_bytes())
    stamped = json.loads((routed.dir / JOB_RECORD).read_text())["config"]["evaluates"]["trained"]
    assert stamped == full.digest
    older = json.loads((full.dir / JOB_RECORD).read_text())
    config = {**older["config"], "trainer": {k: v for k, v in older["config"]["trainer"].items() if k != "max_steps"}}
    (exported / full.dir.name / JOB_RECORD).write_text(json.dumps({**older, "digest": "b036856f38562e14",
                                                                   "config": config}))
    fresh = _jobs(study, tmp_path / "fresh", exported=exported)
    assert fresh["full", 0].status == Status.DONE and fresh["full", 0].dir == exported / full.dir.name
    assert fresh["routed", 0].status == Status.DONE and fresh["routed", 0].dir == exported / routed.dir.name
    # an evaluation stamped with neither digest is not taken from the committed files: it evaluated another training
    record = json.loads((exported / routed.dir.name / JOB_RECORD).read_text())
    record["config"]["evaluates"]["trained"] = "ffffffffffffffff"
    (exported / routed.dir.name / JOB_RECORD).write_text(json.dumps(record))
    assert _jobs(study, tmp_path / "fresh", exported=exported)["routed", 0].status == Status.MISSING


def test_a_committed_evaluation_stays_done_without_the_checkpoint_and_a_waiting_one_is_reported_missing(tmp_path):
    study = _study(tmp_path)
    root = tmp_path / "runs" / study.scale
    jobs = _jobs(study, root)
    for seed in (0, 1):
        _train(jobs["full", seed], root)
    jobs = _jobs(study, root)
    prepare_job_dir(jobs["routed", 0], root)
    _evaluate(jobs["routed", 0])
    results = tmp_path / "results"
    args = [str(study.path), "--results", str(results)]
    assert sweep.run([*args, "--collect-only", str(root), "--export-jobs"]) == 1  # copy s0 and routed s1 missing
    exported = results / "jobs" / study.scale
    assert (exported / "routed_s0" / "route_rule.json").is_file()  # the fitted rule travels with the job
    assert not list(exported.rglob("*.ckpt"))
    # a fresh clone: no runs/; the trained jobs are done from their committed files, which carry no weights
    import shutil

    shutil.rmtree(root)
    fresh = _jobs(study, tmp_path / "fresh", exported=exported)
    assert fresh["full", 1].status == Status.DONE and fresh["full", 1].dir == exported / "full_s1"
    assert fresh["routed", 0].status == Status.DONE  # done: its committed files stand for it
    assert fresh["routed", 1].status == Status.MISSING
    assert fresh["routed", 1].waiting == WAITING.format(exported / "full_s1")
    assert ("routed", 1) not in {(j.row.name, j.seed) for j in to_launch(list(fresh.values()))}
    records = {(r["row"], r["seed"]): r for r in collect(list(fresh.values()))}
    assert records["routed", 1]["status"] == "missing" and records["routed", 1]["error"].startswith("waiting: needs")


# -- one sweep: trained rows first, then the evaluations of their checkpoints --------------------------------------
def test_one_sweep_trains_first_then_evaluates_and_tabulates(tmp_path, monkeypatch, capsys):
    study = _study(tmp_path)
    runs, results = tmp_path / "runs", tmp_path / "results"
    launched = []

    def fake_launch(study, jobs, root, launch, extra=(), keep_fds=(), progress=None):
        for j in jobs:
            launched.append((j.row.name, j.seed))
            if j.kind == "evaluate":  # the command it would run names its own trained job's checkpoint
                cmd = multirun_command(study, j.row, [j.seed], root, launch, extra, j.source)
                assert f"ckpt_path={(j.source.dir / 'checkpoints' / 'best-10.ckpt').resolve()}" in cmd
                _evaluate(j)
            elif j.kind == "train":
                _write_result(j, _source_l1(j.seed), j.dir / "checkpoints" / "best-10.ckpt")
            else:
                _write_result(j, [0.4] * 12)
            j.status = Status.DONE
        return jobs

    monkeypatch.setattr(sweep_main, "launch_row", fake_launch)
    monkeypatch.setattr(sweep_main, "check_precision", lambda *a, **k: None)
    monkeypatch.setattr(sweep_main, "check_launch", lambda *a, **k: None)
    assert sweep.run([str(study.path), "--runs", str(runs), "--results", str(results)]) == 0
    err = capsys.readouterr().err
    assert "(after full_s0, trained first in this run)" in err
    assert launched == [("full", 0), ("full", 1), ("copy", 0), ("routed", 0), ("routed", 1)]

    md = (results / "ev.md").read_text()
    header = next(ln for ln in md.splitlines() if ln.startswith("| Configuration"))
    assert "| Warps skipped | Routes (copy/warp/full) | Eval 64² (ms/img) | × 64² | Eval 256² (ms/img) | × 256² | " \
           "Pick |" in header
    row = {ln.split("|")[1].strip(): [c.strip() for c in ln.split("|")[1:-1]] for ln in md.splitlines()
           if ln.startswith("| ") and not ln.startswith("| Configuration")}
    at = header.split("|")[1:-1]
    cell = {name.strip(): i for i, name in enumerate(at)}
    assert row["Routed"][cell["Routes (copy/warp/full)"]] == "0/93/7"
    assert row["Routed"][cell["Eval 64² (ms/img)"]] == "2.9 ± 0.0" and row["Routed"][cell["× 256²"]] == "1.60×"
    assert row["Full model"][cell["Routes (copy/warp/full)"]] == "—" and row["Full model"][cell["× 64²"]] == "—"
    assert row["Routed"][cell["Train (ms/step)"]] == "—" and row["Routed"][cell["Pick"]] == ""
    # under the table: the routed L1 against the full decoder's, paired on the same test pairs, with its interval
    line = next(ln for ln in md.splitlines() if ln.startswith("- Routed"))
    assert re.match(r"- Routed \(`route=fit`\) against Full model: ΔL1 \+0\.00250 \[\+0\.002\d\d, \+0\.00\d\d\d\] "
                    r"over 4 test models \(12 pairs\), 2 seeds: \*\*worse\*\*; not shown within 1% of its L1 "
                    r"\(0\.00\d+\); eval 256² 1\.60× faster than the network alone\.$", line), line
    assert "An evaluation row evaluates a trained row's checkpoints again" in md
    csv_header = (results / "ev.csv").read_text().splitlines()[0].split(",")
    assert csv_header[len(CSV_COLUMNS):] == ["route_share_copy", "route_share_warp", "route_share_full",
                                             "eval_64px_ms_per_image", "eval_64px_speedup",
                                             "eval_256px_ms_per_image", "eval_256px_speedup"]
    # run again: everything is done, nothing is launched
    launched.clear()
    assert sweep.run([str(study.path), "--runs", str(runs), "--results", str(results)]) == 0
    assert launched == []


def test_rows_that_leave_out_the_trained_row_launch_only_the_evaluations_whose_checkpoint_is_here(
        tmp_path, monkeypatch, capsys):
    study = _study(tmp_path, rows=STUDY["rows"][:2])
    runs, results = tmp_path / "runs", tmp_path / "results"
    root = runs / study.scale
    _train(_jobs(study, root)[("full", 0)], root)  # seed 0 trained here, seed 1 not
    launched = []

    def fake_launch(study, jobs, root, launch, extra=(), keep_fds=(), progress=None):
        for j in jobs:
            launched.append((j.row.name, j.seed))
            _evaluate(j)
            j.status = Status.DONE
        return jobs

    monkeypatch.setattr(sweep_main, "launch_row", fake_launch)
    monkeypatch.setattr(sweep_main, "check_precision", lambda *a, **k: None)
    monkeypatch.setattr(sweep_main, "check_launch", lambda *a, **k: None)
    assert sweep.run([str(study.path), "--runs", str(runs), "--results", str(results), "--rows", "routed",
                      "--dry-run"]) == 0
    err = capsys.readouterr().err
    assert "trained first in this run" not in err
    assert re.search(r"routed +s1 .*\(waiting: needs .*full_s1's checkpoint", err), err
    # 1: seed 1 (its trained job and its evaluation) is still missing
    assert sweep.run([str(study.path), "--runs", str(runs), "--results", str(results), "--rows", "routed"]) == 1
    assert launched == [("routed", 0)]


def test_an_evaluation_whose_trained_job_failed_is_left_waiting_not_failed(tmp_path, monkeypatch, capsys):
    study = _study(tmp_path, rows=STUDY["rows"][:2], seeds=[0])
    runs, results = tmp_path / "runs", tmp_path / "results"

    def fake_launch(study, jobs, root, launch, extra=(), keep_fds=(), progress=None):
        assert all(j.kind == "train" for j in jobs), "an evaluation without its checkpoint was launched"
        for j in jobs:
            (j.dir / sweep.FAILED).write_text("RuntimeError: boom\n")
            j.status = Status.FAILED
        return jobs

    monkeypatch.setattr(sweep_main, "launch_row", fake_launch)
    monkeypatch.setattr(sweep_main, "check_precision", lambda *a, **k: None)
    monkeypatch.setattr(sweep_main, "check_launch", lambda *a, **k: None)
    assert sweep.run([str(study.path), "--runs", str(runs), "--results", str(results)]) == 1
    assert "routed s0: not launched, waiting: needs" in capsys.readouterr().err
    records = list(csv_rows(results / "ev.csv"))
    assert [(r["row"], r["status"]) for r in records] == [("full", "failed"), ("routed", "missing")]
    assert records[1]["error"].startswith("waiting: needs")


def csv_rows(path: Path):
    import csv

    with open(path, newline="") as f:
        yield from csv.DictReader(f)


# -- a table without evaluations is the one it always was ------------------------------------------------------------
def test_a_cost_table_without_routes_or_timings_has_its_old_columns_and_legend(tmp_path):
    study = _study(tmp_path, rows=[STUDY["rows"][0], STUDY["rows"][2]], seeds=[0])
    root = tmp_path / "runs" / study.scale
    jobs = _jobs(study, root)
    _train(jobs["full", 0], root)
    prepare_job_dir(jobs["copy", 0], root)
    _write_result(jobs["copy", 0], [0.4] * 12)
    records = collect(list(_jobs(study, root).values()))
    md = render_markdown(study, records, {"command": "c", "git_sha": "s", "job_shas": [], "date": "d",
                                          "devices": []})
    header = next(ln for ln in md.splitlines() if ln.startswith("| Configuration"))
    assert header == ("| Configuration | n | Eval (ms/img) | × | Train (ms/step) | L1 ↓ | SSIM ↑ | SSIM (paper) ↑ | "
                      "ΔL1 | Warps skipped | Pick | Status |")
    legend = next(ln for ln in md.splitlines() if ln.startswith("Eval is the forward pass"))
    assert legend.endswith("per level conv0/conv2/conv3/conv4 in %.")
    assert not any(ln.startswith("- ") for ln in md.splitlines())
    assert render_csv(records).splitlines()[0] == ",".join(CSV_COLUMNS)


# -- the route study -------------------------------------------------------------------------------------------------
def test_the_route_studys_trained_rows_are_the_committed_comparison_jobs(tmp_path):
    study = sweep.load_study(REPO / "sweeps" / "route.yaml")
    assert study.table == "cost" and study.metrics == ("l1", "ssim", "ssim_paper")
    evaluations = {r.name: r for r in study.rows if r.kind == "evaluate"}
    datasets = ("chairs", "cars", "drive")
    routes = {f"route{m}{n}_{d}" for m in ("", "_margin") for n in ("", "_normfix") for d in datasets if n or not m}
    assert set(evaluations) == routes | {f"skips_normfix_{d}" for d in datasets}
    for name, r in evaluations.items():  # the default rule, and the norms-fixed networks' rule with a margin
        if name.startswith("skips_"):  # per-level warp skips of the norms-fixed network, threshold calibrated
            assert r.overrides == ("skips_threshold=calibrate", "time_sizes=[64]") and r.evaluates == name.replace("skips", "nvs"), name
            continue
        margin = ("calibration.tolerance=-0.05",) if "margin" in name else ()
        assert r.overrides == ("route=fit", *margin, "time_sizes=[64,256]"), name
    for name in ("comparison_objects", "comparison_drive"):
        other = sweep.load_study(REPO / "sweeps" / f"{name}.yaml")
        assert other.overrides == study.overrides and (other.size, other.steps) == (study.size, study.steps)
    exported = REPO / "results" / "jobs" / study.scale
    jobs = plan(study, tmp_path / "runs", exported=exported)
    committed = {d.name for d in exported.iterdir()}
    trained = [j for j in jobs if j.kind == "train" and j.dir.name in committed]
    assert {j.dir.name for j in trained} >= {"fid_colour_norms_s0", "fid_colour_norms_s1", "fid_colour_norms_s2",
                                            "nvs_chairs_conv_s0", "fid_colour_norms_drive_s0", "nvs_drive_conv_s0",
                                            "nvs_cars_conv_s0"}
    assert all(j.status == Status.DONE and j.dir.parent == exported for j in trained), \
        [(j.dir.name, j.status) for j in trained]
    for j in jobs:
        if j.kind == "evaluate" and j.status != Status.DONE:  # waits exactly where the checkpoint is not here
            here = j.source.status == Status.DONE and eval_rows.tested_checkpoint(j.source.dir) is not None
            assert bool(j.waiting) != here, j.dir.name


def test_without_an_interval_the_margin_is_read_on_the_shared_pairs_not_the_rows_means(tmp_path):
    from nvs.sweep.eval_table import Columns, evaluation_line

    def job(name, l1):
        d = tmp_path / name
        d.mkdir()
        lines = ["index,id_src,id_tgt,l1"] + [f"{k},m0_{20 * k}_0s,m0_{20 * k}_0,{x}" for k, x in enumerate(l1)]
        (d / "test_per_image.csv").write_text("\n".join(lines) + "\n")
        return d

    # one test model: nothing to resample. The means differ by far more than the margin (another pair set, e.g.
    # limit=), but on the pairs both were tested on the evaluation is 0.0005 worse, within 1% of 0.1 (0.001)
    src = {"row": "full", "label": "Full", "l1": (0.1, None), "seeds": [0], "dirs": [job("full", [0.1] * 3)]}
    r = {"row": "routed", "label": "Routed", "l1": (0.5, None), "overrides": ("route=fit",), "seeds": [0],
         "dirs": [job("routed", [0.1005] * 3)]}
    line = evaluation_line(r, src, Columns())
    assert "ΔL1 +0.00050 over 1 test models (3 pairs); one test model: nothing to resample" in line
    assert "1 seed (no seed spread in the interval): **unresolved**" in line
    assert line.endswith("; within 1% of its L1 (0.0010) by the point estimate."), line
    far = {**r, "dirs": [job("far", [0.2] * 3)]}
    assert evaluation_line(far, src, Columns()).endswith("; not shown within 1% of its L1 (0.0010).")


def test_an_evaluation_that_changes_no_test_pair_is_identical_without_a_bootstrap(tmp_path, monkeypatch):
    from nvs.sweep import eval_table
    from nvs.sweep.eval_table import Columns, evaluation_line

    def job(name, l1):
        d = tmp_path / name
        d.mkdir()
        lines = ["index,id_src,id_tgt,l1"] + [f"{k},m{k}_0_0s,m{k}_0_0,{x}" for k, x in enumerate(l1)]
        (d / "test_per_image.csv").write_text("\n".join(lines) + "\n")
        return d

    # a route that sends every pair to the full decoder: the evaluation's images are the trained row's, bit for bit
    monkeypatch.setattr(eval_table, "paired_by_seed", lambda *a, **k: pytest.fail("bootstrapped a zero difference"))
    l1 = [0.1, 0.2, 0.3, 0.4]
    src = {"row": "full", "label": "Full", "l1": (0.25, None), "seeds": [1, 2],
           "dirs": [job("full1", l1), job("full2", l1)]}
    r = {"row": "routed", "label": "Routed", "l1": (0.25, None), "overrides": ("route=fit",), "seeds": [1, 2],
         "dirs": [job("routed1", l1), job("routed2", l1)], "eval_256px_speedup": (0.98, None)}
    line = evaluation_line(r, src, Columns(sizes=(256,)))
    assert line == ("- Routed (`route=fit`) against Full: the same L1 on every test pair (8 pairs over 2 seeds): "
                    "**identical**; eval 256² 0.98× slower than the network alone."), line
