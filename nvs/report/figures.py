"""The paper's figures from finished runs: qualitative grids (Fig. 3/4/5), depth point clouds (Fig. 6) and training
curves, as PNG bytes or files. A library: ``python -m nvs.figures`` and ``python -m nvs.sweep --figures`` draw with it.

Trained runs are rebuilt from their validation-selected checkpoint through ``nvs.run.checkpoints`` (the one restore, with
its weight checks); reference runs from their own overrides.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from nvs.core.atomic import write_bytes
from nvs.core.errors import UserError
from nvs.report.png import figure_png
from nvs.run.finished import Run, checkpoint_of


def load_run(run: Run):
    """(module in eval mode, datamodule) rebuilt from a run directory, as ``nvs.evaluate`` rebuilds it."""
    from nvs.run.build import build_data
    from nvs.run.checkpoints import restore_module, restore_run_config
    from nvs.run.compose import compose

    # A reference run is rebuilt from its own overrides; a trained run from its checkpoint alone.
    overrides = []
    if run.reference:
        overrides = [str(o) for o in OmegaConf.load(run.dir / ".hydra" / "overrides.yaml")
                     if not str(o).startswith("seed=")]
    cfg = compose("evaluate", overrides)
    if not run.reference:
        cfg.ckpt_path = str(checkpoint_of(run.dir))
    cfg.paths.output_dir = str(run.dir)
    cfg.out_dir = str(run.dir)
    cfg_run, ckpt = restore_run_config(cfg)
    datamodule = build_data(cfg_run)
    return restore_module(cfg_run, ckpt), datamodule


def fixed_pairs(n_total: int, k: int) -> list[int]:
    """k test-pair indices spread evenly over the test set (the same for every method)."""
    return sorted(set(np.linspace(0, n_total - 1, min(k, n_total)).round().astype(int).tolist()))


@torch.no_grad()
def predict(run: Run, k: int) -> dict:
    """Inputs, targets and the run's outputs on ``k`` fixed test pairs; tensors on CPU."""
    from torch.utils.data import default_collate

    module, datamodule = load_run(run)
    ds = datamodule.dataset("test")
    batch = default_collate([ds[i] for i in fixed_pairs(len(ds), k)])
    out = module(batch)
    return {"batch": batch, "rgb": out["rgb"].float().clamp(0, 1), "depth": out.get("depth")}


def unproject(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Camera-frame points of every pixel: (H,W) depth, (3,3) K -> (H*W,3), OpenCV axes (x right, y down, z fwd)."""
    H, W = depth.shape
    v, u = torch.meshgrid(torch.arange(H, dtype=K.dtype), torch.arange(W, dtype=K.dtype), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], -1).reshape(-1, 3)
    rays = pix @ torch.linalg.inv(K).T
    return rays * depth.reshape(-1, 1).to(K.dtype)


def _png(fig) -> bytes:
    return figure_png(fig, dpi=110, tight=True)


def _img(t: torch.Tensor) -> np.ndarray:
    return t.permute(1, 2, 0).clamp(0, 1).numpy()


def qualitative_grid(preds: list[tuple[Run, dict]]) -> bytes:
    """Rows = test pairs; columns = input, target, then each run's prediction."""
    import matplotlib.pyplot as plt

    batch = preds[0][1]["batch"]
    n = batch["src"].shape[0]
    cols = 2 + len(preds)
    fig, axes = plt.subplots(n, cols, figsize=(1.6 * cols, 1.6 * n + 0.4), squeeze=False)
    for i in range(n):
        panels = [("Input", batch["src"][i]), ("Target", batch["tgt"][i])]
        panels += [(run.label, p["rgb"][i]) for run, p in preds]
        for j, (title, img) in enumerate(panels):
            ax = axes[i][j]
            ax.imshow(_img(img))
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(textwrap.fill(title, 20), fontsize=7)  # long labels wrap instead of overlapping
    fig.tight_layout()
    return _png(fig)


def depth_points(preds: list[tuple[Run, dict]], pair: int = 0, max_points: int = 4000) -> bytes:
    """Ground-truth and predicted target depth of one pair as coloured point clouds from two angles."""
    import matplotlib.pyplot as plt

    batch = preds[0][1]["batch"]
    K = batch["K"][pair].double()
    tgt = batch["tgt"][pair]
    gt = batch.get("depth_tgt")
    mask = (gt[pair, 0] > 0).reshape(-1) if gt is not None else torch.ones(tgt.shape[1] * tgt.shape[2], dtype=bool)
    clouds = ([("Ground truth", gt[pair, 0])] if gt is not None else [])
    clouds += [(run.label, p["depth"][pair, 0].float()) for run, p in preds if p["depth"] is not None]
    colours = tgt.permute(1, 2, 0).reshape(-1, 3)[mask].numpy()
    keep = np.random.default_rng(0).permutation(int(mask.sum()))[:max_points]
    views = ((15, -60), (15, 30))
    points = [unproject(depth, K)[mask].numpy()[keep] for _, depth in clouds]
    # One set of axis limits for every cloud (from the first, the ground truth when there is one): shapes compare.
    lo, hi = np.percentile(points[0], 1, axis=0), np.percentile(points[0], 99, axis=0)
    pad = 0.15 * (hi - lo).max() + 1e-6
    fig = plt.figure(figsize=(3.2 * len(views), 3.0 * len(clouds)))
    for r, ((title, _), pts) in enumerate(zip(clouds, points)):
        for c, (elev, azim) in enumerate(views):
            ax = fig.add_subplot(len(clouds), len(views), r * len(views) + c + 1, projection="3d")
            # Plot (x, z, -y) so that the camera's "down" is the plot's down.
            ax.scatter(pts[:, 0], pts[:, 2], -pts[:, 1], c=colours[keep], s=1.5, depthshade=False)
            ax.view_init(elev=elev, azim=azim)
            ax.set_xlim(lo[0] - pad, hi[0] + pad)
            ax.set_ylim(lo[2] - pad, hi[2] + pad)
            ax.set_zlim(-hi[1] - pad, -lo[1] + pad)
            ax.set_xlabel("x")
            ax.set_ylabel("z (depth)")
            ax.set_zlabel("-y")
            ax.tick_params(labelsize=5)
            ax.set_title(f"{title} (azim {azim}°)", fontsize=8)
    fig.tight_layout()
    return _png(fig)


def training_curves(runs: list[Run]) -> bytes | None:
    """Training loss (smoothed) and validation L1 against step, one line per trained run; None without logs."""
    import matplotlib.pyplot as plt
    import pandas as pd

    logs = [(r, r.dir / "csv" / "metrics.csv") for r in runs if not r.reference]
    logs = [(r, pd.read_csv(p)) for r, p in logs if p.is_file()]
    if not logs:
        return None
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.2))
    for run, df in logs:
        if "train/loss/total" in df:
            t = df[["step", "train/loss/total"]].dropna()
            a.plot(t["step"], t["train/loss/total"].rolling(5, min_periods=1).mean(), label=run.label, lw=1)
        if "val/l1" in df:
            v = df[["step", "val/l1"]].dropna()
            b.plot(v["step"], v["val/l1"], marker="o", ms=3, label=run.label, lw=1)
    a.set(xlabel="step", ylabel="train/loss/total (weighted sum; rolling mean of 5 logs)", yscale="log")
    b.set(xlabel="step", ylabel="val/l1")
    for ax in (a, b):
        ax.grid(alpha=0.3)
    b.legend(fontsize=7)
    fig.tight_layout()
    return _png(fig)


def make_figures(runs: list[Run], out: Path, name: str, pairs: int = 4) -> list[Path]:
    written = []
    by_data: dict[str, list[Run]] = {}
    for r in runs:
        by_data.setdefault(r.data, []).append(r)
    depth_preds = []
    for data, group in by_data.items():
        preds = [(r, predict(r, pairs)) for r in group]
        ids = {tuple(p["batch"]["id_tgt"]) for _, p in preds}
        if len(ids) > 1:
            raise UserError(f"runs on '{data}' do not share their test pairs; draw them separately")
        path = out / f"{name}_qualitative_{data}.png"
        write_bytes(path, qualitative_grid(preds))
        written.append(path)
        with_depth = [(r, p) for r, p in preds if p["depth"] is not None and not r.reference]
        if with_depth:
            depth_preds.append((data, with_depth))
    for data, preds in depth_preds:
        suffix = "" if len(depth_preds) == 1 else f"_{data}"
        path = out / f"{name}_depth_points{suffix}.png"
        write_bytes(path, depth_points(preds))
        written.append(path)
    curves = training_curves(runs)
    if curves is not None:
        path = out / f"{name}_curves.png"
        write_bytes(path, curves)
        written.append(path)
    return written
