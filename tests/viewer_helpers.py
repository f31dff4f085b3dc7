"""What the viewer's and the video tools' tests share: an untrained network and a checkpoint trained for one step."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from tests.conftest import compose_train
from tests.run_helpers import train_in_process


def built_net(tmp_path, *overrides: str):
    """The network of the composed training config (default: the full model), seeded, in eval mode."""
    import torch

    from nvs.run.build import build_module

    cfg = compose_train([f"paths.root_dir={tmp_path}", "loss=[recon_final]", *overrides])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    torch.manual_seed(0)
    return build_module(cfg).net.eval()


def one_step_checkpoint(objects_root, out: Path, *overrides: str) -> Path:
    """Train the default model one step on the fixture objects into ``out``; returns ``out/checkpoints/last.ckpt``."""
    train_in_process(objects_root, out, "trainer.max_steps=1", "trainer.val_check_interval=1",
                     "trainer.limit_val_batches=1", "data.loader.batch_size=2", "data.loader.eval_batch_size=2",
                     "loss=[recon]", "test=false", *overrides)
    return out / "checkpoints" / "last.ckpt"
