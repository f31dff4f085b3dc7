"""``python -m nvs.sweep <study> --time``: every row's forward timed on this machine, in one process, interleaved;
the file it writes and how the tables read it: ``nvs.sweep.timing``.

Per dataset of the study and per size, each timed row is built from its configuration (``row_overrides``, seed 0)
at that size with fresh weights (speed does not depend on them), in the study's precision and layout. The input is
the first test batch of the dataset at the study's size, resized (``nvs.run.size_timing.resized_batch``). What is
timed per row:
    a trained row          its network's forward (every pair through the pixel decoder)
    a routed evaluation    (``route=...``) the evaluated row's network behind each route forced for every pair
    a per-level skips one  (``skips_threshold=...``) the evaluated row's network with adaptive skips in place of its
                           warped ones, every warp done, then each level skipped for every pair
    another evaluation     the evaluated row's network
After two warm-up forwards of each, the forwards are timed round-robin (one of each in turn, ``repeats`` rounds):
load that changes during the pass shifts every row alike. Each time is the median per image.
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

from nvs.core.atomic import write_json
from nvs.core.errors import UserError
from nvs.core.provenance import device_name, git_sha, utc_now
from nvs.sweep.jobs import compose_job, row_overrides
from nvs.sweep.study import Row, Study
from nvs.sweep.timing import VERSION, identity, read_timing, timed_rows, timing_path

WARMUP = 2
SIZES = (256,)  # timed besides the study's own size


def _config(study: Study, row: Row):
    cfg = compose_job("train", [*row_overrides(study, row), "seed=0"])
    cfg.paths.output_dir = "."  # the Hydra run directory: none here, nothing is written
    return cfg


def _mode(cfg) -> tuple[str, bool]:
    """The study's precision and layout as its jobs run them (``auto``: this machine's choice)."""
    precision, layout = cfg.trainer.get("precision", "auto"), cfg.get("channels_last", "auto")
    if str(precision) == "auto" or not isinstance(layout, bool):
        from nvs.run.build import choose_precision

        choice = choose_precision(cfg)
        precision = choice.precision if str(precision) == "auto" else precision
        layout = choice.channels_last if not isinstance(layout, bool) else layout
    return str(precision), bool(layout)


def _forwards(study: Study, row: Row, cfg, size: int, data: dict, channels_last: bool) -> dict[str, Callable]:
    """{part: forward} of one row at one size (see the module docstring)."""
    from nvs.models.route import RoutedNet
    from nvs.run.build import build_module
    from nvs.run.size_timing import FORCED, config_at

    torch.manual_seed(0)
    try:
        module = build_module(config_at(cfg, size), channels_last=channels_last).eval()
    except (UserError, ValueError, RuntimeError, TypeError) as err:
        raise UserError(f"--time: row '{row.name}' cannot be built at {size}x{size} ({err})") from None
    net = module.net
    keys = {o.split("=", 1)[0] for o in row.overrides} if row.evaluates else set()
    if "route" in keys:
        return {f"route:{r}": (lambda routed=RoutedNet(net, FORCED[r]): routed(data)) for r in FORCED}
    if "skips_threshold" in keys:
        from nvs.run.skips_calibration import adaptive_skips

        skips = adaptive_skips(module)

        def forced(levels):
            def forward():
                with skips.levels_forced(levels):
                    return net(data)
            return forward

        return {"level:none": forced(()), **{f"level:{lv}": forced((lv,)) for lv in skips.levels}}
    return {"network": lambda: net(data)}


def _interleaved(forwards: dict[str, Callable], batch_size: int, repeats: int, precision: str,
                 device: torch.device) -> dict[str, float]:
    """Median ms per image of each forward, timed round-robin after ``WARMUP`` untimed calls of each."""
    from nvs.run.size_timing import autocast_for

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    times: dict[str, list[float]] = {k: [] for k in forwards}
    with torch.no_grad(), autocast_for(precision, device):
        for _ in range(WARMUP):
            for f in forwards.values():
                f()
        for _ in range(repeats):
            for k, f in forwards.items():
                sync()
                t0 = time.perf_counter()
                f()
                sync()
                times[k].append(time.perf_counter() - t0)
    return {k: 1000 * statistics.median(v) / batch_size for k, v in times.items()}


def _entry(study: Study, row: Row, ms: dict[str, dict[str, float]]) -> dict:
    """The file's entry of one row from its timed parts per size."""
    entry: dict = {"identity": identity(study, row)}
    parts = ms
    if any(k.startswith("route:") for p in parts.values() for k in p):
        entry["routes"] = {s: {k.split(":", 1)[1]: v for k, v in p.items()} for s, p in parts.items()}
        entry["network"] = {s: p["route:full"] for s, p in parts.items()}
    elif any(k.startswith("level:") for p in parts.values() for k in p):
        entry["levels"] = {s: {k.split(":", 1)[1]: v for k, v in p.items()} for s, p in parts.items()}
        entry["network"] = {s: p["level:none"] for s, p in parts.items()}
    else:
        entry["network"] = {s: p["network"] for s, p in parts.items()}
    return entry


def run_timing(study: Study, results_dir: str | Path, rows: set[str] | None = None, repeats: int = 5,
               log: Callable[[str], None] = lambda text: print(text, file=sys.stderr)) -> Path:
    """Time the study's rows (``rows``: only these names) and write ``results/timing/<stem>.json`` -> its path.
    Entries of rows not timed now are kept from the existing file where it was timed on this device, torch, precision
    and layout; otherwise the file holds only what was timed now."""
    from nvs.run.build import build_data
    from nvs.run.size_timing import resized_batch

    chosen = [r for r in timed_rows(study) if rows is None or r.name in rows]
    if not chosen:
        raise UserError(f"--time: no trained or evaluation row of {study.path} selected")
    by_name = {r.name: r for r in study.rows}
    configs = {r.name: _config(study, by_name[r.evaluates] if r.evaluates else r) for r in chosen}
    precision, channels_last = _mode(next(iter(configs.values())))
    device = torch.device("cpu")
    sizes = sorted({study.size, *SIZES})
    groups: dict[str, list[Row]] = {}
    for r in chosen:
        groups.setdefault(str(configs[r.name].data.name), []).append(r)
    timed: dict[str, dict[str, dict[str, float]]] = {r.name: {} for r in chosen}
    batch_size = None
    for data_name, group in groups.items():
        cfg = configs[group[0].name]
        try:
            batch = next(iter(build_data(cfg).test_dataloader()))
        except (OSError, FileNotFoundError) as err:
            raise UserError(f"--time: the {data_name} test split cannot be read ({err}); render it first") from None
        batch_size = int(batch["src"].shape[0])
        for size in sizes:
            data = {k: v.to(device) if torch.is_tensor(v) else v for k, v in resized_batch(batch, size).items()}
            if channels_last:
                for key in ("src", "tgt"):
                    data[key] = data[key].contiguous(memory_format=torch.channels_last)
            forwards = {}
            for r in group:
                for part, f in _forwards(study, r, configs[r.name], size, data, channels_last).items():
                    forwards[f"{r.name}|{part}"] = f
            log(f"[sweep] --time: {data_name} at {size}x{size}, {len(group)} row(s), {len(forwards)} forward(s)")
            try:
                ms = _interleaved(forwards, batch_size, repeats, precision, device)
            except RuntimeError as err:
                raise UserError(f"--time: a forward at {size}x{size} on {data_name} failed ({err})") from None
            for key, value in ms.items():
                name, part = key.split("|", 1)
                timed[name].setdefault(str(size), {})[part] = value
    header = {"version": VERSION, "study": study.name, "scale": study.scale, "sizes": sizes,
              "device": device_name(device), "torch": torch.__version__, "precision": precision,
              "channels_last": channels_last, "git_sha": git_sha(), "date": utc_now(), "batch": batch_size,
              "repeats": repeats, "warmup": WARMUP}
    path = timing_path(results_dir, study)
    entries = {r.name: _entry(study, r, timed[r.name]) for r in chosen}
    try:
        old = read_timing(path, study)
    except UserError:
        old = None  # replaced: what was there cannot be read as this study's
    same = ("device", "torch", "precision", "channels_last", "sizes", "batch")
    if old is not None and all(old[k] == header[k] for k in same):
        entries = {**{k: v for k, v in old["rows"].items() if k in by_name and k not in entries}, **entries}
    ordered = {r.name: entries[r.name] for r in study.rows if r.name in entries}
    write_json(path, {**header, "rows": ordered})
    return path
