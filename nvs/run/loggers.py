"""What every logger of a run receives beyond the scalars: the resolved config as hyperparameters, and a quiet W&B.

``log_run_config`` gives each logger the run's resolved config (CSV and TensorBoard: ``hparams.yaml``; TensorBoard
also its HPARAMS tab; W&B: the run's config keys). ``QuietWandbLogger`` is Lightning's W&B logger without W&B's
terminal banner and sync lines (their ANSI codes end up in log files) and without the deprecated ``anonymous``
setting Lightning passes on (one warning per run).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lightning.pytorch.loggers import TensorBoardLogger, WandbLogger
from omegaconf import DictConfig, OmegaConf

from nvs.core.atomic import WriteFailed

# metric names TensorBoard's HPARAMS tab shows beside the config (their values come from the logged scalars)
HPARAM_METRICS = ("val/l1", "val/ssim_paper", "test/l1", "test/ssim_paper", "test/psnr", "test/lpips")


def flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dicts -> {'a/b/c': leaf}; a list stays one leaf."""
    if not isinstance(tree, dict):
        return {prefix: tree}
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        flat.update(flatten(value, f"{prefix}/{key}" if prefix else str(key)))
    return flat


def run_config(cfg: DictConfig) -> dict:
    """The run's config as plain containers, interpolations resolved (left as written where one cannot resolve
    outside a Hydra run, e.g. ``${hydra:...}`` in a test)."""
    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except Exception:  # noqa: BLE001 - an unresolvable interpolation is logged as its text
        return OmegaConf.to_container(cfg, resolve=False)


def log_run_config(loggers: list, cfg: DictConfig) -> None:
    """Each logger's hyperparameters are the resolved run config (rank zero only: the loggers' methods are)."""
    params = run_config(cfg)
    for logger in loggers:
        try:
            logger.log_hyperparams(params)
            if isinstance(logger, TensorBoardLogger):
                _tensorboard_hparams(logger, params)
        except OSError as err:  # a full disk: one line naming where, not Lightning's traceback
            where = getattr(logger, "log_dir", None) or getattr(logger, "save_dir", None) or "."
            raise WriteFailed(Path(where) / "hparams.yaml", err) from None


def _tensorboard_hparams(logger: TensorBoardLogger, params: dict) -> None:
    # Lightning writes the HPARAMS summary only together with a metric value it logs at step 0 (a fake point on the
    # curves); the summary alone names the metrics, whose values TensorBoard takes from the scalars.
    from torch.utils.tensorboard.summary import hparams

    flat = {k: (v if isinstance(v, (bool, int, float, str)) else str(v)) for k, v in flatten(params).items()}
    writer = logger.experiment._get_file_writer()
    for summary in hparams(flat, dict.fromkeys(HPARAM_METRICS, 0.0)):
        writer.add_summary(summary)


class QuietWandbLogger(WandbLogger):
    """Lightning's ``WandbLogger`` that prints nothing of W&B's own (banner, sync hints) and sets no ``anonymous``.

    Takes ``WandbLogger``'s arguments; an explicit ``settings=`` is used as given.
    """

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self._wandb_init.pop("anonymous", None)
        if "settings" not in self._wandb_init:
            import wandb

            self._wandb_init["settings"] = wandb.Settings(silent=True)
