"""python -m nvs.bench [sizes=[64,128,256]] [only=[full]] [modes=[fp32,bf16_cl]] [reference=<authors' checkout>]
                      [profile=[64,256]]

Writes results/bench/<device>.{json,md} (every size in one report), or with ``profile=[...]`` the training-step
profiles results/bench/profile_<device>_<size>.md instead.
"""

from __future__ import annotations

import sys

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from nvs.bench.contenders import MODES
from nvs.bench.goals import profile_shares
import nvs.bench.measure as measure
from nvs.bench.reference import check_path
from nvs.bench.viewer_goal import viewer_reports
from nvs.core.atomic import write_json, write_text
from nvs.core.errors import UserError
from nvs.core.provenance import command_line, device_name, header
from nvs.run.cli import exits_cleanly
from nvs.run.compose import CONF_DIR
from nvs.run.precision import choose, native_bf16_flags


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in name.lower()).strip("-")[:60]


def device_slug(device: torch.device) -> str:
    """The report's file name: the device, and for a CPU its class (native bf16 or not), which decides the modes."""
    name = _slug(device_name(device).split("(")[0])
    if device.type != "cpu":
        return name
    flags = native_bf16_flags()
    return f"{name}-{flags[-1].replace('_', '-') if flags else 'no-native-bf16'}"


def _positive(value, key: str) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
        raise UserError(f"bench.yaml '{key}': expected a positive integer, got {value!r}")
    return value


def plan(cfg: DictConfig) -> tuple[list[tuple[int, int]], dict[str, list[str]]]:
    """-> ([(size, train batch)], {model option: overrides}), every key checked."""
    one = cfg.get("image_size")
    sizes = [_positive(one, "image_size")] if one is not None else [_positive(s, "sizes") for s in cfg.sizes]
    batches = cfg.train_batch
    if OmegaConf.is_list(batches):
        if len(batches) != len(cfg.sizes if one is not None else sizes):
            raise UserError(f"bench.yaml 'train_batch': {len(batches)} batches for sizes {list(cfg.sizes)}: give one "
                            "per size or one number for all")
        if one is not None:  # one of the listed sizes takes its batch there (image_size=128: 128's)
            listed = dict(zip(cfg.sizes, batches))
            if one not in listed:
                raise UserError(f"bench.yaml 'train_batch': image_size={one} is not one of sizes {list(cfg.sizes)}, "
                                "so it has no batch there: give train_batch=<n>")
            batches = [listed[one]]
        batches = list(batches)
    else:
        batches = [batches] * len(sizes)
    pairs = [(s, _positive(b, "train_batch")) for s, b in zip(sizes, batches)]
    for key in ("eval_batch", "repeats"):
        _positive(cfg[key], key)
    if cfg.throughput_batch is not None:
        _positive(cfg.throughput_batch, "throughput_batch")
    unknown_modes = [m for m in cfg.modes if m not in MODES]
    if unknown_modes:
        raise UserError(f"bench.yaml 'modes': unknown {unknown_modes}; choose from {list(MODES)}")
    chosen = list(cfg.only) if cfg.only else list(cfg.models)
    unknown = [m for m in chosen if m not in cfg.models]
    if unknown:
        raise UserError(f"bench.yaml 'only': {unknown} not in its models {list(cfg.models)}")
    return pairs, {m: list(cfg.models[m]) for m in chosen}


def _profiles(cfg: DictConfig, device: torch.device) -> None:
    from nvs.bench.profile import markdown, profile_step

    pairs, _ = plan(cfg)
    batch_at = dict(pairs)
    model = cfg.profile_model
    if model not in cfg.models:
        raise UserError(f"bench.yaml 'profile_model': {model!r} not in its models {list(cfg.models)}")
    for size in cfg.profile:
        size = _positive(size, "profile")
        batch = batch_at.get(size, pairs[0][1])
        print(f"profiling {model} at {size}², batch {batch}, {cfg.profile_mode}", flush=True)
        prof = profile_step(list(cfg.models[model]), cfg.profile_mode, size, batch, device, cfg.paths.root_dir,
                            warmup=cfg.warmup + 1, steps=cfg.repeats)
        head = header(command_line("nvs.bench"), device, threads=torch.get_num_threads())
        # bf16_cl, the first mode profiled, keeps the names of the reports committed before the others
        mode = "" if cfg.profile_mode == "bf16_cl" else f"_{cfg.profile_mode}"
        suffix = ("" if model == "full" else f"_{model}") + mode
        stem = f"{cfg.out_dir}/profile_{device_slug(device)}_{size}{suffix}"
        write_text(f"{stem}.md", markdown(head, prof))
        write_json(f"{stem}.json", {"header": head, "model": model, **{k: v for k, v in prof.items() if k != "ops"},
                                    "ops": prof["ops"][:60]})
        print(f"wrote {stem}.md and .json")


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="bench")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    from nvs.bench.report import markdown
    from nvs.bench.run import bench_size, slow_modes

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if cfg.threads is not None:
        torch.set_num_threads(_positive(cfg.threads, "threads"))
    if cfg.profile:
        return _profiles(cfg, device)
    pairs, models = plan(cfg)
    reference = str(check_path(cfg.reference)) if cfg.reference else None
    head = header(command_line("nvs.bench"), device, iso=True, threads=torch.get_num_threads(),
                  python=sys.version.split()[0], reference=reference or "not timed (reference=<path> times it)",
                  repeats=cfg.repeats, warmup=cfg.warmup)
    name = device_slug(device)
    report = {"header": head, "sizes": [], "profiles": profile_shares(cfg.out_dir, name),
              "viewer": viewer_reports(cfg.out_dir, name)}
    if cfg.measure_peak:
        report["peak"] = measure.machine_peak(device)
        print(f"peak: {report['peak']}", flush=True)
    auto = choose("auto", "auto", device.type)
    print(auto.line(), flush=True)
    modes = list(cfg.modes)
    for size, batch in pairs:
        report["sizes"].append(bench_size(models, modes, size, batch, cfg.eval_batch, cfg.throughput_batch,
                                          cfg.warmup, cfg.repeats, device, cfg.paths.root_dir, reference,
                                          log=lambda msg: print(msg, flush=True)))
        report["sizes"][-1]["auto"] = {"mode": auto.mode, "reason": auto.reason, "probe_ms": auto.probe_ms}
        slow = slow_modes(report["sizes"][-1], cfg.get("drop_slower"))
        if slow:  # an emulated mode at 10x would cost the larger sizes hours and tell nothing new
            report["sizes"][-1]["dropped"] = {"modes": slow, "factor": cfg.drop_slower}
            modes = [m for m in modes if m not in slow]
            print(f"{size}²: {', '.join(slow)} not timed at larger sizes (≥ {cfg.drop_slower}× the fastest mode)")
        write_json(f"{cfg.out_dir}/{name}.json", report)  # after every size: a long run keeps what it measured
        write_text(f"{cfg.out_dir}/{name}.md", markdown(report))
    if cfg.measure_peak:  # once more at the end: the rows' % are of the larger of the two
        report["peak_start"] = report["peak"]
        report["peak"], report["peak_end"] = measure.peak_again(device, report["peak_start"])
        print(f"peak at the end: {report['peak_end']}", flush=True)
        write_json(f"{cfg.out_dir}/{name}.json", report)
        write_text(f"{cfg.out_dir}/{name}.md", markdown(report))
    print(f"wrote {cfg.out_dir}/{name}.json and .md")


if __name__ == "__main__":
    main()
