"""The benchmark runs end to end at a tiny size and reports speedups over fp32 NCHW eager."""

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_bench_writes_report_with_speedups(tmp_path):
    cmd = [sys.executable, "-m", "nvs.bench", "image_size=64", "only=[wo_skips]", "modes=[fp32,bf16_cl]",
           "repeats=1", "warmup=0", "train_batch=2", "throughput_batch=2", "measure_peak=false",
           f"out_dir={tmp_path}", f"paths.log_dir={tmp_path}/logs"]
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    report = json.loads(next(tmp_path.glob("*.json")).read_text())
    rows = report["models"]["wo_skips"]
    assert rows["fp32"]["train_step_speedup"] == 1.0
    assert rows["bf16_cl"]["train_step_speedup"] > 0 and rows["bf16_cl"]["eval_speedup"] > 0
    assert rows["fp32"]["train_gflop_per_sample"] > 0 and rows["fp32"]["params"] > 0
    md = next(tmp_path.glob("*.md")).read_text()
    assert "| wo_skips | bf16_cl |" in md and "git SHA" in md


def test_accuracy_section_compares_fp32_and_fast_rows(tmp_path):
    import pandas as pd

    from nvs.bench import accuracy_section

    path = tmp_path / "precision.csv"
    assert "run `python -m nvs.sweep sweeps/precision.yaml`" in "\n".join(accuracy_section(path))
    rows = [{"row": "precision_fp32_chairs", "status": "done", "l1": 0.200, "ssim_paper": 0.7, "train_wall_s": 300,
             "steps": 500},
            {"row": "precision_fast_chairs", "status": "done", "l1": 0.203, "ssim_paper": 0.7, "train_wall_s": 100,
             "steps": 500},
            {"row": "copy_source_chairs", "status": "done", "l1": 0.21, "ssim_paper": 0.7, "train_wall_s": None,
             "steps": None}]
    pd.DataFrame(rows).to_csv(path, index=False)
    text = "\n".join(accuracy_section(path))
    assert "+1.5%: within the 2% goal" in text and "| fp32 NCHW | 0.2000 |" in text
    rows[1]["l1"] = 0.21
    pd.DataFrame(rows).to_csv(path, index=False)
    assert "+5.0%: NOT within" in "\n".join(accuracy_section(path))
