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


def _summary_row(name, l1, ms, kind="train", oracle=False):
    row = {"row": name, "label": name, "kind": kind, "oracle": oracle, "l1": (l1, None),
           sweep.PICK_COST: (ms, None)}
    return row


def test_pick_is_the_cheapest_row_within_one_percent_of_the_best_non_oracle_l1():
    rows = [_summary_row("full", 0.1000, 10.0), _summary_row("skip", 0.1009, 7.0),
            _summary_row("cheaper_but_worse", 0.1011, 5.0), _summary_row("oracle", 0.0500, 1.0, oracle=True),
            _summary_row("copy", 0.0900, 0.1, kind="reference"), _summary_row("untimed", 0.1001, None),
            _summary_row("unfinished", None, 0.5)]
    best, pick = sweep.pick_cheapest(rows)
    assert (best["row"], pick["row"]) == ("full", "skip")
    best, pick = sweep.pick_cheapest(rows, tolerance=0.02)
    assert pick["row"] == "cheaper_but_worse"
    # Nothing cheaper within the margin: the best row is its own pick.
    best, pick = sweep.pick_cheapest([_summary_row("full", 0.1, 10.0), _summary_row("plane", 0.2, 5.0)])
    assert best is pick and pick["row"] == "full"
    # Equal cost: the lower L1 wins; no eligible row: no pick.
    assert sweep.pick_cheapest([_summary_row("a", 0.1005, 5.0), _summary_row("b", 0.1, 5.0)])[1]["row"] == "b"
    assert sweep.pick_cheapest([_summary_row("oracle", 0.05, 1.0, oracle=True)]) == (None, None)


def test_the_pick_is_decided_by_the_interval_of_its_l1_against_the_best(tmp_path):
    n = 30  # 10 test models x 3 pairs
    base = [0.20 + 0.01 * (k % 5) for k in range(n)]
    full = _per_image(tmp_path, "full", base)
    # 0.5% worse on every pair: the interval is tight and its upper end inside the 1% margin
    close = _per_image(tmp_path, "close", [v * 1.005 for v in base])
    # 0.5% worse on the mean, but +-10% by test model: the point estimate is within 1%, the interval is not
    noisy = _per_image(tmp_path, "noisy", [v * (1.005 + (0.1 if (k // 3) % 2 else -0.1)) for k, v in enumerate(base)])

    def row(name, d, ms):
        mean = sum(float(x.split(",")[3]) for x in (d / "test_per_image.csv").read_text().splitlines()[1:]) / n
        return {**_summary_row(name, mean, ms), "dirs": [d]}

    rows = [row("full", full, 10.0), row("close", close, 7.0), row("noisy", noisy, 5.0)]
    assert rows[2]["l1"][0] <= rows[0]["l1"][0] * 1.01  # the point estimate alone would pick the noisy row
    best, pick = sweep.pick_cheapest(rows)
    assert (best["row"], pick["row"]) == ("full", "close")
    ok, gap = sweep.within_margin(rows[2], best)
    assert not ok and gap.lo < 0.01 * best["l1"][0] < gap.hi
    ok, gap = sweep.within_margin(rows[1], best)
    assert ok and 0 < gap.lo <= gap.hi <= 0.01 * best["l1"][0]
    # Without per-image results the point estimate decides, and says so.
    assert sweep.within_margin(_summary_row("x", 0.2009, 1.0), {**_summary_row("b", 0.2, 2.0)}) == (True, None)
    from nvs.sweep.tables import _pick_sentence
    gap = sweep.within_margin(pick, best)[1]
    assert "shown by the interval of ΔL1 against it, Δ +0.00" in _pick_sentence(best, pick, rows[0], "1%", gap)


COST_STUDY = {
    "name": "cost", "seeds": [0], "size": 64, "steps": 10, "group_by": "data", "table": "cost",
    "metrics": ["l1", "ssim"],
    "rows": [
        {"name": "full_chairs", "label": "Full", "experiment": "nvs_chairs"},
        {"name": "lean_chairs", "label": "Lean", "experiment": "nvs_chairs", "overrides": ["model/depth=plane"]},
        {"name": "oracle_chairs", "label": "Oracle", "experiment": "nvs_chairs", "oracle": True,
         "overrides": ["model/depth=oracle"]},
        {"name": "full_drive", "label": "Full", "experiment": "nvs_drive"},
        {"name": "adaptive_drive", "label": "Adaptive", "experiment": "nvs_drive",
         "overrides": ["model/skips=adaptive"]},
        {"name": "copy_drive", "label": "Copy", "reference": "copy_source", "data": "drive"},
    ],
}
COST_RESULTS = {  # row: (l1, eval forward ms, train step ms, warp_skipped per level or None)
    "full_chairs": (0.100, 8.0, 300.0, None), "lean_chairs": (0.120, 4.0, 200.0, None),
    "oracle_chairs": (0.050, 7.0, 250.0, None), "full_drive": (0.200, 8.0, 300.0, None),
    "adaptive_drive": (0.201, 5.0, 280.0, {"conv0": 0.0, "conv2": 0.25, "conv3": 0.5, "conv4": 0.75}),
    "copy_drive": (0.300, 0.5, None, None),
}


def test_cost_table_marks_the_pick_per_dataset(tmp_path):
    path = tmp_path / "cost.yaml"
    path.write_text(json.dumps(COST_STUDY))
    study = sweep.load_study(path)
    root = tmp_path / "runs"
    for job in sweep.plan(study, root):
        l1, fwd, step, skipped = COST_RESULTS[job.row.name]
        sweep.prepare_job_dir(job, root)
        test = {"l1": l1, "ssim": 0.8, "ssim_paper": 0.9, "psnr": 20.0, "lpips": 0.1, "n_pairs": 4}
        if skipped:
            test.update({f"warp_skipped_{lv}": v for lv, v in skipped.items()},
                        warp_skipped=sum(skipped.values()) / len(skipped))
        (job.dir / "metrics.json").write_text(json.dumps({
            "data": job.data, "eval_ms_per_image": fwd + 20, "eval_forward_ms_per_image": fwd,
            "train_step_ms": step, "device": "cpu: Fake CPU (2 threads)", "test": test}))
    results = tmp_path / "results"
    assert sweep.run([str(path), "--collect-only", str(root), "--results", str(results)]) == 0
    md = (results / "cost.md").read_text()
    chairs, drive = md.split("## chairs")[1].split("## drive")
    line = {(grp, ln.split("|")[1].strip()): ln for grp, text in (("chairs", chairs), ("drive", drive))
            for ln in text.splitlines() if ln.startswith("| ") and "---" not in ln}
    # chairs: the plane row is 2x faster but 20% worse; the oracle is better and cheaper but never the pick.
    assert "| ★ |" in line["chairs", "Full"] and "★" not in line["chairs", "Lean"] + line["chairs", "Oracle (oracle)"]
    assert "| 1.00× | 300 | 0.1000 | 0.8000 | +0.0% |" in line["chairs", "Full"]
    assert "| 2.00× |" in line["chairs", "Lean"] and "+20.0%" in line["chairs", "Lean"]
    assert "-50.0%" in line["chairs", "Oracle (oracle)"]
    assert "nothing can be skipped here" in chairs
    # The CSV marks the oracle row's jobs (nvs.pareto leaves them out), only those.
    with open(results / "cost.csv") as f:
        marked = {r["row"]: r["oracle"] for r in csv.DictReader(f)}
    assert marked == {name: "True" if name == "oracle_chairs" else "" for name in COST_RESULTS}
    # drive: the adaptive row is within 1% and cheaper: the pick, with its skipped warps per level.
    assert "| ★ |" in line["drive", "Adaptive"] and "| 1.60× | 280 |" in line["drive", "Adaptive"]
    assert "| 38% (0/25/50/75) |" in line["drive", "Adaptive"] and "| — |" in line["drive", "Full"]
    assert "1.60× faster than Full at +0.5% L1" in drive
    assert "★" not in line["drive", "Copy (reference)"]
    rows = list(csv.DictReader(open(results / "cost.csv")))
    adaptive = next(r for r in rows if r["row"] == "adaptive_drive")
    assert float(adaptive["warp_skipped_conv3"]) == 0.5 and float(adaptive["train_step_ms"]) == 280


def test_paper_numbers_match_the_paper_tables():
    def paper(stem, metric):
        return [r.paper.get(metric) for r in sweep.load_study(REPO / "sweeps" / f"{stem}.yaml").rows if r.paper]

    assert paper("ablation", "l1") == [.0769, .0611, .0584, .0949, .0654, .0602, .0603, .1109, .0618]
    assert paper("ablation", "ssim_paper") == [.9099, .9228, .9256, .8971, .9166, .9231, .9236, .8862, .9212]
    assert paper("comparison_objects", "l1") == [.1043, .0810, .0769, .0584, .0491, .0444, .0396, .0286]
    assert paper("comparison_objects", "ssim_paper") == [.8851, .8993, .9099, .9256, .9226, .9282, .9395, .9493]
    assert paper("comparison_drive", "l1") == [.3119, .1868, .2354, .1985]
    assert paper("comparison_drive", "ssim_paper") == [.6191, .6582, .6461, .7043]
    assert paper("depth", "depth_sc_inv") == [.0583, .0523]
    assert paper("depth", "depth_l1_rel") == [.0360, .0305]


@pytest.mark.parametrize("bad, message", [
    ({"rows": [{"name": "a", "overrides": ["seed=0,1"]}]}, "is a sweep"),
    ({"rows": [{"name": "a"}, {"name": "a"}]}, "used twice"),
    ({"rows": [{"name": "a", "reference": "copy_source"}]}, "names 'data'"),
    ({"rows": [{"name": "a", "colour": 1}]}, "unknown key"),
    ({"rows": [{"name": "a b"}]}, "names a directory"),
    ({"rows": [{"name": "a", "paper": {"acc": 1}}]}, "unknown metric"),
    ({"rows": [{"name": "a", "overrides": ["seed=3"]}]}, "set by the study"),
    ({"overrides": ["data.size=128"], "rows": [{"name": "a"}]}, "set by the study"),
    ({"table": "fancy", "rows": [{"name": "a"}]}, "table must be one of"),
    ({"rows": [{"name": "a", "oracle": "yes"}]}, "oracle must be true or false"),
    ({"rows": [{"name": "a", "reference": "copy_source", "data": "chairs", "seeds": [0]}]},
     r"s.yaml:\d+: rows\[0\]: a reference row has no 'seeds'"),
    ({"rows": [{"name": "a", "seeds": [1, 1]}]}, r"rows\[0\]: seeds must be distinct"),
    ({"rows": [{"name": "a", "seeds": "two"}]}, "seeds must be"),
    ({"against": ["c"], "rows": [{"name": "a"}, {"name": "c", "reference": "copy_source", "data": "chairs"}]},
     r"s.yaml:\d+: against\[0\]: 'c' is not a trained row of the study; trained rows: a"),
    # a variant ('stands_for') names another trained row with paper numbers, no variant itself, and has none of its own
    ({"rows": [{"name": "a", "paper": {"l1": 0.1}}, {"name": "v", "stands_for": "v"}]},
     r"s.yaml:\d+: rows\[1\].stands_for: row 'v' cannot stand for itself"),
    ({"rows": [{"name": "a", "paper": {"l1": 0.1}}, {"name": "v", "stands_for": "x"}]},
     r"s.yaml:\d+: rows\[1\].stands_for: 'x' is not a row of the study"),
    ({"rows": [{"name": "a", "paper": {"l1": 0.1}}, {"name": "b"}, {"name": "v", "stands_for": "b"}]},
     r"s.yaml:\d+: rows\[2\].stands_for: 'b' is not a trained row with paper numbers; a variant stands for one "
     r"of: a$"),
    ({"rows": [{"name": "a", "paper": {"l1": 0.1}}, {"name": "c", "reference": "copy_source", "data": "chairs",
                                                     "paper": {"l1": 0.2}}, {"name": "v", "stands_for": "c"}]},
     r"rows\[2\].stands_for: 'c' is not a trained row with paper numbers"),
    ({"rows": [{"name": "a", "paper": {"l1": 0.1}}, {"name": "v", "stands_for": "a"},
               {"name": "w", "stands_for": "v"}]},
     r"s.yaml:\d+: rows\[2\].stands_for: 'v' stands for 'a' itself; name that row \(no chains\)"),
    ({"rows": [{"name": "a", "paper": {"l1": 0.1}}, {"name": "v", "stands_for": "a", "paper": {"l1": 0.2}}]},
     r"rows\[1\].stands_for: row 'v' has paper numbers of its own"),
    ({"rows": [{"name": "a", "paper": {"l1": 0.1}}, {"name": "v", "stands_for": ["a"]}]}, r"rows\[1\].stands_for"),
])
def test_malformed_study_is_one_clear_error(tmp_path, bad, message):
    path = tmp_path / "s.yaml"
    path.write_text(json.dumps({"size": 64, "steps": 2, **bad}))
    with pytest.raises(sweep.UserError, match=message):
        sweep.load_study(path)


def test_a_row_runs_its_own_seeds_unless_the_command_line_gives_them(tmp_path):
    rows = [{"name": "full", "experiment": "nvs_chairs"},
            {"name": "noskip", "experiment": "nvs_chairs", "overrides": ["model/skips=none"], "seeds": [0]},
            {"name": "two", "experiment": "nvs_chairs", "overrides": ["model/skips=wo_conv0"], "seeds": 2},
            {"name": "copy", "reference": "copy_source", "data": "chairs"}]
    path = tmp_path / "s.yaml"
    path.write_text(json.dumps({"size": 64, "steps": 2, "seeds": [0, 1, 2], "rows": rows}))
    planned = {}
    for job in sweep.plan(sweep.load_study(path), tmp_path / "runs"):
        planned.setdefault(job.row.name, []).append(job.seed)
    assert planned == {"full": [0, 1, 2], "noskip": [0], "two": [0, 1], "copy": [0]}
    # Each (row, seed) is still its own directory: the row's seed list changes which jobs run, not their keys.
    assert len({j.key for j in sweep.plan(sweep.load_study(path), tmp_path / "runs")}) == 7
    from nvs.sweep.tables import _seeds_cell
    assert _seeds_cell(sweep.load_study(path)) == "0, 1, 2; noskip: 0; two: 0, 1 (reference rows: 0)"
    everywhere = sweep.load_study(path, seeds=[0, 1])
    assert {r.name: sweep.row_seeds(everywhere, r) for r in everywhere.rows} == {
        "full": (0, 1), "noskip": (0, 1), "two": (0, 1), "copy": (0,)}
    assert _seeds_cell(everywhere) == "0, 1 (reference rows: 0)"


# -- a fabricated multirun directory --------------------------------------------------------------------------------
STUDY = {
    "name": "fab", "title": "fabricated", "paper_source": "Table 9", "seeds": [0, 1], "size": 64, "steps": 10,
    "overrides": ["trainer.enable_progress_bar=false"], "group_by": "data",
    "rows": [
        {"name": "full", "label": "Full model", "experiment": "nvs_chairs",
         "paper": {"l1": 0.0584, "ssim_paper": 0.9256}},
        {"name": "chen", "label": "Chen", "experiment": "chen_chairs"},
        {"name": "noskip", "experiment": "nvs_chairs", "overrides": ["model/skips=none"]},
        {"name": "copy", "reference": "copy_source", "data": "chairs"},
    ],
}


def _study(tmp_path, **changes) -> sweep.Study:
    path = tmp_path / "fab.yaml"
    path.write_text(json.dumps({**STUDY, **changes}))
    return sweep.load_study(path)


def _fake_result(job: sweep.Job, root: Path, l1: float, record: bool = True) -> None:
    if record:
        sweep.prepare_job_dir(job, root)
    else:
        job.dir.mkdir(parents=True, exist_ok=True)
    (job.dir / ".hydra").mkdir(exist_ok=True)
    (job.dir / ".hydra" / "overrides.yaml").write_text(
        "".join(f"- {o}\n" for o in [*job.overrides, f"seed={job.seed}"]))
    test = {"l1": l1, "ssim_paper": 0.9, "ssim": 0.8, "psnr": 20.0, "lpips": 0.1, "n_pairs": 4}
    if job.row.name == "full":
        test.update(depth_l1=0.05, depth_l1_rel=0.02, depth_l1_inv=0.01, depth_sc_inv=0.03)
    (job.dir / "metrics.json").write_text(json.dumps({
        "model": "nvs", "data": "chairs", "image_size": 64, "seed": job.seed, "steps": 10, "train_wall_s": 100.0 + l1,
        "train_samples_per_s": 1.0, "params": 1234567, "device": "cpu: Fake CPU (2 threads)", "precision": "32-true",
        "git_sha": "abc123", "eval_ms_per_image": 5.0, "eval_forward_ms_per_image": 2.0 + l1, "test": test}))


def _fake_failure(job: sweep.Job, root: Path, line: str) -> None:
    sweep.prepare_job_dir(job, root)
    (job.dir / sweep.FAILED).write_text(line + "\n")


@pytest.fixture
def fabricated(tmp_path):
    """full: 2 seeds done; chen: s0 done, s1 failed; noskip: s0 done, s1 never ran; copy: done."""
    study = _study(tmp_path)
    root = tmp_path / "runs" / study.scale
    jobs = {(j.row.name, j.seed): j for j in sweep.plan(study, root)}
    _fake_result(jobs["full", 0], root, 0.10)
    _fake_result(jobs["full", 1], root, 0.12)
    _fake_result(jobs["chen", 0], root, 0.20)
    _fake_failure(jobs["chen", 1], root, "NonFiniteLossError: non-finite training loss at step 7 (recon)")
    _fake_result(jobs["noskip", 0], root, 0.30)
    _fake_result(jobs["copy", 0], root, 0.40)
    return study, root


def test_collection_of_a_fabricated_multirun(fabricated, tmp_path):
    study, root = fabricated
    results = tmp_path / "results"
    rc = sweep.run([str(study.path), "--collect-only", str(root), "--results", str(results)])
    assert rc == 1  # not every job finished
    with open(results / "fab.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 7  # one line per job, the failed and the missing one included
    by = {(r["row"], r["seed"]): r for r in rows}
    assert by["chen", "1"]["status"] == "failed" and "step 7" in by["chen", "1"]["error"]
    assert by["noskip", "1"]["status"] == "missing"
    assert float(by["full", "1"]["l1"]) == pytest.approx(0.12)
    assert by["full", "0"]["overrides"].startswith("experiment=nvs_chairs") and by["full", "0"]["paper_l1"] == "0.0584"
    assert float(by["full", "0"]["depth_sc_inv"]) == pytest.approx(0.03) and by["chen", "0"]["depth_sc_inv"] == ""

    md = (results / "fab.md").read_text()
    for field in ("| command | `python -m nvs.sweep", "| git SHA |", "| date |", "| device | cpu: Fake CPU",
                  "| image size | 64² |", "| steps | 10 |", "| seeds | 0, 1"):
        assert field in md, field
    line = {ln.split("|")[1].strip(): ln for ln in md.splitlines() if ln.startswith("| ") and "|" in ln[2:]}
    # mean ± sample std of 0.10 and 0.12; the paper's number beside ours, labelled as such.
    assert "| 2/2 | 0.1100 ± 0.0141 |" in line["Full model"] and "| 0.0584 | 0.9256 |" in line["Full model"]
    assert "Paper L1" in md and "real datasets at 256²" in md and "Table 9" in md
    assert "**FAILED** s1 failed: NonFiniteLossError: non-finite training loss at step 7" in line["Chen"]
    assert "| 1/2 | 0.2000 |" in line["Chen"]
    assert "s1 missing" in line["noskip"]
    assert "| 1/1 | 0.4000 |" in line["copy (reference)"]
    assert "depth sc-inv" in md  # a depth metric some row has gets its column


def test_mean_std_is_the_sample_std():
    assert sweep.mean_std([1.0, 2.0, 3.0]) == (2.0, 1.0)
    assert sweep.mean_std([0.5]) == (0.5, None)
    assert sweep.mean_std([None]) == (None, None)


# -- planning: what a (re-)run launches -----------------------------------------------------------------------------
def test_planning_skips_done_and_relaunches_the_rest(fabricated):
    study, root = fabricated
    jobs = sweep.plan(study, root)
    status = {(j.row.name, j.seed): j.status for j in jobs}
    assert status == {("full", 0): "done", ("full", 1): "done", ("chen", 0): "done", ("chen", 1): "failed",
                      ("noskip", 0): "done", ("noskip", 1): "missing", ("copy", 0): "done"}
    launch = {(j.row.name, j.seed) for j in sweep.to_launch(jobs)}
    assert launch == {("chen", 1), ("noskip", 1)}
    assert {(j.row.name, j.seed) for j in sweep.to_launch(jobs, retry_failed=False)} == {("noskip", 1)}
    assert len(sweep.to_launch(jobs, force=True)) == len(jobs)


def test_a_changed_config_is_stale_and_moved_aside_before_relaunch(fabricated, tmp_path):
    study, root = fabricated
    changed = _study(tmp_path, steps=10, overrides=["trainer.enable_progress_bar=false", "optim.lr=0.001"])
    jobs = {(j.row.name, j.seed): j for j in sweep.plan(changed, root)}
    assert jobs["full", 0].status == "stale" and jobs["copy", 0].status == "done"  # reference rows ignore optim
    assert jobs["full", 0] in sweep.to_launch(list(jobs.values()))
    from nvs.sweep.collect import collect

    record = next(r for r in collect([jobs["full", 0]]))
    assert record["status"] == "stale" and "optim.lr" in record["error"] and record["l1"] is None
    sweep.prepare_job_dir(jobs["full", 0], root)
    assert not (jobs["full", 0].dir / "metrics.json").exists()  # the old result can no longer be mistaken for new
    assert list((root / ".stale").glob("full_s0.*/metrics.json"))
    assert sweep.job_status(jobs["full", 0].dir, jobs["full", 0].key)[0] == "missing"


def test_placement_only_overrides_do_not_change_the_key(tmp_path):
    study = _study(tmp_path)
    a = sweep.plan(study, tmp_path / "a")
    b = sweep.plan(study, tmp_path / "b", extra=("trainer.enable_progress_bar=true", "hydra/launcher=joblib"))
    c = sweep.plan(study, tmp_path / "c", extra=("trainer.max_epochs=3",))
    assert [j.key for j in a] == [j.key for j in b]
    assert all(x.key != y.key for x, y in zip(a, c) if not x.row.reference)
    assert len({j.key for j in a}) == len(a)  # every (row, seed) is its own job


def test_an_interrupted_job_is_incomplete_and_relaunched(fabricated):
    study, root = fabricated
    job = next(j for j in sweep.plan(study, root) if (j.row.name, j.seed) == ("noskip", 1))
    sweep.prepare_job_dir(job, root)
    (job.dir / "checkpoints").mkdir()
    (job.dir / "checkpoints" / "last.ckpt").write_bytes(b"x")
    assert sweep.job_status(job.dir, job.key) == ("incomplete", "")
    sweep.prepare_job_dir(job, root)  # relaunching keeps the checkpoint that ckpt_path=auto resumes from
    assert (job.dir / "checkpoints" / "last.ckpt").is_file()


def test_last_error_line():
    log = "Seed set to 0\nTraceback (most recent call last):\n  File x\nValueError: bad value\nsome trailing note\n"
    assert sweep.last_error_line(log) == "ValueError: bad value"
    assert sweep.last_error_line("warn\nerror: data root missing\n") == "error: data root missing"
    assert sweep.last_error_line("just text\n") == "just text"
    assert sweep.last_error_line("just text\n", fallback=False) == ""
    assert sweep.last_error_line("x\nnvs.module.lightning_module.NonFiniteLossError: nan\n") == "nvs.module.lightning_module.NonFiniteLossError: nan"
    assert sweep.last_error_line("UserWarning: careful\n", fallback=False) == ""


def test_parallel_launch_never_oversubscribes_the_cores(monkeypatch):
    from nvs.sweep import launch as launching

    monkeypatch.setattr(launching, "available_cores", lambda: 8)
    launch = sweep.Launch.local(jobs=4)
    assert launch.threads == 2 and "hydra/launcher=joblib" in launch.hydra_overrides
    assert "hydra.launcher.n_jobs=4" in launch.hydra_overrides
    assert sweep.Launch.local(jobs=1).threads == 8 and sweep.Launch.local(jobs=1).hydra_overrides == ()
    with pytest.raises(sweep.UserError, match="cores"):
        sweep.Launch.local(jobs=4, threads=4)


def test_multirun_command_puts_each_job_in_its_own_directory(tmp_path):
    study = _study(tmp_path)
    row = study.rows[0]
    cmd = sweep.multirun_command(study, row, [0, 1], tmp_path, sweep.Launch(jobs=1, threads=2))
    assert cmd[1:4] == ["-m", "nvs.train", "-m"] and "seed=0,1" in cmd
    assert f"hydra.sweep.dir={tmp_path.resolve()}" in cmd and "hydra.sweep.subdir=full_s${seed}" in cmd
    ref = sweep.multirun_command(study, study.rows[3], [0], tmp_path, sweep.Launch())
    assert ref[2] == "nvs.evaluate" and "model=copy_source" in ref and not any("max_steps" in c for c in ref)


# -- Pareto and figures ----------------------------------------------------------------------------------------------
def test_pareto_front_by_hand():
    cost = [1.0, 2.0, 3.0, 2.5, 1.0]
    err = [0.5, 0.3, 0.1, 0.4, 0.6]
    # (2.5, 0.4) is beaten by (2.0, 0.3); (1.0, 0.6) by (1.0, 0.5).
    assert pareto_lib.pareto_front(cost, err) == [True, True, True, False, False]


def test_pareto_report_from_sweep_csv(fabricated, tmp_path):
    study, root = fabricated
    results = tmp_path / "results"
    sweep.run([str(study.path), "--collect-only", str(root), "--results", str(results)])
    md, png = pareto.run([str(results / "fab.csv"), "--results", str(results)])
    text = md.read_text()
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "## chairs" in text and "copy" not in text.split("## chairs")[1]  # reference rows are not methods
    full = next(ln for ln in text.splitlines() if ln.startswith("| Full model"))
    assert "| 0.1100 |" in full and full.count("★") == 4  # lowest L1 at every cost in this fabricated set


def test_pareto_lists_a_row_without_paper_numbers_under_its_own_label(tmp_path):
    """The norms-fixed network (a variant: 'stands_for', no paper numbers) is its own labelled point beside the
    paper's row, once its jobs exist; before that it is not in the report."""
    rows = [*STUDY["rows"][:1], {"name": "fixed", "label": "Full, norms fixed", "experiment": "nvs_chairs",
                                 "overrides": ["fidelity.conv0_norm=none"], "stands_for": "full"}]
    study = _study(tmp_path, rows=rows)
    root = tmp_path / "runs" / study.scale
    results = tmp_path / "results"
    jobs = sweep.plan(study, root)
    for j in jobs:
        if j.row.name == "full":
            _fake_result(j, root, 0.12)
    sweep.run([str(study.path), "--collect-only", str(root), "--results", str(results)])
    assert "norms fixed" not in pareto.run([str(results / "fab.csv"), "--results", str(results)])[0].read_text()
    for j in jobs:
        if j.row.name == "fixed":
            _fake_result(j, root, 0.08)
    sweep.run([str(study.path), "--collect-only", str(root), "--results", str(results)])
    text = pareto.run([str(results / "fab.csv"), "--results", str(results)])[0].read_text()
    table = [ln for ln in text.splitlines() if ln.startswith("| ") and "---" not in ln][1:]
    assert [ln.split(" | ")[0] for ln in table] == ["| Full, norms fixed", "| Full model"]  # by L1
    assert table[0].startswith("| Full, norms fixed | fab | 2 | 0.0800 |")


def test_pareto_never_puts_two_scales_on_one_front(fabricated, tmp_path):
    study, root = fabricated
    results = tmp_path / "results"
    sweep.run([str(study.path), "--collect-only", str(root), "--results", str(results)])
    rows = list(csv.DictReader(open(results / "fab.csv")))
    other = tmp_path / "other.csv"
    with open(other, "w", newline="") as f:  # the same jobs as if trained 10x longer elsewhere
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            long_dir = str(Path(r["run_dir"]).parent.with_name("64px_100steps") / Path(r["run_dir"]).name)
            w.writerow(r | {"steps": "100", "run_dir": long_dir, "train_wall_s": "1.0"})
    agg = pareto_lib.load_rows([results / "fab.csv", other])
    assert set(agg["data"]) == {"chairs @ 64²/10 steps", "chairs @ 64²/100 steps"}
    # each scale has its own front: the fast long run does not knock the short runs off theirs
    short = agg[agg["data"] == "chairs @ 64²/10 steps"]
    assert short["front_l1_train_wall_s"].any()
    # a job the stopping rule ended early stays in its budget's series
    with open(other, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]) + ["stop"])
        w.writeheader()
        for r in rows:
            w.writerow(r | {"steps": "7", "stop": "converged", "run_dir": r["run_dir"] + "_ruled"})
    assert set(pareto_lib.load_rows([other])["data"]) == {"chairs"}  # one scale: no suffix
    mixed = pareto_lib.load_rows([results / "fab.csv", other])
    assert set(mixed["data"]) == {"chairs @ 64²/10 steps", "chairs @ 64²/10 steps at most"}


def test_pareto_reads_the_paper_studies_by_default(tmp_path):
    header = ",".join(sweep.CSV_COLUMNS) + "\n"
    for name in ("ablation", "skip", "fidelity", "comparison_drive"):
        (tmp_path / f"{name}.csv").write_text(header)
    assert [p.name for p in pareto_lib.default_csvs(tmp_path)] == ["ablation.csv", "comparison_drive.csv", "skip.csv"]


def test_unproject_inverts_the_projection():
    from nvs.report.figures import unproject

    K = torch.tensor([[100.0, 0, 31.5], [0, 120.0, 31.5], [0, 0, 1]], dtype=torch.float64)
    depth = torch.rand(64, 64, dtype=torch.float64) + 1
    pts = unproject(depth, K)
    proj = pts @ K.T
    uv = proj[:, :2] / proj[:, 2:]
    v, u = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
    assert torch.allclose(uv, torch.stack([u, v], -1).reshape(-1, 2).double(), atol=1e-9)
    assert torch.allclose(pts[:, 2], depth.reshape(-1))
    assert torch.allclose(pts[0], torch.tensor([-31.5 / 100, -31.5 / 120, 1.0], dtype=torch.float64) * depth[0, 0])


# -- a tiny real sweep end to end ------------------------------------------------------------------------------------
def _sweep(*args):
    return subprocess.run([sys.executable, "-m", "nvs.sweep", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=900)


def _tiny_study(tmp_path, objects_root, steps: int, overrides: list[str], references: list[dict]):
    """tiny.yaml: one trained row (the full model's network, recon only) on the fixture chairs plus ``references``."""
    study = tmp_path / "tiny.yaml"
    study.write_text(json.dumps({
        "name": "tiny", "seeds": [0], "size": 64, "steps": steps,
        "overrides": [f"data.root={objects_root}", "trainer.val_check_interval=2", "data.loader.batch_size=2",
                      "trainer.limit_val_batches=1", "trainer.enable_progress_bar=false", *overrides],
        "rows": [{"name": "recon_only", "experiment": "nvs_chairs", "overrides": ["loss=[recon]"]}, *references]}))
    return study


@pytest.mark.slow
def test_tiny_sweep_end_to_end_then_rerun_launches_nothing(objects_root, tmp_path):
    study = _tiny_study(tmp_path, objects_root, 2, [], [{"name": "copy", "reference": "copy_source", "data": "chairs"}])
    runs, results = tmp_path / "runs", tmp_path / "results"
    args = [str(study), "--runs", str(runs), "--results", str(results)]
    res = _sweep(*args)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "launching 2" in res.stderr
    job = runs / "64px_2steps" / "recon_only_s0"
    metrics = json.loads((job / "metrics.json").read_text())
    assert metrics["steps"] == 2 and metrics["test"]["n_pairs"] == 4
    assert (job / sweep.JOB_RECORD).is_file() and (job / ".hydra" / "overrides.yaml").is_file()
    assert (job / sweep.STDERR).is_file()  # the job's own stderr, kept by the Hydra callback
    assert "(2 threads)" in metrics["device"] or "threads)" in metrics["device"]
    md = (results / "tiny.md").read_text()
    assert "| recon_only | 1/1 |" in md and "| copy (reference) | 1/1 |" in md
    stamps = {p: p.stat().st_mtime_ns for p in runs.rglob("metrics.json")}
    assert len(stamps) == 2

    again = _sweep(*args, "--figures")
    assert again.returncode == 0, again.stderr[-3000:]
    assert "2 done; launching 0" in again.stderr and "[sweep] $" not in again.stderr  # no multirun started
    assert {p: p.stat().st_mtime_ns for p in runs.rglob("metrics.json")} == stamps
    for name in ("tiny_qualitative_chairs.png", "tiny_depth_points.png", "tiny_curves.png"):
        assert (results / name).read_bytes()[:4] == b"\x89PNG", name


def failing_study(tmp_path: Path) -> Path:
    """A two-seed study of one row whose data root does not exist: every job fails with a UserError."""
    study = tmp_path / "bad.yaml"
    study.write_text(json.dumps({
        "name": "bad", "seeds": [0, 1], "size": 64, "steps": 2,
        "overrides": ["trainer.val_check_interval=2", "data.loader.batch_size=2", "trainer.enable_progress_bar=false",
                      "loss=[recon]"],
        "rows": [{"name": "nodata", "experiment": "nvs_chairs", "overrides": [f"data.root={tmp_path}/none"]}]}))
    return study


@pytest.mark.slow
def test_failed_jobs_are_recorded_with_their_error_line(objects_root, tmp_path):
    # sys.exit inside the job (a UserError) ends the multirun process; the second seed must still get its turn.
    study = failing_study(tmp_path)
    res = _sweep(str(study), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "results"))
    assert res.returncode == 1
    for seed in (0, 1):
        failed = (tmp_path / "runs" / "64px_2steps" / f"nodata_s{seed}" / sweep.FAILED).read_text()
        assert failed.startswith("error:") and "does not exist" in failed
    md = (tmp_path / "results" / "bad.md").read_text()
    assert "**FAILED** s0, s1 failed: error:" in md


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
    # the runner imports nvs.sweep and starts its child: seconds on a loaded 2-core machine (10 s ran out there)
    deadline = time.monotonic() + 120
    while not (pid_file.exists() and pid_file.read_text()) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert pid_file.exists() and pid_file.read_text(), f"the job never started (runner exit code {proc.poll()})"
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
