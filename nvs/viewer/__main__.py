"""python -m nvs.viewer ckpt_path=... [data=...] [port=...]: the interactive viewer on 127.0.0.1."""

from __future__ import annotations

import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from nvs.build import build_data, build_module
from nvs.config_check import check_cli_overrides
from nvs.errors import UserError, exits_cleanly
from nvs.evaluate import load_weights, run_config
from nvs.viewer.controls import build_controls
from nvs.viewer.server import build_app, check_address, serve
from nvs.viewer.session import PRECISIONS, Source, ViewSession


def build_session(cfg: DictConfig) -> tuple[ViewSession, dict]:
    """The checkpoint's network, camera and test-split gallery (config stops here); and what the page shows."""
    if not cfg.ckpt_path:
        raise UserError("give ckpt_path=<a trained checkpoint>, e.g. runs/demo/<time>/checkpoints/last.ckpt")
    if cfg.precision not in PRECISIONS:
        raise UserError(f"precision={cfg.precision!r}: expected one of {', '.join(PRECISIONS)}")
    if not isinstance(cfg.gallery, int) or cfg.gallery < 1:
        raise UserError(f"gallery={cfg.gallery!r}: expected a positive number of images")
    run, ckpt = run_config(cfg)
    run.data.loader.with_depth = False  # the viewer shows predicted depth only
    run.loss = {}  # no loss networks (VGG) to build
    datamodule = build_data(run)
    run.model.image_size = run.data.size
    module = build_module(run)
    load_weights(module, ckpt, cfg.ckpt_path)
    test = datamodule.dataset("test")
    controls = build_controls(run.data.format, datamodule)
    ids = list(dict.fromkeys(src for src, _ in test.pairs))
    picked = [ids[i] for i in sorted(set(np.linspace(0, len(ids) - 1, min(cfg.gallery, len(ids))).round().astype(int)))]
    gallery = [Source(f"g{i}", fid, test.cache.get(fid)[0], controls.source_meta(fid)) for i, fid in enumerate(picked)]
    session = ViewSession(module.net, int(run.data.size), test.K, test.pivot, controls, gallery,
                          PRECISIONS[cfg.precision])
    meta = {"model": module.model_name, "data": run.data.get("name"), "checkpoint": cfg.ckpt_path,
            "precision": cfg.precision, "encoder_once": session.splits}
    return session, meta


@hydra.main(version_base="1.3", config_path="../../conf", config_name="viewer")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    check_cli_overrides("viewer", HydraConfig.get().overrides.task)
    check_address(cfg.host, cfg.port)  # before the model loads: a taken port is reported at once
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    session, meta = build_session(cfg)
    first = next(iter(session.gallery.values()))
    session.view(first.key, session.controls.initial(first.meta))  # warm-up: the first page view is not the slowest
    print(f"viewer: model '{meta['model']}' at {session.image_size}², {len(session.gallery)} gallery images, "
          f"{cfg.precision}, {'encoder once per source' if session.splits else 'whole network per view'}", flush=True)
    serve(build_app(session, meta, cfg.threads), cfg.host, cfg.port)


if __name__ == "__main__":
    main()
