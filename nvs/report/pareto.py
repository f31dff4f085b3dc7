"""Run time against error from the sweep results: the rows, their Pareto front per dataset and scale, the report.

Every finished trained row is a point under its label, with or without paper numbers (a variant such as the
norms-fixed network stands beside the paper's full model); reference rows (no training) and rows that use ground
truth at test time (the CSV's ``oracle`` column) are left out; a job shared by
several studies counts once (the label of the first CSV that holds it). Rows trained at different scales (image
size, steps) are never compared: each scale of a dataset is its own series and front.
(``python -m nvs.pareto`` writes ``results/pareto.md`` and ``.png`` from these.)
"""

from __future__ import annotations

import re
from pathlib import Path

import pandas as pd

from nvs.core.errors import UserError
from nvs.core.metric_spec import SPECS
from nvs.core.provenance import git_sha, utc_now
from nvs.report.png import figure_png

# (column, label, True when larger is better), from the one metric specification
ERRORS = tuple((m, SPECS[m].label, SPECS[m].higher_is_better) for m in ("l1", "ssim_paper"))
COSTS = (("train_wall_s", "train wall time (s)"), ("eval_forward_ms_per_image", "eval forward ms / image"))
# The default inputs: the studies whose rows are the paper's methods and ablations, then the skip study's
# configurations (plane depth, without conv0, lean) trained at the same scale.
PAPER_STUDIES = ("ablation", "comparison_objects", "comparison_drive", "skip")


def pareto_front(cost: list[float], error: list[float]) -> list[bool]:
    """Which points no other point beats: lower-or-equal cost and error, one of them strictly lower. (N,) -> (N,)."""
    on = []
    for i, (c, e) in enumerate(zip(cost, error)):
        dominated = any(c2 <= c and e2 <= e and (c2 < c or e2 < e)
                        for j, (c2, e2) in enumerate(zip(cost, error)) if j != i)
        on.append(not dominated)
    return on


def _scale(row) -> str:
    match = re.fullmatch(r"(\d+)px_(\d+)steps", Path(str(row["run_dir"])).parent.name)
    if match:
        return f"{match[1]}²/{match[2]} steps" + (" at most" if str(row.get("stop", "nan")) != "nan" else "")
    return _int_text(row["image_size"]) + "²/" + _int_text(row["steps"]) + " steps"


def load_rows(csv_paths: list[Path]) -> pd.DataFrame:
    """Mean over finished seeds per (data, run) of the trained rows of the given sweep CSVs."""
    frames = []
    for p in csv_paths:
        df = pd.read_csv(p)
        missing = {"study", "row", "kind", "status", "run_dir", "l1", "train_wall_s"} - set(df.columns)
        if missing:
            raise UserError(f"{p}: not a sweep CSV (no {sorted(missing)} columns)")
        frames.append(df)
    if not frames:
        raise UserError("no sweep CSVs given (run python -m nvs.sweep sweeps/<study>.yaml first)")
    df = pd.concat(frames, ignore_index=True)
    df = df[(df["status"] == "done") & (df["kind"] == "train")].drop_duplicates("run_dir")
    if "oracle" in df.columns:  # ground truth at test time (the oracle depth): an upper bound, not a configuration
        df = df[df["oracle"].map(lambda v: str(v).strip().lower() not in ("true", "1"))]
    if df.empty:
        raise UserError("the sweep CSVs hold no finished trained jobs")
    for cost, _ in COSTS:
        if cost not in df.columns:
            df[cost] = float("nan")  # a CSV from before the column existed: those points are left out of that plot
    # One series per dataset and scale: train time at 500 steps says nothing next to 1500 steps. A job's scale is its
    # study's (the run directory's <size>px_<steps>steps parent): a job that the stopping rule ended early belongs to
    # its budget's series, not to a series of its own.
    scales = df.apply(_scale, axis=1)
    if scales.nunique() > 1:
        df = df.assign(data=df["data"] + " @ " + scales)
    # The job directory stem without the seed names a configuration across studies.
    df = df.assign(run=df["run_dir"].map(lambda d: Path(str(d)).name.rsplit("_s", 1)[0]))
    cols = [c for c, *_ in ERRORS] + [c for c, _ in COSTS]
    agg = df.groupby(["data", "run"], sort=False).agg(
        label=("label", "first"), study=("study", "first"), seeds=("seed", "nunique"),
        dirs=("run_dir", lambda d: [str(x) for x in d]), **{c: (c, "mean") for c in cols}).reset_index()
    for err, _, higher in ERRORS:
        for cost, _ in COSTS:
            flags = pd.Series(False, index=agg.index)
            for _, g in agg.groupby("data"):
                g = g.dropna(subset=[err, cost])
                e = (-g[err] if higher else g[err]).tolist()
                flags.loc[g.index] = pareto_front(g[cost].tolist(), e)
            agg[f"front_{err}_{cost}"] = flags
    return agg


def _int_text(v) -> str:
    try:
        return str(int(float(v)))
    except (TypeError, ValueError):
        return "?"


def render_markdown(agg: pd.DataFrame, sources: list[Path], command: str, picks: dict[str, str] | None = None) -> str:
    """The report; ``picks``: a dataset's pick sentence (``nvs.pareto``: the cheapest row at evaluation within the
    margin of the best L1, decided by the interval), printed under its table."""
    (l1, _, _), (ssim, _, _) = ERRORS
    lines = [
        "# Run time against error", "",
        f"Generated by `{command}` from {', '.join(f'`{p.as_posix()}`' for p in sources)}; do not edit by hand.",
        f"git SHA `{git_sha()}`, {utc_now()}.", "",
        "Each point is a trained row (mean over its finished seeds). Train time is the fit's wall time (validation",
        "included); eval is the forward pass alone per test image in the test loop (`eval_forward_ms_per_image` of",
        "`metrics.json`; batched, metrics excluded; `python -m nvs.bench` times batch 1 and every execution mode).",
        "★ marks the Pareto front within a dataset: no other row there is both faster and better.", "",
        "![pareto](pareto.png)", "",
    ]
    for data, g in agg.groupby("data", sort=False):
        lines += [f"## {data}", "",
                  f"| Row | study | seeds | {SPECS[l1].label} {SPECS[l1].arrow} "
                  f"| {SPECS[ssim].label} {SPECS[ssim].arrow} | train (s) | eval forward (ms/img) "
                  "| L1 vs train | L1 vs eval | SSIM vs train | SSIM vs eval |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for _, r in g.sort_values("l1").iterrows():
            flags = ["★" if r[f"front_{e}_{c}"] else "" for e, *_ in ERRORS for c, _ in COSTS]
            lines.append(f"| {r['label']} | {r['study']} | {r['seeds']} | {SPECS[l1].format(r[l1])} "
                         f"| {SPECS[ssim].format(r[ssim])} "
                         f"| {r['train_wall_s']:.0f} | {r['eval_forward_ms_per_image']:.2f} | " + " | ".join(flags) + " |")
        lines.append("")
        if picks and data in picks:
            lines += [picks[data], ""]
    return "\n".join(lines)


def plot(agg: pd.DataFrame) -> bytes:
    """A 2×2 grid (L1, SSIM) × (train time, eval time), PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(ERRORS), len(COSTS), figsize=(12, 9), squeeze=False)
    colours = dict(zip(agg["data"].unique(), plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    for i, (err, err_label, higher) in enumerate(ERRORS):
        for j, (cost, cost_label) in enumerate(COSTS):
            ax = axes[i][j]
            for data, g in agg.groupby("data", sort=False):
                g = g.dropna(subset=[err, cost])
                front = g[g[f"front_{err}_{cost}"]].sort_values(cost)
                ax.scatter(g[cost], g[err], color=colours[data], label=data, s=30, alpha=0.8)
                ax.step(front[cost], front[err], where="post", color=colours[data], lw=1.2, ls="--")
                ax.scatter(front[cost], front[err], color=colours[data], marker="*", s=160, edgecolor="k", lw=0.5)
                for _, r in g.iterrows():
                    ax.annotate(str(r["run"]), (r[cost], r[err]), fontsize=7, xytext=(3, 3),
                                textcoords="offset points")
            spread = agg[cost].dropna()
            if len(spread) and spread.min() > 0 and spread.max() / spread.min() > 10:
                ax.set_xscale("log")  # costs spanning decades (pixel generator vs full model) stay readable
            ax.set_xlabel(cost_label)
            ax.set_ylabel(f"{err_label} ({'higher' if higher else 'lower'} is better)")
            ax.grid(True, which="both", alpha=0.3)
    axes[0][0].legend(title="data (★ Pareto front)")
    fig.suptitle("Run time against error per trained row")
    fig.tight_layout()
    return figure_png(fig, dpi=110)


def default_csvs(results: Path) -> list[Path]:
    """The paper studies' sweep CSVs in ``results`` (``<study>.csv`` at the committed scale), in PAPER_STUDIES order."""
    out = []
    for name in PAPER_STUDIES:
        p = results / f"{name}.csv"
        if p.is_file():
            with open(p) as f:
                if f.readline().startswith("study,row,"):
                    out.append(p)
    return out
