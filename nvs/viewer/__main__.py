"""python -m nvs.viewer ckpt_path=... [data=...] [port=...]: the interactive viewer on 127.0.0.1."""

from __future__ import annotations

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from nvs.run.cli import exits_cleanly
from nvs.run.compose import CONF_DIR
from nvs.run.config_check import check_config
from nvs.viewer.address import check_address


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="viewer")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    check_config("viewer", cfg, HydraConfig.get().overrides.task)
    check_address(cfg.host, cfg.port)  # before torch, Lightning and the model load: a taken port is said at once
    import torch

    from nvs.run.quiet import silence_known_noise
    from nvs.viewer.build import build_session
    from nvs.viewer.server import build_app, serve

    silence_known_noise()
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    session, meta = build_session(cfg)
    first = next(iter(session.gallery.values()))
    if session.compiled:
        print("viewer: compile=true: compiling the pose step (once; minutes on a small CPU)", flush=True)
    session.view(first.key, session.controls.initial(first.meta))  # warm-up: the first page view is not the slowest
    meta["compiled"] = session.compiled  # False again if the compile failed
    meta["pose_gflop"] = session.pose_gflop(first.key)
    print(f"viewer: model '{meta['model']}' at {session.image_size}², {len(session.gallery)} gallery images, "
          f"{meta['precision_choice']}, {'encoder once per source' if session.splits else 'whole network per view'}"
          f"{', pose step compiled' if session.compiled else ''}", flush=True)
    serve(build_app(session, meta, cfg.threads), cfg.host, cfg.port)


if __name__ == "__main__":
    main()
