"""The Pareto report's pick per dataset: the cheapest row at evaluation within 1% of the best L1, decided by the
interval of its L1 against the best (as the cost table's), written under the dataset's table."""

from __future__ import annotations

import csv

from nvs import pareto
from nvs.sweep.pick import PICK_COST, pareto_pick_line


def _job(root, name, values):
    """A job directory whose test_per_image.csv has l1 = values[k] on pair k (test model m<k // 3>)."""
    d = root / name
    d.mkdir(parents=True)
    lines = ["index,id_src,id_tgt,l1,ssim_paper"]
    lines += [f"{k},m{k // 3}_{20 * (k % 3)}_0s,m{k // 3}_{20 * (k % 3)}_0,{v},{1 - v}" for k, v in enumerate(values)]
    (d / "test_per_image.csv").write_text("\n".join(lines) + "\n")
    return d


BASE = [0.20 + 0.01 * (k % 5) for k in range(30)]  # 10 test models x 3 pairs
CLOSE = [v * 1.005 for v in BASE]  # 0.5% worse on every pair: the interval's upper end inside the 1% margin
# 0.5% worse on the mean but +-10% by test model: the point estimate is within 1%, the interval is not
NOISY = [v * (1.005 + (0.1 if (k // 3) % 2 else -0.1)) for k, v in enumerate(BASE)]


def _row(label, d, values, ms):
    return {"label": label, "dirs": [str(d)], "l1": sum(values) / len(values), PICK_COST: ms}


def test_the_pick_is_the_cheapest_row_the_interval_puts_within_the_margin(tmp_path):
    full, close, noisy = (_job(tmp_path, n, v) for n, v in (("full", BASE), ("close", CLOSE), ("noisy", NOISY)))
    rows = [_row("Full", full, BASE, 10.0), _row("Close", close, CLOSE, 7.0), _row("Noisy", noisy, NOISY, 5.0)]
    assert rows[2]["l1"] <= 1.01 * rows[0]["l1"]  # the point estimate alone would pick the noisy row
    line = pareto_pick_line(rows)
    assert line.startswith("**Pick**: Close, the cheapest at evaluation within 1% of the best L1")
    assert "shown by the interval of ΔL1 against it" in line and "1.43× faster" in line
    # Without the close row nothing cheaper is shown to be within the margin: the best row is its own pick.
    assert "the best row itself" in pareto_pick_line([rows[0], rows[2]])
    # Without per-image results the point estimate decides, and the line says so.
    gone = [{**r, "dirs": [str(tmp_path / "missing")]} for r in rows]
    assert "Noisy" in pareto_pick_line(gone) and "by the point estimate" in pareto_pick_line(gone)
    # No row with both an L1 and an eval time: no pick.
    assert pareto_pick_line([{**rows[0], PICK_COST: float("nan")}]).startswith("No pick")


def test_the_report_prints_each_datasets_pick_under_its_table(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the CSV's run_dir is relative to the working directory, as the runner writes it
    jobs = tmp_path / "results" / "jobs" / "64px_10000steps"
    fields = ["study", "row", "label", "kind", "data", "seed", "status", "run_dir", "l1", "ssim_paper",
              "train_wall_s", PICK_COST, "image_size", "steps"]
    out = []
    for label, stem, values, ms in (("Full", "full", BASE, 10.0), ("Close", "close", CLOSE, 7.0),
                                    ("Noisy", "noisy", NOISY, 5.0)):
        d = _job(jobs, f"{stem}_s0", values)
        out.append({"study": "fab", "row": stem, "label": label, "kind": "train", "data": "chairs", "seed": 0,
                    "status": "done", "run_dir": d.relative_to(tmp_path).as_posix(),
                    "l1": sum(values) / len(values), "ssim_paper": 0.9, "train_wall_s": 100.0, PICK_COST: ms,
                    "image_size": 64, "steps": 10000})
    with open(tmp_path / "results" / "fab.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(out)
    md, _ = pareto.run(["results/fab.csv", "--results", "results"])
    text = md.read_text()
    assert "**Pick**: Close" in text and text.index("| Close |") < text.index("**Pick**: Close")


def test_oracle_rows_are_left_out_and_the_skip_study_is_read_by_default(tmp_path, monkeypatch):
    """A row that uses ground truth at test time (the CSV's oracle column) is no configuration: however cheap and good,
    it is neither a point nor the pick. The skip study's CSV is among the default inputs."""
    monkeypatch.chdir(tmp_path)
    jobs = tmp_path / "results" / "jobs" / "64px_10000steps"
    fields = ["study", "row", "label", "kind", "data", "seed", "status", "run_dir", "l1", "ssim_paper",
              "train_wall_s", PICK_COST, "image_size", "steps", "oracle"]
    out = []
    for label, stem, values, ms, oracle in (("Full", "full", BASE, 10.0, ""),
                                            ("Oracle depth", "oracle", [v * 0.5 for v in BASE], 1.0, "True")):
        d = _job(jobs, f"{stem}_s0", values)
        out.append({"study": "skip", "row": stem, "label": label, "kind": "train", "data": "chairs", "seed": 0,
                    "status": "done", "run_dir": d.relative_to(tmp_path).as_posix(), "oracle": oracle,
                    "l1": sum(values) / len(values), "ssim_paper": 0.9, "train_wall_s": 100.0, PICK_COST: ms,
                    "image_size": 64, "steps": 10000})
    with open(tmp_path / "results" / "skip.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(out)
    md, _ = pareto.run(["--results", "results"])  # no CSV named: the default studies, skip.csv among them
    text = md.read_text()
    assert "`results/skip.csv`" in text and "| Full |" in text and "**Pick**: Full" in text
    assert "Oracle depth" not in text
