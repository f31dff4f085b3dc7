"""python -m nvs.evaluate ckpt_path=... [data=...]: test metrics (metrics.json) and per-image CSV of a checkpoint.

Reference models that need no training are evaluated without a checkpoint: ``model=copy_source``, ``gt_warp``,
``mean_depth`` or ``gt_plane`` (nvs.models.reference.REFERENCE_MODELS).

Skipping at inference (docs/skipping.md): ``route=fit`` or ``route=<route_rule.json>`` routes each pair to copy, warp
or the full decoder (``nvs.run.routing``); ``skips_threshold=calibrate`` picks the adaptive skips' threshold on the
validation pairs (``nvs.run.skips_calibration``). ``time_sizes=[64,256]`` adds the forward time per image at those
sizes (and per route) to metrics.json (``nvs.run.size_timing``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from nvs.core.errors import UserError, user_message
from nvs.run.artifacts import (check_writable, is_global_zero, run_record, summary_line, test_record,
                               write_run_results)
from nvs.run.cli import before_hydra, exits_cleanly, hydra_task
from nvs.run.compose import CONF_DIR

if TYPE_CHECKING:
    from nvs.run.precision import Choice
    from nvs.run.standard_callbacks import SignalStop


def evaluate(cfg: DictConfig, out_dir: Path) -> dict:
    """Test the checkpoint (or reference model) of ``cfg``; write metrics.json and test_per_image.csv into
    ``out_dir``, both when it completes (SIGINT/SIGTERM before that: :class:`Interrupted`, nothing written)."""
    from nvs.run.standard_callbacks import SignalStop  # Lightning, torch: loaded once the config is known good

    stop = SignalStop()
    stop.install()
    try:
        return _evaluate(cfg, out_dir, stop)
    finally:
        stop.restore()


def _evaluate(cfg: DictConfig, out_dir: Path, stop: SignalStop) -> dict:
    import lightning as L

    from nvs.core.types import ROUTES
    from nvs.run.build import build_data
    from nvs.run.checkpoints import restore_module, restore_run_config
    from nvs.run.display_callbacks import PairTestBar
    from nvs.run.inference_skipping import skip_at_inference
    from nvs.run.quiet import silence_known_noise
    from nvs.run.routing import RULE_FILE, route_option, write_rule
    from nvs.run.size_timing import sizes_option, timing_by_size
    from nvs.run.skips_calibration import threshold_option
    from nvs.run.validation_pass import Calibration

    silence_known_noise()  # again, now that Lightning is loaded (its console handler)
    limit = cfg.get("limit")
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int) or limit < 1):
        raise UserError(f"limit={limit}: expected a positive number of test pairs (limit=null: all of them)")
    route, threshold = route_option(cfg.get("route")), threshold_option(cfg.get("skips_threshold"))
    settings = Calibration.from_config(cfg.get("calibration"))
    sizes, repeats = sizes_option(cfg.get("time_sizes"), cfg.get("time_repeats", 5))
    run, ckpt = restore_run_config(cfg)
    asked = _size_override()
    if ckpt is not None and asked is not None and asked != str(run.data.size):
        raise UserError(f"data.size={asked}: {cfg.ckpt_path} was trained at {run.data.size}x{run.data.size} and is "
                        "evaluated at that size; drop data.size")
    if ckpt is None and (route or threshold is not None or sizes):
        raise UserError("route / skips_threshold / time_sizes act on a trained network: give ckpt_path=...")
    L.seed_everything(int(run.seed), workers=True)
    datamodule = build_data(run)
    datamodule.validate(("test",))
    choice = evaluation_precision(cfg, run)
    module = restore_module(run, ckpt, channels_last=choice.channels_last)
    precision = choice.precision
    if is_global_zero():
        print(choice.line(), flush=True)
    if is_global_zero():
        check_writable(out_dir)
    placement = OmegaConf.to_container(cfg.trainer) if cfg.get("trainer") else {}
    # skipping at inference (off by default): metrics.json's extra entries, and a rule fitted here to write
    extra, rule_file = skip_at_inference(module, datamodule, ckpt, route, threshold, settings, placement, precision)
    try:
        # the test bar counts test pairs, with elapsed time and ETA (+trainer.enable_progress_bar=false: none)
        trainer_args = {"enable_progress_bar": True, **placement}
        bar = [PairTestBar()] if trainer_args["enable_progress_bar"] else []
        trainer = L.Trainer(**trainer_args, callbacks=[stop, *bar], precision=precision, logger=False,
                            enable_model_summary=False)
    except Exception as err:  # noqa: BLE001 - a placement the Trainer refuses (devices, strategy) is the user's
        raise UserError(f"config 'trainer': {user_message(err) or f'{err.__class__.__name__}: {err}'}") from None
    t0 = time.perf_counter()
    trainer.test(module, datamodule=datamodule, verbose=False)
    elapsed = time.perf_counter() - t0
    tested = f"checkpoint {cfg.ckpt_path}" if cfg.ckpt_path else "a reference model (nothing trained)"
    result = {**run_record(module, run, choice), **test_record(module, elapsed, cfg.ckpt_path, tested), **extra}
    if sizes:  # after the test: a routed network's times are mixed at the test pairs' route shares
        summary = module.test_summary()
        shares = {r: summary[f"route_share_{r}"] for r in ROUTES} if route else None
        batch = next(iter(datamodule.test_dataloader()))
        result["timing_by_size"] = timing_by_size(module, run, batch, sizes, repeats, precision, shares)
    if trainer.is_global_zero:  # the rows are gathered from every rank: one writer
        if rule_file is not None:
            write_rule(out_dir / RULE_FILE, rule_file)
        write_run_results(out_dir, result, module.test_rows)
    return result


def _size_override() -> str | None:
    """The value of a ``data.size=`` / ``+data.size=`` given on the command line (None: not given)."""
    if not HydraConfig.initialized():
        return None
    for line in HydraConfig.get().overrides.task:
        key, _, value = line.partition("=")
        if key.lstrip("+") == "data.size":
            return value
    return None


def check_composes(argv: list[str]) -> None:
    """The overrides compose with conf/evaluate.yaml, or one UserError (instead of Hydra's lines and exit 1)."""
    if any(a.startswith("-") for a in argv):  # Hydra's own flags and multiruns: Hydra's business
        return
    from hydra.errors import HydraException

    from nvs.run.compose import compose_raw
    from nvs.run.config_check import unknown_override

    try:
        compose_raw("evaluate", argv)
    except HydraException as err:
        from nvs.models.reference import REFERENCE_MODELS  # torch: only to word this error

        given = dict(a.lstrip("+").split("=", 1) for a in argv if "=" in a)
        text = str(err).split("Config search path")[0]
        if "'data.size'" in text:
            raise UserError(f"data.size={given.get('data.size')}: "
                            + ("a checkpoint is evaluated at the size it was trained at; drop data.size"
                               if given.get("ckpt_path") else "choose a dataset first (data=<name> data.size=...)")
                            ) from None
        if text.startswith("In 'model/") and given.get("model") not in REFERENCE_MODELS:
            raise UserError(f"model={given.get('model')}: nvs.evaluate builds only the reference models from model= "
                            f"({'|'.join(REFERENCE_MODELS)}); a trained model comes from its checkpoint "
                            "(ckpt_path=...)") from None
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        unknown = unknown_override("evaluate", argv, lines[0] if lines else "")
        if unknown:
            raise unknown from None
        raise UserError(" ".join(lines[:4]) or err.__class__.__name__) from None


def evaluation_precision(cfg: DictConfig, run: DictConfig) -> Choice:
    """``precision=auto``: measured on this machine; null: the run's own (precision and layout); else as given.
    A reference model (no checkpoint) always runs its own (32-true)."""
    from nvs.run.precision import choose

    accelerator = (cfg.get("trainer") or {}).get("accelerator", "auto")
    try:
        # a reference model has no network worth speeding up: it keeps its exact fp32 (as committed jobs ran it)
        if cfg.get("precision") is None or not cfg.get("ckpt_path"):
            return choose(run.trainer.get("precision", "32-true"), run.get("channels_last", "auto"), accelerator)
        return choose(cfg.precision, "auto", accelerator)
    except ValueError as err:
        raise UserError(f"precision={cfg.precision}: {err}") from None


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="evaluate")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    # a failed evaluation leaves no run directory behind (a multirun job's stays: it is reported at the end)
    with hydra_task("evaluate", cfg):
        out_dir = Path(cfg.out_dir)
        result = evaluate(cfg, out_dir)
    if not is_global_zero():
        return
    from nvs.run.routing import RULE_FILE

    print(summary_line(result["test"]))
    print(f"wrote {out_dir / 'metrics.json'} and {out_dir / 'test_per_image.csv'}"
          + (f" and {out_dir / RULE_FILE}" if cfg.get("route") == "fit" else ""))


def main_cli() -> None:
    before_hydra("evaluate", check_composes)
    main()


if __name__ == "__main__":
    main_cli()
