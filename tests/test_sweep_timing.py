"""The timing pass of a cost study (``python -m nvs.sweep <study> --time``): every row timed in one process, the
file it writes, and the table columns and pick that read it (nvs.sweep.timing, nvs.sweep.time_rows)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from nvs import sweep
from nvs.core.errors import UserError
from nvs.sweep import timing

ROWS = [
    {"name": "full", "label": "Full", "experiment": "nvs_chairs"},
    {"name": "skips_full", "label": "Full, per-level skips", "evaluates": "full",
     "overrides": ["skips_threshold=calibrate"]},
    {"name": "route_full", "label": "Full, routed", "evaluates": "full", "overrides": ["route=fit"]},
    {"name": "lean", "label": "Lean", "experiment": "nvs_chairs",
     "overrides": ["model/depth=plane", "model/skips=wo_conv0"]},
    {"name": "copy", "label": "Copy source", "reference": "copy_source", "data": "chairs"},
]


def _study(tmp_path: Path, root: Path | None = None) -> Path:
    data = [f"data.root={root}"] if root else []
    study = {"name": "tiny_cost", "title": "t", "seeds": [0], "size": 64, "steps": 2, "table": "cost",
             "group_by": "data", "metrics": ["l1", "ssim"], "rows": ROWS,
             "overrides": [*data, "data.loader.eval_batch_size=2", "trainer.precision=32", "channels_last=false"]}
    path = tmp_path / "tiny_cost.yaml"
    path.write_text(json.dumps(study))
    return path


def _summary(name: str, **means) -> dict:
    return {"row": name, **{k: (v, None) for k, v in means.items()}}


# -- reading the file ------------------------------------------------------------------------------------------------
def test_a_bad_timing_file_is_one_error_naming_the_file_and_the_key(tmp_path):
    study = sweep.load_study(_study(tmp_path))
    path = timing.timing_path(tmp_path / "results", study)
    assert timing.read_timing(path, study) is None  # no pass yet: the table has no timed columns
    path.parent.mkdir(parents=True)
    path.write_text("{not json")
    with pytest.raises(UserError, match="tiny_cost.json: not a readable timing file"):
        timing.read_timing(path, study)
    good = {k: None for k in timing.HEADER} | {"version": timing.VERSION, "study": "tiny_cost",
                                                "scale": study.scale, "sizes": [32], "rows": {}}
    path.write_text(json.dumps({k: v for k, v in good.items() if k != "device"}))
    with pytest.raises(UserError, match="key 'device' is missing"):
        timing.read_timing(path, study)
    path.write_text(json.dumps(good | {"study": "other"}))
    with pytest.raises(UserError, match="'study' is 'other', this study's is 'tiny_cost'"):
        timing.read_timing(path, study)
    path.write_text(json.dumps(good))
    assert timing.read_timing(path, study)["sizes"] == [32]


def test_evaluation_rows_mix_their_parts_at_the_finished_jobs_shares(tmp_path):
    study = sweep.load_study(_study(tmp_path))
    routes = {"routes": {"64": {"copy": 1.0, "warp": 3.0, "full": 10.0}}}
    row = _summary("route_full", route_share_copy=0.5, route_share_warp=0.25, route_share_full=0.25)
    assert timing.mixed_ms(routes, row, 64) == pytest.approx(0.5 + 0.75 + 2.5)
    assert timing.mixed_ms(routes, _summary("route_full"), 64) is None  # no finished job: no shares
    assert timing.mixed_ms(routes, row, 256) is None  # not timed at that size
    levels = {"levels": {"64": {"none": 10.0, "conv2": 8.0, "conv4": 9.0}}}
    row = _summary("skips_full", warp_skipped_conv2=0.5, warp_skipped_conv4=1.0)
    assert timing.mixed_ms(levels, row, 64) == pytest.approx(10 - 0.5 * 2 - 1.0 * 1)
    # an entry is shown only while the row is defined as it was when it was timed
    entry = {"identity": timing.identity(study, study.rows[3]), "network": {"32": 4.0}}
    file = {"sizes": [32], "rows": {"lean": entry, "full": {"identity": ["experiment=nvs_cars"],
                                                            "network": {"32": 5.0}}}}
    rows = [_summary("full"), _summary("lean")]
    assert timing.attach(study, rows, file) == [32]
    assert rows[1][timing.timed_key(32)] == (4.0, None) and rows[0][timing.timed_key(32)] == (None, None)


def test_the_pick_reads_the_timed_cost_only_where_every_candidate_has_it():
    key = timing.timed_key(64)

    def row(name, own, timed, kind="train", oracle=False):
        return {"row": name, "kind": kind, "oracle": oracle, "l1": (0.1, None), "eval_forward_ms_per_image":
                (own, None), key: (timed, None)}

    rows = [row("a", 5.0, 10.0), row("b", 9.0, 5.0), row("o", 1.0, None, oracle=True), row("e", 1.0, None, "evaluate")]
    assert timing.pick_cost(rows, [64, 256], 64) == key
    assert timing.timed_cells(rows[1], rows, [64]) == ["5.0", "2.00×"]
    assert timing.pick_cost(rows, [256], 64) == "eval_forward_ms_per_image"  # not timed at the study's size
    rows[1][key] = (None, None)
    assert timing.pick_cost(rows, [64], 64) == "eval_forward_ms_per_image"
    assert timing.timed_cells(rows[1], rows, [64]) == ["—", "—"]


def test_time_refuses_a_study_without_a_cost_table(tmp_path):
    with pytest.raises(UserError, match="--time: .*has no cost table"):
        sweep.run([str(Path(__file__).resolve().parents[1] / "sweeps" / "ablation.yaml"), "--collect-only",
                   str(tmp_path), "--time", "--results", str(tmp_path / "results")])


# -- the pass -------------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_the_timing_pass_times_every_row_and_the_cost_table_shows_it(objects_root, tmp_path, monkeypatch):
    from nvs.sweep import time_rows

    monkeypatch.setattr(time_rows, "SIZES", (96,))  # 256² in fp32 would take minutes here
    path = _study(tmp_path, objects_root)
    (tmp_path / "runs").mkdir()
    results = tmp_path / "results"
    sweep.run([str(path), "--collect-only", str(tmp_path / "runs"), "--time", "--results", str(results)])
    data = json.loads((results / "timing" / "tiny_cost.json").read_text())
    assert data["sizes"] == [64, 96] and data["precision"] == "32" and data["channels_last"] is False
    assert data["batch"] == 2 and data["repeats"] >= 1 and data["device"].startswith("cpu")
    assert sorted(data["rows"]) == ["full", "lean", "route_full", "skips_full"]  # reference rows are not timed
    rows = data["rows"]
    assert set(rows["route_full"]["routes"]["96"]) == {"copy", "warp", "full"}
    assert set(rows["skips_full"]["levels"]["64"]) == {"none", "conv0", "conv2", "conv3", "conv4"}
    assert set(rows["lean"]) == {"identity", "network"}  # a trained row: its network alone
    for name in ("full", "lean"):
        assert all(v > 0 for v in rows[name]["network"].values())
    assert rows["route_full"]["network"] == {s: t["full"] for s, t in rows["route_full"]["routes"].items()}
    assert rows["skips_full"]["network"] == {s: t["none"] for s, t in rows["skips_full"]["levels"].items()}
    md = (results / "tiny_cost.md").read_text()
    assert "| timing | cpu" in md and "Timed 64² (ms/img)" in md and "× timed 96²" in md
    full_line = next(line for line in md.splitlines() if line.startswith("| Full |"))
    assert f"{rows['full']['network']['64']:.1f}" in full_line
    # --rows times only those rows and keeps the others' entries (same device, torch, precision and layout)
    sweep.run([str(path), "--collect-only", str(tmp_path / "runs"), "--time", "--rows", "lean",
               "--results", str(results)])
    again = json.loads((results / "timing" / "tiny_cost.json").read_text())["rows"]
    assert again["full"] == rows["full"] and sorted(again) == sorted(rows)
    assert again["lean"]["identity"] == rows["lean"]["identity"]
    assert all(v > 0 for v in again["lean"]["network"].values())
