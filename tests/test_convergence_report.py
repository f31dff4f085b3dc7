"""The convergence layout: per-job stop, best validation L1 and the first step near it; the curves figure."""

from __future__ import annotations

import json

import pytest

from nvs.sweep.convergence_report import convergence_tables, curves_png, first_step_near_best, history


def _job(tmp_path, name, values, data="chairs", kind="train", stop="converged"):
    d = tmp_path / name
    d.mkdir()
    hist = [{"step": 100 * (i + 1), "value": v, "wall_s": 60.0 * (i + 1)} for i, v in enumerate(values)]
    (d / "convergence.json").write_text(json.dumps({"outcome": stop, "history": hist}))
    return {"row": name, "label": name, "kind": kind, "status": "done", "dir": d, "data": data, "seed": 0,
            "stop": stop, "steps": 100 * len(values), "train_wall_s": 60.0 * len(values)}


def test_first_step_near_best_is_the_first_validation_within_one_percent():
    hist = [{"step": s, "value": v} for s, v in [(100, 0.30), (200, 0.2015), (300, 0.2001), (400, 0.2000)]]
    assert first_step_near_best(hist) == 200  # 0.2015 <= 0.2000 * 1.01
    assert first_step_near_best(hist, near=0.0) == 400
    assert first_step_near_best([]) is None


def test_history_drops_non_finite_values_and_sorts_by_step(tmp_path):
    d = tmp_path / "j"
    d.mkdir()
    (d / "convergence.json").write_text('{"history": [{"step": 200, "value": 0.5, "wall_s": 2},'
                                        ' {"step": 100, "value": NaN, "wall_s": 1}]}')
    assert history(d) == [{"step": 200, "value": 0.5, "wall_s": 2}]
    assert history(tmp_path / "missing") == []


def test_tables_give_one_line_per_trained_job_grouped_by_dataset(tmp_path):
    records = [_job(tmp_path, "nvs_chairs", [0.3, 0.25, 0.2, 0.199]),
               _job(tmp_path, "chen_cars", [0.2, 0.1], data="cars", stop="max_steps"),
               {"row": "copy", "label": "copy", "kind": "reference", "status": "done", "dir": tmp_path, "data": "chairs",
                "seed": 0}]
    text = "\n".join(convergence_tables(records, budget=400))
    assert "within a budget of 400 steps" in text
    assert "| nvs_chairs | 0 | converged | 400 | 4.0 | 0.1990 | 300 |" in text
    assert "| chen_cars | 0 | max_steps | 200 | 2.0 | 0.1000 | 200 |" in text
    assert text.index("### Convergence: chairs") < text.index("### Convergence: cars") and "| copy |" not in text
    png = curves_png(records)
    assert png is not None and png[:8] == b"\x89PNG\r\n\x1a\n"


def test_nothing_finished_is_said_and_draws_nothing(tmp_path):
    assert "No trained job has finished yet." in convergence_tables([], budget=10)
    assert curves_png([]) is None


@pytest.mark.parametrize("table", ["convergence"])
def test_the_study_schema_accepts_the_convergence_layout(tmp_path, table):
    from nvs.sweep.study import load_study

    path = tmp_path / "c.yaml"
    path.write_text(json.dumps({"name": "c", "size": 64, "steps": 10, "table": table,
                                "rows": [{"name": "copy", "reference": "copy_source", "data": "chairs"}]}))
    assert load_study(path).table == table
