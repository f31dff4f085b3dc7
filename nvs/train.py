"""python -m nvs.train experiment=<name> [key=value ...]: train, select on validation, evaluate on the test pairs."""

from __future__ import annotations

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from nvs.core.errors import UserError
from nvs.run.artifacts import existing_files, is_global_zero, summary_line
from nvs.run.cli import before_hydra, exits_cleanly, hydra_task
from nvs.run.compose import CONF_DIR
from nvs.run.overrides import trainer_arguments


def main_cli() -> None:
    """``python -m nvs.train``: every Lightning Trainer argument is ``trainer.<arg>=...`` (nvs.run.overrides)."""
    before_hydra("train", check_composes, rewrite=trainer_arguments)
    main()


def check_composes(argv: list[str]) -> None:
    """A single run's overrides compose, or one UserError naming the key (instead of Hydra's exit 1 before main): a
    key the config lacks is refused with its schema's reason (nvs.run.config_check.unknown_override).

    Multiruns and Hydra's own flags (``--cfg``, ``--help``...) are left to Hydra: their overrides are sweeps.
    """
    if any(a.startswith("-") for a in argv):
        return
    from hydra.errors import HydraException

    from nvs.run.compose import compose_raw
    from nvs.run.config_check import unknown_override

    try:
        compose_raw("train", argv)
    except HydraException as err:
        lines = [ln.strip() for ln in str(err).split("Config search path")[0].splitlines() if ln.strip()]
        unknown = unknown_override("train", argv, lines[0] if lines else "")
        if unknown:
            raise unknown from None
        raise UserError(" ".join(lines[:8])) from None


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="train")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    # A run that ends before its first step leaves no directory behind (a multirun job's stays: it is reported).
    keep = HydraConfig.get().mode != RunMode.RUN
    existing = existing_files(out_dir)  # the user's files there (and Hydra's, written before main): never removed
    with hydra_task("train", cfg, existing):
        OmegaConf.resolve(cfg)
    from nvs.run.training import run  # Lightning is imported once the config is known good (seconds on a small CPU)

    result = run(cfg, out_dir, keep_unstarted=keep, existing=existing)
    if not is_global_zero():
        return
    test = result.get("test", {})
    if test:
        print(summary_line(test))
    print(f"run directory: {out_dir}")


if __name__ == "__main__":
    main_cli()
