"""A study's timing file, ``results/timing/<stem>.json``, written by ``python -m nvs.sweep <study> --time``
(``nvs.sweep.time_rows``) and read by the cost tables.

Each job's own eval time is measured on the machine that ran it, beside whatever else ran there: a table of jobs
from several machines mixes them (the full model's 16.7 ± 15.8 ms of three seeds). The timing pass measures every
trained row and every evaluation row of the study in one process on one machine, interleaved, at the study's size
and at 256². Speed does not depend on the weights, so each row is its configuration built with fresh weights.

The file:
    version, study, scale, sizes, device, torch, precision, channels_last, git_sha, date, batch, repeats, warmup
    rows: {row name: {"identity": the overrides that define it (an evaluation row: its evaluated row's, then its own),
                      "network": {size: ms per image}, and for a routed evaluation row "routes": {size: {copy, warp,
                      full: ms}} (every pair sent down that route), for a per-level skips row "levels": {size:
                      {"none": ms with every warp done, <level>: ms with that level skipped for every pair}}}}
An evaluation row's time is mixed at table time from its finished jobs' mean shares, so the file stays valid as
seeds finish: a route row's is the sum over routes of share x that route's time; a skips row's is
none - sum over levels of (fraction of that level's warps skipped) x (none - that level's time). An entry whose
identity is not the row's as defined now is stale and not shown.
"""

from __future__ import annotations

import json
from pathlib import Path

from nvs.core.errors import UserError
from nvs.sweep.collect import ROUTES, SKIP_LEVELS
from nvs.sweep.jobs import row_overrides
from nvs.sweep.pick import PICK_COST
from nvs.sweep.study import Row, Study

VERSION = 1
HEADER = ("version", "study", "scale", "sizes", "device", "torch", "precision", "channels_last", "git_sha", "date",
          "batch", "repeats", "warmup", "rows")


def timing_path(results_dir: str | Path, study: Study) -> Path:
    return Path(results_dir) / "timing" / f"{study.results_stem}.json"


def timed_key(size: int) -> str:
    """The summary rows' key of the timed cost at one size."""
    return f"timed_{size}px_ms_per_image"


def timed_rows(study: Study) -> list[Row]:
    """The rows a timing pass measures: every trained and evaluation row (reference rows are not configurations)."""
    return [r for r in study.rows if not r.reference]


def identity(study: Study, row: Row) -> list[str]:
    """What defines a timed row: its overrides, and an evaluation row's evaluated row's before its own."""
    if row.evaluates:
        source = next(r for r in study.rows if r.name == row.evaluates)
        return [*row_overrides(study, source), "--", *row.overrides]
    return row_overrides(study, row)


def read_timing(path: Path, study: Study) -> dict | None:
    """The study's timing file, checked; None where there is none. A file that is not this study's, at this scale
    and version, with every header field, is one UserError naming the file and the key."""
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise UserError(f"{path}: not a readable timing file ({err}); run --time again or delete it") from None
    if not isinstance(data, dict):
        raise UserError(f"{path}: expected a JSON object; run --time again or delete it")
    missing = [k for k in HEADER if k not in data]
    if missing:
        raise UserError(f"{path}: key '{missing[0]}' is missing; run --time again or delete it")
    for key, want in (("version", VERSION), ("study", study.name), ("scale", study.scale)):
        if data[key] != want:
            raise UserError(f"{path}: '{key}' is {data[key]!r}, this study's is {want!r}; run "
                            f"python -m nvs.sweep {study.path.as_posix()} --time again or delete it")
    if not isinstance(data["rows"], dict) or not isinstance(data["sizes"], list):
        raise UserError(f"{path}: 'rows' must be an object and 'sizes' a list; run --time again or delete it")
    return data


def _mean(row: dict, key: str) -> float | None:
    value = row.get(key)
    return value[0] if isinstance(value, tuple) else None


def mixed_ms(entry: dict, row: dict, size: int) -> float | None:
    """One row's timed ms per image at ``size`` from its file entry; an evaluation row's mixed at the mean shares of
    its finished jobs (``row``: a ``summarize`` entry). None where a part or a share is missing."""
    key = str(size)
    try:
        if "routes" in entry:
            shares = [_mean(row, f"route_share_{r}") for r in ROUTES]
            if any(s is None for s in shares):
                return None
            return float(sum(s * float(entry["routes"][key][r]) for s, r in zip(shares, ROUTES)))
        if "levels" in entry:
            parts = entry["levels"][key]
            none = float(parts["none"])
            levels = [lv for lv in SKIP_LEVELS if lv in parts]
            fractions = [_mean(row, f"warp_skipped_{lv}") for lv in levels]
            if any(f is None for f in fractions):
                return None
            return none - sum(f * (none - float(parts[lv])) for f, lv in zip(fractions, levels))
        return float(entry["network"][key])
    except (KeyError, TypeError, ValueError):
        return None


def attach(study: Study, rows: list[dict], timing: dict | None) -> list[int]:
    """Add each summary row's timed cost per size (``timed_key``: (ms, None), (None, None) where the row has no valid
    entry) -> the sizes timed ([] without a file)."""
    if timing is None:
        return []
    sizes = sorted(int(s) for s in timing["sizes"])
    by_name = {r.name: r for r in study.rows}
    for r in rows:
        entry = timing["rows"].get(r["row"])
        row = by_name.get(r["row"])
        valid = isinstance(entry, dict) and row is not None and entry.get("identity") == identity(study, row)
        for size in sizes:
            r[timed_key(size)] = (mixed_ms(entry, r, size) if valid else None, None)
    return sizes


def header_cell(timing: dict, path: Path) -> str:
    """The tables' provenance line of the timing pass."""
    return (f"{timing['device']}, torch {timing['torch']}, {timing['precision']}"
            f"{' + channels_last' if timing['channels_last'] else ''}, {timing['date']}, git `{timing['git_sha']}`; "
            f"batch {timing['batch']}, median of {timing['repeats']} interleaved forwards after {timing['warmup']} "
            f"warm-up (`{path.as_posix()}`)")


def pick_cost(grows: list[dict], timed: list[int], size: int) -> str:
    """The cost the pick reads: the timing pass's at the study's size where every candidate has it, else each job's
    own eval time."""
    key = timed_key(size)
    candidates = [r for r in grows if r["kind"] == "train" and not r["oracle"] and r["l1"][0] is not None]
    if size in timed and candidates and all(r.get(key, (None,))[0] for r in candidates):
        return key
    return PICK_COST


def timed_cells(r: dict, grows: list[dict], timed: list[int]) -> list[str]:
    """A row's timed ms per image and its speed-up over the table's first trained row, at each timed size."""
    cells = []
    for s in timed:
        key = timed_key(s)
        base = next((g for g in grows if g["kind"] == "train" and not g["oracle"] and g.get(key, (None,))[0]), None)
        ms = r.get(key, (None,))[0]
        cells += [f"{ms:.1f}" if ms else "—", f"{base[key][0] / ms:.2f}×" if base and ms else "—"]
    return cells


def timed_legend(timed: list[int], size: int) -> str:
    sizes = " and ".join(f"{s}²" for s in timed)
    return (f"Timed {sizes}: every row's forward measured in one process on one machine (the timing line above), "
            "interleaved, each configuration built with fresh weights at that size; an evaluation row's time is its "
            "routes' (or its levels' skipped) times mixed at its finished jobs' mean shares (nvs.sweep.timing). × "
            f"timed: against the table's first trained row. The pick reads the timed {size}² cost where every "
            "candidate has one.")
