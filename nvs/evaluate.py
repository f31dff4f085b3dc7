"""python -m nvs.evaluate ckpt_path=... [data=...]: test metrics (metrics.json) and per-image CSV of a checkpoint.

Reference models that need no training are evaluated without a checkpoint: ``model=copy_source`` or ``model=gt_warp``.
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from nvs.build import build_data, build_module, device_name, git_sha, parameter_count
from nvs.config_check import check_cli_overrides, model_mismatch
from nvs.errors import UserError, exits_cleanly, user_message
from nvs.module import NVSModule
from nvs.quiet import silence_known_noise
from nvs.run_files import (check_creatable, check_writable, is_global_zero, remove_unstarted_run, run_dir_of,
                           summary_line, write_metrics, write_per_image)


def load_checkpoint(path: str) -> dict:
    p = Path(path)
    if not p.is_file():
        raise UserError(f"ckpt_path={path}: no such checkpoint")
    try:
        ckpt = torch.load(p, map_location="cpu", weights_only=False)
    except Exception as err:  # noqa: BLE001 - any unpickling failure is a bad file for the user
        raise UserError(f"{path}: not a readable checkpoint ({err.__class__.__name__}: {err})") from None
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or not ckpt.get("nvs_config"):
        raise UserError(f"{path}: not an nvs checkpoint (no state_dict / nvs_config)")
    return ckpt


def load_weights(module: NVSModule, ckpt: dict, path: str) -> None:
    """Load a checkpoint's weights into a module built from its config; any mismatch is one clear error."""
    name = module.model_name
    try:
        missing, unexpected = module.load_state_dict(ckpt["state_dict"], strict=False)
    except RuntimeError as err:  # weights of another shape: name the first one
        lines = [ln.strip() for ln in str(err).splitlines() if "size mismatch" in ln] or [str(err)]
        raise UserError(f"{path} does not fit model '{name}': {lines[0]}") from None
    if missing or unexpected:
        raise UserError(f"{path} does not fit model '{name}': {len(missing)} missing and {len(unexpected)} "
                        f"unexpected weights (e.g. {(missing or unexpected)[0]})")


def run_config(cfg: DictConfig) -> tuple[DictConfig, dict | None]:
    """The configuration to evaluate: the checkpoint's own, with data (and size) from the CLI when given."""
    ckpt = None
    if cfg.ckpt_path:
        ckpt = load_checkpoint(cfg.ckpt_path)
        run = OmegaConf.create(ckpt["nvs_config"])
        if cfg.get("model") is not None and cfg.model.get("name") != run.model.get("name"):
            raise UserError(f"{cfg.ckpt_path} holds model '{run.model.get('name')}', not '{cfg.model.get('name')}'")
        if cfg.get("model") is not None:
            diff = model_mismatch(OmegaConf.to_container(cfg.model, resolve=False),
                                  OmegaConf.to_container(run.model, resolve=False))
            if diff:
                raise UserError(f"{cfg.ckpt_path} holds another option of model '{run.model.get('name')}': {diff}")
    elif cfg.get("model") is not None:
        # A reference model trains nothing; the module still takes an optimiser factory (never called).
        run = OmegaConf.create({"model": OmegaConf.to_container(cfg.model), "loss": {},
                                "optim": {"_target_": "torch.optim.SGD", "_partial_": True, "lr": 0.0},
                                "nonfinite": "stop", "channels_last": False, "trainer": {"precision": "32-true"}})
    else:
        raise UserError("give ckpt_path=... (a trained model) or model=copy_source|gt_warp (no training)")
    data_cli = cfg.get("data") or {}
    if data_cli.get("format") is not None:  # a data=<name> group: that dataset config
        data = OmegaConf.to_container(cfg.data, resolve=False)
        if "data" in run:
            data["size"] = run.data.size  # the network is built for the size it was trained at
        run.data = data
    elif "data" not in run:
        raise UserError("give data=<chairs|cars|drive|...> for a model without a checkpoint")
    elif data_cli.get("root") is not None:  # data.root=<dir> alone: the checkpoint's dataset, read from there
        run.data.root = str(data_cli.root)
    run.seed = int(cfg.seed)
    run.paths = OmegaConf.to_container(cfg.paths, resolve=True)
    if cfg.get("limit"):
        run.data.loader.limit_test_pairs = int(cfg.limit)
    OmegaConf.resolve(run)
    return run, ckpt


def evaluate(cfg: DictConfig, out_dir: Path) -> dict:
    run, ckpt = run_config(cfg)
    L.seed_everything(int(run.seed), workers=True)
    datamodule = build_data(run)
    datamodule.validate(("test",))
    run.model.image_size = run.data.size
    module = build_module(run)
    if ckpt is not None:
        load_weights(module, ckpt, cfg.ckpt_path)
    precision = cfg.precision or run.trainer.get("precision", "32-true")
    if is_global_zero():
        check_writable(out_dir)
    placement = OmegaConf.to_container(cfg.trainer) if cfg.get("trainer") else {}
    try:
        # Lightning's test bar: batches of test pairs, elapsed and ETA (+trainer.enable_progress_bar=false: none)
        trainer = L.Trainer(**{"enable_progress_bar": True, **placement}, precision=precision, logger=False,
                            enable_model_summary=False)
    except Exception as err:  # noqa: BLE001 - a placement the Trainer refuses (devices, strategy) is the user's
        raise UserError(f"config 'trainer': {user_message(err) or f'{err.__class__.__name__}: {err}'}") from None
    t0 = time.perf_counter()
    trainer.test(module, datamodule=datamodule, verbose=False)
    elapsed = time.perf_counter() - t0
    result = {
        "model": run.model.get("name"),
        "data": run.data.get("name"),
        "image_size": run.data.size,
        "checkpoint": cfg.ckpt_path,
        "seed": int(run.seed),
        "params": parameter_count(module.net),
        "device": device_name(module.device),
        "precision": str(precision),
        "git_sha": git_sha(),
        "eval_ms_per_image": 1000 * elapsed / max(len(module.test_rows), 1),
        "eval_forward_ms_per_image": module.test_forward_ms_per_image(),
        "test": module.test_summary(),
    }
    if trainer.is_global_zero:  # the rows are gathered from every rank: one writer
        write_per_image(out_dir / "test_per_image.csv", module.test_rows)
        write_metrics(out_dir / "metrics.json", result)
    return result


@hydra.main(version_base="1.3", config_path="../conf", config_name="evaluate")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        check_cli_overrides("evaluate", HydraConfig.get().overrides.task)
        silence_known_noise()
        out_dir = Path(cfg.out_dir)
        result = evaluate(cfg, out_dir)
    except BaseException:
        # A failed evaluation leaves no run directory behind (a multirun job's stays: it is reported at the end).
        if HydraConfig.get().mode == RunMode.RUN and is_global_zero():
            remove_unstarted_run(run_dir, HydraConfig.get().job.name)
        raise
    if not is_global_zero():
        return
    print(summary_line(result["test"]))
    print(f"wrote {out_dir / 'metrics.json'} and {out_dir / 'test_per_image.csv'}")


def main_cli() -> None:
    import sys

    try:
        check_creatable(run_dir_of(sys.argv[1:], "evaluate"))  # Hydra creates it before main(), with a traceback
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    main()


if __name__ == "__main__":
    main_cli()
