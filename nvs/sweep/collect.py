"""Collection: one record per job (status, error line, test metrics, costs) and the study's CSV; per-row means.

An evaluation with a route (``nvs.evaluate route=fit``) adds the share of test pairs per route (``ROUTE_SHARES``), and
one with ``time_sizes`` the forward time per image at each size (metrics.json's ``timing_by_size``: ``{"<S>":
{network_ms_per_image, routed_ms_per_image?, speedup?, ...}}``), read as ``eval_<S>px_ms_per_image`` (the routed
forward where there is a route, else the network's) and ``eval_<S>px_speedup``. The CSV has their columns only where
some job has them, so a study without them writes the columns it always did; likewise ``oracle`` (True on the jobs of a
trained or evaluated row that uses ground truth at test time, e.g. the oracle depth, which ``nvs.pareto`` leaves out).
"""

from __future__ import annotations

import csv
import io
import math
import re
from pathlib import Path

from omegaconf import OmegaConf

from nvs.core.metric_spec import METRICS
from nvs.sweep.jobs import Job, Status, read_json, stale_error
from nvs.sweep.study import Study

SKIP_LEVELS = ("conv0", "conv2", "conv3", "conv4")
# Fraction of (sample, level) warps an adaptive-skips model skipped at test time, overall and per level.
SKIP_FRACTIONS = ("warp_skipped", *(f"warp_skipped_{lv}" for lv in SKIP_LEVELS))
# Costs read from metrics.json: eval forward time per test image (no metrics), median train step time.
# The stopping rule's record (nvs.run.convergence.RECORD; not imported here: that module loads Lightning).
CONVERGENCE = "convergence.json"
COSTS = ("eval_ms_per_image", "eval_forward_ms_per_image", "train_step_ms")
ROUTES = ("copy", "warp", "full")
ROUTE_SHARES = tuple(f"route_share_{r}" for r in ROUTES)  # fraction of the test pairs sent down each route
CSV_COLUMNS = ["study", "row", "label", "kind", "data", "seed", "status", "error", *METRICS, "n_pairs", "params",
               "train_wall_s", "train_samples_per_s", "eval_ms_per_image", "steps", "image_size", "precision",
               "device", "git_sha", "run_dir", "overrides", *[f"paper_{m}" for m in METRICS],
               "eval_forward_ms_per_image", "train_step_ms", *SKIP_FRACTIONS, "stop", "stop_reason"]


def _read_overrides(job_dir: Path) -> list[str]:
    path = job_dir / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return []
    try:
        return [str(o) for o in OmegaConf.load(path)]
    except Exception:  # noqa: BLE001 - an unreadable file only loses the overrides column
        return []


def _num(v) -> float | None:
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return None if math.isnan(f) else f


def shown_path(p: Path) -> str:
    """Relative to the working directory when inside it (committed tables should not carry a machine's paths)."""
    try:
        return Path(p).resolve().relative_to(Path.cwd().resolve()).as_posix()
    except ValueError:
        return str(p)


def size_columns(size: int) -> tuple[str, str]:
    """The record keys of one timed size: (ms per image, speed-up of the route over the network)."""
    return f"eval_{size}px_ms_per_image", f"eval_{size}px_speedup"


def timed_sizes(records: list[dict]) -> list[int]:
    """The sizes some record has a forward time at (``timing_by_size``), ascending."""
    return sorted({int(m[1]) for r in records for k, v in r.items()
                   if v is not None and (m := re.fullmatch(r"eval_(\d+)px_ms_per_image", k))})


def _timing(m: dict) -> dict:
    """metrics.json's ``timing_by_size`` as record keys (``size_columns``); {} without it."""
    out = {}
    for size, t in sorted((m.get("timing_by_size") or {}).items(), key=lambda kv: int(kv[0])):
        if not isinstance(t, dict):
            continue
        ms, speedup = size_columns(int(size))
        out[ms] = _num(t.get("routed_ms_per_image", t.get("network_ms_per_image")))
        out[speedup] = _num(t.get("speedup"))
    return out


def collect(jobs: list[Job]) -> list[dict]:
    """One record per job: its status, error line, test metrics and costs (None where absent)."""
    records = []
    for j in jobs:
        m = (read_json(j.dir / "metrics.json") if j.status == Status.DONE else None) or {}
        # the stopping rule's record (callbacks=convergence): 'converged' at metrics' steps, or 'max_steps'
        stop = (read_json(j.dir / CONVERGENCE) if j.status == Status.DONE else None) or {}
        test = m.get("test") or {}
        error = j.error
        if j.waiting and j.status != Status.DONE:  # an evaluation job without its evaluated job's checkpoint
            error = j.waiting
        elif j.status == Status.INCOMPLETE:
            error = "interrupted; re-run the study to resume from last.ckpt"
        elif j.status == Status.STALE:
            error = stale_error(j)
        records.append({
            "study": j.study, "row": j.row.name, "label": j.row.label, "kind": j.kind,
            "data": m.get("data") or j.data, "seed": j.seed, "status": str(j.status), "error": error,
            **{k: _num(test.get(k)) for k in METRICS},
            "n_pairs": test.get("n_pairs"), "params": m.get("params"),
            "train_wall_s": _num(m.get("train_wall_s")), "train_samples_per_s": _num(m.get("train_samples_per_s")),
            **{k: _num(m.get(k)) for k in COSTS}, **{k: _num(test.get(k)) for k in SKIP_FRACTIONS},
            "steps": m.get("steps"),
            "image_size": m.get("image_size"), "precision": m.get("precision"), "device": m.get("device"),
            "git_sha": m.get("git_sha"), "run_dir": shown_path(j.dir),
            "overrides": " ".join(_read_overrides(j.dir)) if j.status == Status.DONE else "",
            **{f"paper_{k}": j.row.paper.get(k) for k in METRICS},
            "stop": stop.get("outcome"), "stop_reason": stop.get("reason"),
            **{k: _num(test.get(k)) for k in ROUTE_SHARES}, **_timing(m),
            # a trained or evaluated row that uses ground truth at test time (reference rows say so in their label)
            "oracle": True if j.row.oracle and not j.row.reference else None,
            "dir": j.dir,  # not a CSV column: where the tables read the job's per-image results
        })
    return records


def render_csv(records: list[dict]) -> str:
    """The CSV: ``CSV_COLUMNS``, then ``oracle``, the route shares and per-size times where some job has them."""
    extra = [k for k in ("oracle", *ROUTE_SHARES) if any(r.get(k) is not None for r in records)]
    extra += [k for size in timed_sizes(records) for k in size_columns(size)]
    columns = CSV_COLUMNS + extra
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in records:
        w.writerow({k: ("" if r.get(k) is None else (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]))
                    for k in columns})
    return buf.getvalue()


def mean_std(values: list[float]) -> tuple[float | None, float | None]:
    """Mean and sample standard deviation (ddof=1; None for fewer than two values)."""
    vals = [v for v in values if v is not None]
    if not vals:
        return None, None
    mean = sum(vals) / len(vals)
    if len(vals) < 2:
        return mean, None
    return mean, math.sqrt(sum((v - mean) ** 2 for v in vals) / (len(vals) - 1))


def _notes(recs: list[dict]) -> list[str]:
    """'s0, s2 failed: <error line>' for each distinct (status, error) among the unfinished jobs of a row."""
    by: dict[tuple[str, str], list[int]] = {}
    for r in recs:
        if r["status"] != Status.DONE:
            by.setdefault((r["status"], r["error"] or ""), []).append(r["seed"])
    return [f"{', '.join(f's{s}' for s in seeds)} {status}" + (f": {err}" if err else "")
            for (status, err), seeds in by.items()]


def summarize(study: Study, records: list[dict]) -> list[dict]:
    """Per row: mean/std of each metric and cost over its done seeds, counts, and the error lines of failures."""
    out = []
    timed = [k for size in timed_sizes(records) for k in size_columns(size)]
    for row in study.rows:
        recs = [r for r in records if r["row"] == row.name]
        done = [r for r in recs if r["status"] == Status.DONE]
        s = {"row": row.name, "label": row.label, "kind": row.kind, "reference": row.reference,
             "n_done": len(done), "n_jobs": len(recs),
             "data": next((r["data"] for r in recs if r["data"]), row.data), "paper": row.paper,
             "oracle": row.oracle, "stands_for": row.stands_for, "evaluates": row.evaluates,
             "overrides": row.overrides, "notes": _notes(recs),
             "dirs": [r["dir"] for r in done if r.get("dir")],
             "seeds": [r["seed"] for r in done if r.get("dir")]}  # the seed of each of 'dirs'
        for k in (*METRICS, "params", "train_wall_s", *COSTS, *SKIP_FRACTIONS, *ROUTE_SHARES, *timed):
            s[k] = mean_std([_num(r.get(k)) for r in done])
        out.append(s)
    return out
