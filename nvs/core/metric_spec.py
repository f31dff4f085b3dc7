"""What every reported metric is: its key, column title, which way is better and how many decimals it is shown with.

metrics.py computes them under these keys; the sweep tables, the figures and the demo print them from here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class MetricSpec:
    key: str
    label: str
    higher_is_better: bool
    decimals: int
    kind: Literal["image", "depth"]

    @property
    def arrow(self) -> str:
        return "↑" if self.higher_is_better else "↓"

    def format(self, value: float | None) -> str:
        return "–" if value is None else f"{value:.{self.decimals}f}"


_ALL = (
    MetricSpec("l1", "L1", False, 4, "image"),
    MetricSpec("ssim_paper", "SSIM (paper)", True, 4, "image"),
    MetricSpec("ssim", "SSIM", True, 4, "image"),
    MetricSpec("psnr", "PSNR", True, 2, "image"),
    MetricSpec("lpips", "LPIPS", False, 4, "image"),
    MetricSpec("depth_l1", "depth L1-all", False, 4, "depth"),
    MetricSpec("depth_l1_rel", "depth L1-rel", False, 4, "depth"),
    MetricSpec("depth_l1_inv", "depth L1-inv", False, 4, "depth"),
    MetricSpec("depth_sc_inv", "depth sc-inv", False, 4, "depth"),
)
SPECS: dict[str, MetricSpec] = {m.key: m for m in _ALL}
IMAGE_METRICS: tuple[str, ...] = tuple(m.key for m in _ALL if m.kind == "image")
DEPTH_METRICS: tuple[str, ...] = tuple(m.key for m in _ALL if m.kind == "depth")
METRICS: tuple[str, ...] = IMAGE_METRICS + DEPTH_METRICS
