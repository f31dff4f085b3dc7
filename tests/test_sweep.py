"""Study files compose; collection, planning and resumption of nvs.sweep; Pareto front; figures' unprojection."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from nvs import pareto, sweep
from nvs.report import pareto as pareto_lib
from nvs.run.config_check import check_config
from tests.conftest import compose_train

REPO = Path(__file__).resolve().parents[1]
STUDIES = sorted((REPO / "sweeps").glob("*.yaml"))


def _compose_row(study: sweep.Study, row: sweep.Row, seed: int = 0):
    name = "train" if row.kind == "train" else "evaluate"
    return compose_train([*sweep.row_overrides(study, row), f"seed={seed}"], config_name=name)


# -- study files ---------------------------------------------------------------------------------------------------
def test_the_studies_exist():
    assert {p.stem for p in STUDIES} >= {"comparison_objects", "comparison_drive", "ablation", "depth", "skip"}


@pytest.mark.parametrize("path", STUDIES, ids=lambda p: p.stem)
@pytest.mark.parametrize("scale", [{}, {"size": 256, "steps": 140000}], ids=["study-scale", "paper-scale"])
def test_every_study_row_composes_with_the_real_config(path, scale, tmp_path):
    study = sweep.load_study(path, **scale)
    assert study.rows and study.seeds
    for row in study.rows:
        cfg = _compose_row(study, row)
        check_config("train" if row.kind == "train" else "evaluate", cfg)  # the typed schema takes every row
        if row.evaluates:  # an evaluation row: nvs.evaluate's settings only; data and model come with the checkpoint
            assert cfg.ckpt_path is None and cfg.data.get("name") is None, row.name
            continue
        cfg.paths.output_dir = str(tmp_path)
        if row.reference:
            cfg.out_dir = str(tmp_path)
        OmegaConf.resolve(cfg)
        assert cfg.data.size == study.size, row.name
        if row.reference:
            assert cfg.model.name == row.reference and cfg.data.name == row.data
        else:
            assert cfg.trainer.max_steps == study.steps, row.name
        # Every reference row and every trained row that names its data lands on that dataset.
        assert row.data is None or cfg.data.name == row.data


def test_each_study_carries_every_reference_row_per_dataset():
    """Floors and ceilings in every table: copy source, the ground-truth warp, the constant depth at the training
    mean, and (an oracle) each image's plane at its ground-truth mean."""
    for path in STUDIES:
        study = sweep.load_study(path)
        datasets = {_compose_row(study, r).data.name for r in study.rows if r.kind == "train"}
        for data in datasets:
            refs = {r.reference: r for r in study.rows if r.reference and r.data == data}
            assert set(refs) == {"copy_source", "gt_warp", "mean_depth", "gt_plane"}, (path.stem, data)
            assert refs["gt_plane"].oracle and not refs["mean_depth"].oracle, (path.stem, data)


def test_runs_shared_between_studies_have_the_same_config(tmp_path):
    """A run name used by several studies (chen_chairs, nvs_chairs, ...) must be one job, not a silent conflict."""
    keys: dict[str, tuple[str, str, str]] = {}
    users: dict[str, set[str]] = {}
    for path in STUDIES:
        study = sweep.load_study(path)
        for job in sweep.plan(study, tmp_path):
            users.setdefault(job.dir.name, set()).add(study.name)
            seen = keys.setdefault(job.dir.name, (job.key, job.digest, study.name))
            assert seen[0] == job.key, f"{job.dir.name}: {seen[2]} and {study.name} define it differently"
            assert seen[1] == job.digest, f"{job.dir.name}: {seen[2]} and {study.name} compose it differently"
    # Seed 0 of the tables' method rows is the convergence study's job: trained once, reused by every table.
    assert users["nvs_chairs_conv_s0"] == {"convergence", "ablation", "depth", "comparison_objects", "fidelity",
                                           "data_scale", "route"}
    assert users["chen_drive_conv_s0"] == {"convergence", "comparison_drive"}
    # the route study's trained rows are the comparison studies' jobs, not jobs of its own
    assert users["fid_colour_norms_s1"] >= {"comparison_objects", "route"}
    assert users["fid_colour_norms_drive_s0"] >= {"comparison_drive", "route"}


def test_ablation_rows_switch_what_they_say():
    study = sweep.load_study(REPO / "sweeps" / "ablation.yaml")
    cfg = {r.name: _compose_row(study, r) for r in study.rows if not r.reference}
    full = ["recon", "vgg", "depth_consistency", "edge_smooth", "warp"]
    assert list(cfg["nvs_chairs"].loss) == full and cfg["nvs_chairs"].model.skips._target_.endswith("WarpedSkips")
    assert list(cfg["baseline_arch"].loss) == ["recon"] and list(cfg["baseline_arch"].loss.recon.scale_weights) == [1.0]
    assert cfg["wo_skip"].model.skips._target_.endswith("NoSkips")
    assert list(cfg["wo_conv0"].model.skips.levels) == ["conv2", "conv3", "conv4"]
    assert list(cfg["wo_multiscale"].loss) == full and list(cfg["wo_multiscale"].loss.recon.scale_weights) == [1.0]
    for row, term in (("wo_vgg", "vgg"), ("wo_depth", "depth_consistency"), ("wo_edge", "edge_smooth")):
        assert list(cfg[row].loss) == [t for t in full if t != term], row
    assert cfg["chen_chairs"].model.name == "chen"


def test_skip_study_rows_switch_what_they_say():
    study = sweep.load_study(REPO / "sweeps" / "skip.yaml")
    assert study.table == "cost" and study.group_by == "data"
    trained = {r.name: _compose_row(study, r) for r in study.rows if r.kind == "train"}
    assert {c.data.name for c in trained.values()} == {"chairs", "cars", "drive"}
    # every trained row is the norms-fixed network: the one whose test chairs do not fail through colour norms
    assert all((c.model.conv0_norm, c.model.decoder_norm) == ("none", "batch") for c in trained.values())
    rows = {r.name: r for r in study.rows}
    for data in ("chairs", "cars", "drive"):
        def get(name):
            return trained[name.format(data)].model

        def parts(name):
            m = get(name)
            return m.skips._target_.rsplit(".", 1)[1], m.depth._target_.rsplit(".", 1)[1], list(m.skips.levels)

        four, three = ["conv0", "conv2", "conv3", "conv4"], ["conv2", "conv3", "conv4"]
        assert parts("nvs_normfix_{}") == ("WarpedSkips", "PredictedDepth", four)
        assert parts("skip_plane_{}") == ("WarpedSkips", "PlaneDepth", four)
        assert parts("skip_wo_conv0_{}") == ("WarpedSkips", "PredictedDepth", three)
        assert parts("skip_lean_{}") == ("WarpedSkips", "PlaneDepth", three)
        assert parts("skip_oracle_{}") == ("WarpedSkips", "OracleDepth", four) and rows[f"skip_oracle_{data}"].oracle
        # the per-level skips: the full and the lean checkpoints evaluated with a calibrated threshold
        for evaluation, source in (("skips_normfix_{}", "nvs_normfix_{}"), ("skips_lean_{}", "skip_lean_{}")):
            row = rows[evaluation.format(data)]
            assert row.evaluates == source.format(data) and "skips_threshold=calibrate" in row.overrides


def test_skip_study_shares_its_full_rows_with_the_comparison_and_route_studies(tmp_path):
    """Nothing is trained twice: the full rows and the full model's per-level skips have the keys of the comparison
    studies' and route study's jobs."""
    skip = sweep.load_study(REPO / "sweeps" / "skip.yaml")
    others = [sweep.load_study(REPO / "sweeps" / f"{s}.yaml")
              for s in ("comparison_objects", "comparison_drive", "route")]
    shared = {r.name for r in skip.rows if r.name.startswith(("nvs_normfix_", "skips_normfix_"))}
    assert len(shared) == 6
    keys = {}
    for study in others:
        for j in sweep.plan(study, tmp_path, (), None):
            keys.setdefault(j.dir.name, set()).add(j.key)
    for j in sweep.plan(skip, tmp_path, (), None):
        if j.row.name in shared:
            assert keys.get(j.dir.name) == {j.key}, j.dir.name


@pytest.mark.slow
def test_skip_study_rows_run_end_to_end_on_fixture_data(objects_root, tmp_path):
    """The chairs rows of sweeps/skip.yaml, 2 steps each on the fixture data: every component trains, tests, and
    lands in the cost table with one pick."""
    raw = OmegaConf.to_container(OmegaConf.load(REPO / "sweeps" / "skip.yaml"))
    raw["rows"] = [{k: v for k, v in r.items() if k != "seeds"} for r in raw["rows"] if r["name"].endswith("_chairs")]
    raw.update(steps=2, overrides=[f"data.root={objects_root}", "trainer.val_check_interval=2",
                                   "data.loader.batch_size=2", "trainer.limit_val_batches=1",
                                   "trainer.enable_progress_bar=false"])
    study = tmp_path / "skip.yaml"
    study.write_text(json.dumps(raw))
    res = _sweep(str(study), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "results"))
    assert res.returncode == 0, res.stderr[-3000:]
    rows = {r["row"]: r for r in csv.DictReader(open(tmp_path / "results" / "skip.csv"))}
    assert len(rows) == 11 and all(r["status"] == "done" for r in rows.values())  # 5 trained, 2 evaluated, 4 reference
    assert rows["skips_lean_chairs"]["warp_skipped"] != "" and rows["nvs_normfix_chairs"]["warp_skipped"] == ""
    assert all(rows[r]["eval_forward_ms_per_image"] != "" for r in rows)
    md = (tmp_path / "results" / "skip.md").read_text()
    assert md.count("| ★ |") == 1 and "**Pick**:" in md and "(oracle)" in md


def test_sigterm_to_the_sweep_stops_its_running_job(tmp_path):
    """`kill <sweep pid>` must not leave the job it launched running (and writing its run directory) as an orphan."""
    import os
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "runner.py"
    pid_file = tmp_path / "child.pid"
    script.write_text(
        "import signal, sys\n"
        "from nvs import sweep\n"
        "signal.signal(signal.SIGTERM, sweep.interrupt_on_signal)\n"
        f"child = ['{sys.executable}', '-c', 'import os, time; open(r\"{pid_file}\", \"w\").write(str(os.getpid())); "
        "time.sleep(60)']\n"
        "try:\n"
        "    sweep.run_streaming(child, dict(__import__('os').environ))\n"
        "except KeyboardInterrupt:\n"
        "    sys.exit(130)\n")
    # PYTHONPATH: the script lives outside the checkout, so the checkout is not on its path otherwise
    proc = subprocess.Popen([sys.executable, str(script)], cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    for _ in range(200):
        if pid_file.exists() and pid_file.read_text():
            break
        time.sleep(0.05)
    child = int(pid_file.read_text())
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=20) == 130
    time.sleep(0.2)
    with pytest.raises(ProcessLookupError):
        os.kill(child, 0)


def _per_image(tmp_path, name, values, views=None):
    """A job directory whose test_per_image.csv holds l1 = values[k] and ssim_paper = 1 - values[k] for pair k;
    pair k shows object model m<k // 3> (views '<model>_<az>_0') unless ``views`` gives the target ids."""
    d = tmp_path / name
    d.mkdir()
    lines = ["index,id_src,id_tgt,l1,ssim_paper"]
    for k, v in enumerate(values):
        tgt = views[k] if views else f"m{k // 3}_{20 * (k % 3)}_0"
        lines.append(f"{k},{tgt}s,{tgt},{v},{'' if v is None else 1 - v}")
    (d / "test_per_image.csv").write_text("\n".join(lines).replace(",None,", ",,") + "\n")
    return d


def _ordered_row(name, dirs, paper_l1, paper_ssim=None):
    from nvs.sweep.bootstrap import seed_mean

    means = seed_mean(dirs)
    l1 = sum(v["l1"] for v in means.values()) / len(means) if means else 0.5
    paper = {"l1": paper_l1} | ({"ssim_paper": paper_ssim} if paper_ssim is not None else {})
    return {"row": name, "l1": (l1, None), "ssim_paper": (1 - l1, None), "paper": paper, "dirs": dirs}


def test_orderings_are_decided_by_a_two_level_bootstrap_over_seeds_and_test_models(tmp_path):
    from nvs.sweep.bootstrap import MAX_RESAMPLES, RESAMPLES

    n = 30  # 10 test models x 3 pairs
    a = _per_image(tmp_path, "a", [0.30 + 0.01 * (k % 5) for k in range(n)])
    b = _per_image(tmp_path, "b", [0.20 + 0.01 * (k % 5) for k in range(n)])
    # c is b +- 0.05 by model: the same mean, a spread that holds zero
    c = _per_image(tmp_path, "c", [0.20 + 0.01 * (k % 5) + (0.05 if (k // 3) % 2 else -0.05) for k in range(n)])
    rows = [_ordered_row("a", [a], 0.10, 0.80), _ordered_row("b", [b], 0.08, 0.90), _ordered_row("c", [c], 0.06, 0.95),
            {"row": "copy", "l1": (0.5, None), "ssim_paper": (0.1, None), "paper": {}, "dirs": []}]
    lines = sweep.orderings(rows, ["l1", "ssim_paper"])
    assert lines == sweep.orderings(rows, ["l1", "ssim_paper"])  # seeded: the same files give the same text
    assert "two-level bootstrap: each row's seeds, then the test models" in lines[0]
    assert f"{RESAMPLES} to {MAX_RESAMPLES} resamples" in lines[0]
    l1_at = next(i for i, line in enumerate(lines) if line.startswith("- **L1**"))
    assert "paper: c > b > a;" in lines[l1_at] and "of 3 pairs 2 agree, 0 swap, 1 unresolved" in lines[l1_at]
    pairs = {ln.split(":")[0].strip("- "): ln for ln in lines[l1_at + 1:l1_at + 4]}
    assert pairs["c / b"].startswith("  - c / b: unresolved (1 seed: c, b), Δ +0.00000 [-0.")
    assert "over 10 test models (30 pairs)" in pairs["c / b"]
    assert pairs["c / a"].startswith("  - c / a: agree (1 seed: c, a), Δ -0.10000 [-0.1")
    assert "b / a: agree (1 seed: b, a), Δ -0.10000" in pairs["b / a"]
    # the per-model trace: b beats a on every model (sign test 2 / 2^10 = 0.00195), and no three models undo it;
    # c - b is -0.05 on five models and +0.05 on the other five
    assert "; b better on 10/10 models, sign test p = 0.00195; undone without: ≥4 models" in pairs["b / a"]
    assert pairs["c / b"].endswith("; c better on 5/10 models, sign test p = 1")  # unresolved: nothing to undo
    # SSIM: higher is better; the same verdicts (the CSV's ssim_paper is 1 - l1)
    ssim_line = next(line for line in lines if line.startswith("- **SSIM (paper)**"))
    assert "of 3 pairs 2 agree, 0 swap, 1 unresolved" in ssim_line
    # c clearly worse than b: a swap, with an interval that excludes zero
    worse = _per_image(tmp_path, "worse", [0.25 + 0.01 * (k % 5) for k in range(n)])
    lines = sweep.orderings([_ordered_row("b", [b], 0.08), _ordered_row("c", [worse], 0.06)], ["l1"])
    assert "0 agree, 1 swap, 0 unresolved" in lines[2]
    assert "c / b: swap (1 seed: c, b), Δ +0.05000 [+0.05000, +0.05000]" in lines[3]
    assert sweep.orderings(rows[:1], ["l1"]) == []


def test_a_variant_is_decided_in_the_place_of_the_row_it_stands_for_and_never_against_it(tmp_path):
    n = 30
    wobble = [0.01 * (k % 5) for k in range(n)]
    # the paper: c > b > a on L1; v stands for b and is measured better than c, b worse than a
    c = _ordered_row("c", [_per_image(tmp_path, "c", [0.20 + w for w in wobble])], 0.06)
    b = _ordered_row("b", [_per_image(tmp_path, "b", [0.40 + w for w in wobble])], 0.08)
    a = _ordered_row("a", [_per_image(tmp_path, "a", [0.30 + w for w in wobble])], 0.10)
    v = {**_ordered_row("v", [_per_image(tmp_path, "v", [0.10 + w for w in wobble])], 0.0), "paper": {},
         "stands_for": "b"}
    plain = sweep.orderings([c, b, a], ["l1"])
    lines = sweep.orderings([c, b, a, v], ["l1"])
    # the paper's rows' lines are the same, the counts only theirs; the variant's pairs follow, marked, in b's place
    assert lines[0].startswith(plain[0]) and lines[0] != plain[0] and "v for b." in lines[0]
    assert lines[1:6] == plain[1:-1] and "of 3 pairs 2 agree, 1 swap, 0 unresolved" in lines[2]
    variant = lines[6:-1]
    assert [ln.split(":")[0] for ln in variant] == ["  - c / v (for b)", "  - v (for b) / a"]
    assert variant[0].startswith("  - c / v (for b): swap (1 seed: c, v), Δ +0.10000 [+0.10000, +0.10000]")
    assert variant[1].startswith("  - v (for b) / a: agree (1 seed: v, a), Δ -0.20000 [")
    assert "v better on 10/10 models" in variant[1]
    decided = sweep.decide([c, b, a, v], ["l1"])["l1"]
    assert [(o.a, o.b, o.a_for, o.b_for) for o in decided if o.stands_for] == [("c", "v", None, "b"),
                                                                                ("v", "a", "b", None)]
    assert not any({o.a, o.b} == {"v", "b"} for o in decided)  # never against the row it stands for
    # a variant without a finished job has no line and changes nothing; nor does one whose row never ran
    assert sweep.orderings([c, b, a, {**v, "l1": (None, None), "dirs": []}], ["l1"]) == plain
    unrun_b = {**b, "l1": (None, None), "dirs": []}
    only_variant = sweep.orderings([c, unrun_b, a, v], ["l1"])
    assert "paper: c > a; ours: c > a; of 1 pairs 1 agree, 0 swap" in only_variant[2]
    assert [ln.split(":")[0] for ln in only_variant[4:-1]] == ["  - c / v (for b)", "  - v (for b) / a"]


def test_the_bootstrap_averages_seeds_groups_scenes_by_sequence_and_names_missing_results(tmp_path):
    from nvs.sweep.bootstrap import group_of, paired_gap, read_seeds, seed_mean

    assert group_of("1a2b_c3_340_20") == ("models", "1a2b_c3") and group_of("03_000120") == ("sequences", "03")
    s0 = _per_image(tmp_path, "s0", [0.2, 0.4, None])
    s1 = _per_image(tmp_path, "s1", [0.4, 0.4, 0.6])
    mean = seed_mean([s0, s1])
    assert mean["m0_0_0s", "m0_0_0"]["l1"] == pytest.approx(0.3) and mean["m0_40_0s", "m0_40_0"]["l1"] == 0.6
    views = [f"{s:02d}_{f:06d}" for s in range(4) for f in range(5)]
    x = read_seeds([_per_image(tmp_path, "x", [0.1 * (k % 4) for k in range(20)], views)])
    y = read_seeds([_per_image(tmp_path, "y", [0.1 * (k % 4) + 0.01 for k in range(20)], views)])
    gap = paired_gap(x, y, "l1")
    assert gap.unit == "sequences" and (gap.n_groups, gap.n_pairs) == (4, 20)
    assert gap.diff == pytest.approx(-0.01) and gap.lo == pytest.approx(-0.01) and gap.hi == pytest.approx(-0.01)
    lines = sweep.orderings([_ordered_row("p", [s1], 0.1), {"row": "q", "l1": (0.3, None), "ssim_paper": (0, None),
                                                            "paper": {"l1": 0.2}, "dirs": []}], ["l1"])
    assert "p / q: unresolved, no per-image results" in lines[3]
    one = paired_gap(read_seeds([s1]), read_seeds([s0]), "l1")
    assert one.lo is None and "one test model" in one.why
    # only the pairs every seed of both rows has: s0 lacks pair 2, so a row with s0 and s1 is compared on two
    both = paired_gap(read_seeds([s0, s1]), read_seeds([s1]), "l1")
    assert (both.n_pairs, both.seeds, both.diff) == (2, (2, 1), pytest.approx((0.3 - 0.4 + 0.4 - 0.4) / 2))


# -- committed job files --------------------------------------------------------------------------------------------
def test_exported_jobs_rebuild_the_tables_on_a_fresh_clone(fabricated, tmp_path):
    study, root = fabricated
    full0 = root / "full_s0"
    (full0 / "checkpoints").mkdir()
    (full0 / "checkpoints" / "last.ckpt").write_bytes(b"weights")
    (full0 / "csv").mkdir()
    (full0 / "csv" / "metrics.csv").write_text("step,val/l1\n10,0.5\n")
    (full0 / "test_per_image.csv").write_text("index,id_src,id_tgt,l1\n0,m0_0_0,m0_20_0,0.1\n")
    results = tmp_path / "results"
    args = [str(study.path), "--results", str(results)]
    assert sweep.run([*args, "--collect-only", str(root), "--export-jobs"]) == 1  # chen s1 failed, noskip s1 missing
    exported = results / "jobs" / study.scale
    assert sorted(p.name for p in exported.iterdir()) == ["chen_s0", "copy_s0", "full_s0", "full_s1", "noskip_s0"]
    files = sorted(p.relative_to(exported / "full_s0").as_posix() for p in (exported / "full_s0").rglob("*")
                   if p.is_file())
    assert files == [".hydra/overrides.yaml", "csv/metrics.csv", "metrics.json", "sweep_job.json",
                     "test_per_image.csv"]  # never a checkpoint
    first_csv, first_md = (results / "fab.csv").read_text(), (results / "fab.md").read_text()
    assert f"{exported}/full_s0" in first_csv  # the tables read the committed copies, as a fresh clone will

    # A fresh clone: no runs directory at all, only the committed files.
    import shutil

    shutil.rmtree(root)
    fresh = tmp_path / "fresh"
    assert sweep.run([*args, "--collect-only", "--runs", str(tmp_path / "no_runs")]) == 1

    def done(text):  # every finished job's line (unfinished ones name this machine's run directory)
        return [ln for ln in text.splitlines() if ",done," in ln]

    assert len(done(first_csv)) == 5 and done((results / "fab.csv").read_text()) == done(first_csv)
    lines = {ln.split("|")[1].strip(): ln for ln in (results / "fab.md").read_text().splitlines()
             if ln.startswith("| ")}
    first = {ln.split("|")[1].strip(): ln for ln in first_md.splitlines() if ln.startswith("| ")}
    assert lines["Full model"] == first["Full model"] and lines["copy (reference)"] == first["copy (reference)"]
    # A job the runner would launch: exported jobs are done, the failed and the missing one are not.
    jobs = {(j.row.name, j.seed): j for j in sweep.plan(study, fresh, exported=exported)}
    assert jobs["full", 0].status == "done" and jobs["full", 0].dir == exported / "full_s0"
    assert jobs["chen", 1].status == "missing" and jobs["noskip", 1].status == "missing"
    assert {(j.row.name, j.seed) for j in sweep.to_launch(list(jobs.values()))} == {("chen", 1), ("noskip", 1)}
    # The same staleness rule as in runs/: a changed config makes committed results stale, so they are not used.
    changed = _study(tmp_path, overrides=["trainer.enable_progress_bar=false", "optim.lr=0.001"])
    jobs = {(j.row.name, j.seed): j for j in sweep.plan(changed, fresh, exported=exported)}
    assert jobs["full", 0].status == "missing" and jobs["copy", 0].status == "done"


def test_a_result_in_runs_is_preferred_and_a_new_export_replaces_the_old(fabricated, tmp_path):
    study, root = fabricated
    results = tmp_path / "results"
    assert sweep.run([str(study.path), "--results", str(results), "--collect-only", str(root), "--export-jobs"]) == 1
    exported = results / "jobs" / study.scale
    metrics = json.loads((root / "full_s0" / "metrics.json").read_text())
    (root / "full_s0" / "metrics.json").write_text(json.dumps(metrics | {"test": metrics["test"] | {"l1": 0.05}}))
    jobs = {(j.row.name, j.seed): j for j in sweep.plan(study, root, exported=exported)}
    assert jobs["full", 0].dir == root / "full_s0"
    assert sweep.run([str(study.path), "--results", str(results), "--collect-only", str(root), "--export-jobs"]) == 1
    assert json.loads((exported / "full_s0" / "metrics.json").read_text())["test"]["l1"] == 0.05
    assert not [p for p in exported.iterdir() if p.name.startswith(".")]  # no half-written export left behind


def test_the_stopping_rule_record_reaches_the_csv_the_header_and_the_export(fabricated, tmp_path):
    from nvs.run.convergence import RECORD
    from nvs.sweep.collect import CONVERGENCE

    assert CONVERGENCE == RECORD
    study, root = fabricated
    for name, outcome, step in (("full_s0", "converged", 6), ("full_s1", "max_steps", 10)):
        (root / name / RECORD).write_text(json.dumps({"outcome": outcome, "step": step, "reason": f"why {name}"}))
        metrics = json.loads((root / name / "metrics.json").read_text())
        (root / name / "metrics.json").write_text(json.dumps(metrics | {"steps": step}))
    results = tmp_path / "results"
    sweep.run([str(study.path), "--collect-only", str(root), "--results", str(results), "--export-jobs"])
    rows = {(r["row"], r["seed"]): r for r in csv.DictReader(open(results / "fab.csv"))}
    assert (rows["full", "0"]["stop"], rows["full", "0"]["stop_reason"]) == ("converged", "why full_s0")
    assert rows["full", "1"]["stop"] == "max_steps" and rows["chen", "0"]["stop"] == ""
    md = (results / "fab.md").read_text()
    assert "| steps | 10 at most (callbacks=convergence;" in md
    assert "1 of 2 trained jobs converged earlier, at steps 6–6" in md
    assert (results / "jobs" / study.scale / "full_s0" / RECORD).is_file()


@pytest.mark.slow
def test_a_tiny_study_with_the_stopping_rule_and_floors_is_rebuilt_from_its_committed_files(objects_root, tmp_path):
    """Run, export, remove the run directories (a fresh clone), --collect-only: the same rows and values."""
    stop = ["callbacks=convergence", "callbacks.convergence.min_improvement=10.0"]
    study = _tiny_study(tmp_path, objects_root, 8, stop,
                        [{"name": "floor", "reference": "mean_depth", "data": "chairs"},
                         {"name": "plane", "reference": "gt_plane", "data": "chairs", "oracle": True}])
    runs, results = tmp_path / "runs", tmp_path / "results"
    res = _sweep(str(study), "--runs", str(runs), "--results", str(results), "--export-jobs")
    assert res.returncode == 0, res.stderr[-3000:]
    assert "exported 3 finished job(s)" in res.stderr
    rows = {r["row"]: r for r in csv.DictReader(open(results / "tiny.csv"))}
    assert rows["recon_only"]["stop"] == "converged" and rows["recon_only"]["steps"] == "4"
    assert float(rows["plane"]["depth_l1"]) == pytest.approx(0.0, abs=1e-5)  # the fixture's depth is one plane
    first = (results / "tiny.csv").read_text()
    import shutil

    shutil.rmtree(runs)
    again = _sweep(str(study), "--runs", str(runs), "--results", str(results), "--collect-only")
    assert again.returncode == 0, again.stderr[-3000:]
    assert "3 done; launching 0" in again.stderr and (results / "tiny.csv").read_text() == first
    assert not list((results / "jobs").rglob("*.ckpt"))


def test_rows_launches_only_the_matching_rows_and_names_a_glob_that_matches_none(tmp_path, capsys):
    """--rows splits a study across sessions: only the matching rows are launched (here: planned by --dry-run)."""
    from nvs.core.errors import UserError
    from nvs.sweep.__main__ import run

    path = _study(tmp_path).path
    assert run([str(path), "--dry-run", "--runs", str(tmp_path / "runs"), "--rows", "c*,noskip"]) == 0
    err = capsys.readouterr().err
    launched = {(line.split()[2], line.split()[3]) for line in err.splitlines() if line.startswith("[sweep] -> ")}
    # trained rows over the study's seeds; a reference row needs no training, so seed 0 only
    assert launched == {(r, s) for r in ("chen", "noskip") for s in ("s0", "s1")} | {("copy", "s0")}
    with pytest.raises(UserError, match=f"'ful\\*x' matches no row of {path}; rows: full, chen, noskip, copy"):
        run([str(path), "--dry-run", "--runs", str(tmp_path / "runs"), "--rows", "chen,ful*x"])


def test_goals_compare_each_trained_row_with_the_floors_and_their_interval(tmp_path):
    n = 30  # 10 test models x 3 pairs
    copy = _per_image(tmp_path, "copy", [0.20 + 0.01 * (k % 5) for k in range(n)])
    good = _per_image(tmp_path, "good", [0.10 + 0.01 * (k % 5) for k in range(n)])  # ~45% below copying
    close = _per_image(tmp_path, "close", [0.18 + 0.01 * (k % 5) for k in range(n)])  # ~9% below
    # 25% below on average, +-0.04 by model: the interval holds the goal
    edge = _per_image(tmp_path, "edge", [0.165 + 0.01 * (k % 5) + (0.04 if (k // 3) % 2 else -0.04) for k in range(n)])

    def row(name, d, kind="train", reference=None):
        r = _ordered_row(name, [d], 0.1)
        return {**r, "label": name, "kind": kind, "reference": reference, "oracle": False, "paper": {},
                "depth_l1": (None, None)}

    rows = [row("good", good), row("close", close), row("edge", edge),
            row("copy", copy, kind="reference", reference="copy_source")]
    lines = sweep.goals(rows)
    assert lines[0].startswith("Goals of the converged studies")
    by_row = {ln.split(":")[0][2:]: ln for ln in lines[2:] if ln}
    assert set(by_row) == {"good", "close", "edge"}
    assert "L1 0.1200 against copying the source 0.2200: -45.5% [-45.5%, -45.5%]" in by_row["good"]
    assert by_row["good"].endswith("**met** (1 seed: good)") and by_row["close"].endswith("**not met** (1 seed: close)")
    assert by_row["edge"].endswith("**unresolved** (1 seed: edge)"), by_row["edge"]
    assert sweep.goals(rows[:3]) == []  # no floor in the table: nothing to say


def test_against_compares_every_trained_row_with_the_base_and_its_interval(tmp_path):
    n = 30  # 10 test models x 3 pairs
    base = _per_image(tmp_path, "base", [0.20 + 0.01 * (k % 5) for k in range(n)])
    lower = _per_image(tmp_path, "lower", [0.15 + 0.01 * (k % 5) for k in range(n)])
    higher = _per_image(tmp_path, "higher", [0.23 + 0.01 * (k % 5) for k in range(n)])
    # the base +- 0.05 by model: the same mean, a spread that holds zero
    mixed = _per_image(tmp_path, "mixed", [0.20 + 0.01 * (k % 5) + (0.05 if (k // 3) % 2 else -0.05) for k in range(n)])

    def row(name, d, kind="train"):
        r = _ordered_row(name, [d], 0.1)
        return {**r, "label": name.title(), "kind": kind, "reference": None, "oracle": False, "paper": {}}

    rows = [row("lower", lower), row("base", base), row("higher", higher), row("mixed", mixed),
            row("copy", base, kind="reference")]
    lines = sweep.against_base(rows, ("absent", "base"), ["l1", "ssim_paper"])
    assert lines == sweep.against_base(rows, ("absent", "base"), ["l1", "ssim_paper"])  # seeded
    assert lines[0].startswith("Against Base (`base`): Δ = row − base") and "two-level bootstrap" in lines[0]
    by_row = {ln.split(":")[0][2:]: ln for ln in lines[2:] if ln}
    assert set(by_row) == {"Lower", "Higher", "Mixed"}  # neither the base nor a reference row
    assert "L1 0.1700 (↓) Δ -0.05000 [-0.05000, -0.05000] **better** (1 seed: lower, base)" in by_row["Lower"]
    assert "SSIM (paper) 0.8300 (↑) Δ +0.05000 [+0.05000, +0.05000] **better**" in by_row["Lower"]
    assert "L1 0.2500 (↓) Δ +0.03000 [+0.03000, +0.03000] **worse**" in by_row["Higher"]
    assert "**unresolved**" in by_row["Mixed"] and "**better**" not in by_row["Mixed"]
    assert sweep.against_base(rows, ("absent",), ["l1"]) == []  # no base in this table: nothing to say
    assert sweep.against_base(rows, ("copy",), ["l1"]) == []  # a reference row is never a base
