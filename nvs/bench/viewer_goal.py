"""The viewer's speed goal (≥ 20 views/s at 128²), read off the viewer's load reports of the bench's machine.

``python -m nvs.viewer.load`` measures views through the HTTP endpoint and writes a JSON report; those of one machine
lie in ``results/viewer/<device>/`` (``<device>``: the bench report's name without its ``cpu--`` prefix, subfolders
included). A bench report lists them (``report["viewer"]``) and its goal lines say, per way of running the pose step
(eager or ``compile=true``), the median views/s of those runs, met or by how much not, and what bounds it: the pose
step's FLOPs (the viewer counts them at start-up) against its time and the conv peak of its mode on this machine.
"""

from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path

from nvs.bench.measure import mode_peak

VIEWS_PER_S_128 = 20.0
_KEEP = ("image_size", "views_per_s", "median_ms", "model_median_ms", "compiled", "pose_gflop", "mode", "precision",
         "threads", "git_sha", "date")


def viewer_dir(bench_dir: str | Path, slug: str) -> Path:
    """Where the viewer's load reports of the bench report ``<bench_dir>/<slug>.json``'s machine lie."""
    return Path(bench_dir).resolve().parent / "viewer" / slug.removeprefix("cpu--")


def viewer_reports(bench_dir: str | Path, slug: str) -> list[dict]:
    """The load reports of this machine (the fields the goal reads, and the file from the folder above results/)."""
    root = viewer_dir(bench_dir, slug)
    found = []
    for path in sorted(root.rglob("*.json")) if root.is_dir() else []:
        try:
            data = json.loads(path.read_text())
            row = {k: data.get(k) for k in _KEEP}
            float(row["views_per_s"]), int(row["image_size"])
        except (OSError, ValueError, KeyError, TypeError):
            print(f"{path}: not a report of nvs.viewer.load; ignored", file=sys.stderr)
            continue
        found.append({**row, "file": str(path.relative_to(root.parent.parent.parent))})
    return found


def _mode(row: dict) -> str:
    """The bench mode of a report (reports before the viewer recorded it: fp32 for 32-true, bf16_cl for bf16)."""
    return row.get("mode") or ("bf16_cl" if str(row.get("precision", "")).startswith("bf16") else "fp32")


def viewer_goal_lines(reports: list[dict], peaks: dict) -> list[str]:
    """One goal line per way of running the pose step, over this machine's 128² reports at the default threads."""
    groups: dict[tuple[bool, str], list[dict]] = {}
    for row in reports:
        if row["image_size"] == 128 and not row.get("threads"):
            groups.setdefault((bool(row.get("compiled")), _mode(row)), []).append(row)
    lines = []
    for (compiled, mode), rows in sorted(groups.items()):
        vps = statistics.median(r["views_per_s"] for r in rows)
        files = ", ".join(f"`{r['file']}`" for r in rows)
        how = "compile=true" if compiled else "eager"
        ok = vps >= VIEWS_PER_S_128
        line = (f"- viewer at 128² ({how}, {mode}; median of {len(rows)} run(s) of `nvs.viewer.load`: {files}): "
                f"{vps:.1f} views/s; goal ≥ {VIEWS_PER_S_128:.0f}: {'**met**' if ok else '**not met**'}")
        if not ok:
            line += (f", short by {VIEWS_PER_S_128 / vps:.2f}×: a view takes {1000 / vps:.0f} ms end to end against "
                     f"the goal's {1000 / VIEWS_PER_S_128:.0f} ms")
            gflop = [r["pose_gflop"] for r in rows if r.get("pose_gflop")]
            model_ms = [r["model_median_ms"] for r in rows if r.get("model_median_ms")]
            if gflop and model_ms:
                g, ms = statistics.median(gflop), statistics.median(model_ms)
                rate = 1000 * g / ms
                line += f"; the pose step does {g:.1f} GFLOP in {ms:.0f} ms ({rate:.0f} GFLOP/s)"
                peak = mode_peak(peaks, mode)
                best = max((v for k, v in peaks.items() if k.startswith("fp32_conv")), default=None)
                if peak:
                    line += f", {100 * rate / peak:.0f}% of its mode's conv peak ({peak:.0f})"
                if best:
                    bound = 1000 * g / best
                    line += (f"; at the best fp32 conv peak ({best:.0f} GFLOP/s, batch 8) it would take {bound:.0f} "
                             f"ms ({1000 / bound:.0f} views/s before PNG and HTTP), so the goal "
                             + ("is beyond this machine's arithmetic" if 1000 / bound < VIEWS_PER_S_128 else
                                "needs the pose step's batch-1 convolutions nearer that peak"))
        lines.append(line)
    return lines
