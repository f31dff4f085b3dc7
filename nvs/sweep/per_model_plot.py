"""The figure under a table's orderings: for each ordering, every test group's Δ (mean over seeds, turned so that
> 0 favours the paper's better row), with ±1 standard error of the seed spread where a row has two seeds or more."""

from __future__ import annotations


import numpy as np

from nvs.core.metric_spec import SPECS
from nvs.report.png import figure_png
from nvs.sweep.paper_order import Ordering

ROW_INCH = 0.32  # height per ordering


def per_model_png(title: str, decided: dict[str, list[Ordering]]) -> bytes | None:
    """One panel per metric, one line per ordering, one dot per test group (coloured alike across panels)."""
    panels = {m: [o for o in pairs if o.favour_a is not None] for m, pairs in decided.items()}
    panels = {m: pairs for m, pairs in panels.items() if pairs}
    if not panels:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = sorted({g for pairs in panels.values() for o in pairs for g in o.groups})
    cmap = plt.get_cmap("tab20" if len(groups) > 10 else "tab10")
    colour = {g: cmap(i % cmap.N) for i, g in enumerate(groups)}
    heights = [1.0 + ROW_INCH * len(pairs) for pairs in panels.values()]
    fig, axes = plt.subplots(len(panels), 1, figsize=(12, sum(heights) + 0.8), squeeze=False,
                             gridspec_kw={"height_ratios": heights, "hspace": 0.9 / len(panels)})
    for ax, (m, pairs) in zip(axes[:, 0], panels.items()):
        dots: dict[str, list[tuple[float, float, float]]] = {}   # group -> (Δ, y, s.e.): one call per colour
        for i, o in enumerate(pairs):
            # spread a line's dots vertically by group, so that dots at the same Δ stay visible
            y = i + np.linspace(-0.25, 0.25, len(o.groups)) if len(o.groups) > 1 else np.full(1, float(i))
            se = o.se if o.se is not None else np.zeros(len(o.groups))
            for g, x, yy, err in zip(o.groups, o.favour_a, y, se):
                dots.setdefault(g, []).append((x, yy, err))
            ax.plot([o.gap.diff * (1 if SPECS[m].higher_is_better else -1)] * 2, [i - 0.35, i + 0.35], color="k",
                    lw=1.5)
        for g, pts in dots.items():
            x, y, err = np.array(pts).T
            ax.errorbar(x, y, xerr=err, fmt="o", ms=3.5, lw=0.8, color=colour[g])
        ax.axvline(0, color="grey", lw=0.8, ls="--")
        ax.set_yticks(range(len(pairs)), [f"{o.pair}: {o.verdict}{o.note}" for o in pairs], fontsize=7)
        ax.invert_yaxis()
        ax.set_xlabel(f"{SPECS[m].label}: per-group Δ toward A (> 0: A better); black: Δ over all pairs", fontsize=8)
        ax.tick_params(axis="x", labelsize=7)
    handles = [plt.Line2D([], [], ls="", marker="o", color=colour[g], label=g) for g in groups]
    fig.legend(handles=handles, loc="center left", bbox_to_anchor=(0.81, 0.5), fontsize=6, frameon=False)
    fig.suptitle(f"{title}: per test group Δ of each ordering (error bars: ±1 s.e. over seeds)", fontsize=9)
    fig.subplots_adjust(left=0.33, right=0.8, top=1 - 0.45 / (sum(heights) + 0.8), bottom=0.5 / (sum(heights) + 0.8))
    return figure_png(fig, dpi=90)
