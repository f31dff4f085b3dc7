"""python -m nvs.render_video ckpt_path=... [source=...] path=orbit|forward|custom frames=N fps=F: MP4 and GIF of the
synthesised views along a camera path, the predicted depth beside each view (conf/render_video.yaml)."""

from __future__ import annotations

import os
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from nvs.core.errors import UserError
from nvs.run.artifacts import is_global_zero, remove_unstarted_run
from nvs.run.cli import exits_cleanly, hydra_task
from nvs.run.compose import CONF_DIR
from nvs.viewer.build import build_session, pick_source, source_ids
from nvs.viewer.cloud import file_stem
from nvs.viewer.controls import check_values
from nvs.viewer.paths import camera_path
from nvs.viewer.video import compose_frames, render_views, write_video


def render(cfg: DictConfig) -> list[Path]:
    """Render the video(s) the config asks for; returns the files written."""
    if not isinstance(cfg.fps, (int, float)) or cfg.fps <= 0:
        raise UserError(f"fps={cfg.fps!r}: expected a positive number")
    if not isinstance(cfg.scale, int) or cfg.scale < 1:
        raise UserError(f"scale={cfg.scale!r}: expected a positive integer")
    session, _ = build_session(cfg, source_ids(cfg.source))
    source = pick_source(session, cfg.source)
    poses = camera_path(str(cfg.path), session.controls, source.meta, cfg.frames, cfg.custom)
    for values in poses:  # every pose inside the trained range before the bar starts
        check_values(session.controls.axes, values)
    views = render_views(session, source.key, poses, progress=bool(cfg.progress))
    frames = compose_frames(views, scale=int(cfg.scale))
    name = cfg.name or f"{cfg.path}_{file_stem(source.label)}"
    out_dir = Path(cfg.out_dir) if cfg.out_dir else videos_dir(cfg.ckpt_path)
    return write_video(out_dir / name, frames, float(cfg.fps), list(cfg.formats), int(cfg.gif_colors))


def videos_dir(ckpt_path: str | Path) -> Path:
    """``<run dir>/videos`` for a run's ``checkpoints/<name>.ckpt``; a checkpoint elsewhere: ``videos/`` beside it."""
    ckpt = Path(ckpt_path)
    run_dir = ckpt.parent.parent if ckpt.parent.name == "checkpoints" else ckpt.parent
    return run_dir / "videos"


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="render_video")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    hydra_dir, job = Path(HydraConfig.get().runtime.output_dir), HydraConfig.get().job.name
    try:
        with hydra_task("render_video", cfg):
            written = render(cfg)
    finally:
        # Hydra's own folder holds only its record of the command when the videos went beside the checkpoint (or
        # nothing was written): it goes, rather than a folder per video to clean up by hand.
        own = {".hydra", f"{job}.log"}
        if HydraConfig.get().mode == RunMode.RUN and is_global_zero() and hydra_dir.is_dir() \
                and set(os.listdir(hydra_dir)) <= own:
            remove_unstarted_run(hydra_dir, job)
    for path in written:
        print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KB)")


if __name__ == "__main__":
    main()
