"""python -m nvs.export_ply ckpt_path=... [source=...] ['pose={azimuth:20,elevation:10}']: the predicted depth of a
synthesised view as a coloured point cloud (binary PLY; conf/export_ply.yaml, conventions in nvs/report/pointcloud.py)."""

from __future__ import annotations

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from nvs.core.errors import UserError
from nvs.report.pointcloud import write_ply
from nvs.run.cli import exits_cleanly, hydra_task
from nvs.run.compose import CONF_DIR
from nvs.viewer.build import build_session, pick_source, source_ids
from nvs.viewer.cloud import file_stem, view_points


def export(cfg: DictConfig) -> Path:
    session, _ = build_session(cfg, source_ids(cfg.source))
    source = pick_source(session, cfg.source)
    pose = OmegaConf.to_container(cfg.pose) if cfg.pose else {}
    if not isinstance(pose, dict):
        raise UserError(f"pose={pose!r}: expected a mapping of control values, e.g. 'pose={{azimuth:20,elevation:10}}'")
    names = [ax.name for ax in session.controls.axes]
    unknown = sorted(set(pose) - set(names))
    if unknown:
        raise UserError(f"pose: unknown control(s) {', '.join(unknown)}; this model's are {', '.join(names)}")
    values = {**session.controls.initial(source.meta), **{k: float(v) for k, v in pose.items()}}
    xyz, rgb, comments = view_points(session, source.key, values, cfg.max_depth, bool(cfg.keep_background))
    out = Path(cfg.out) if cfg.out else Path(HydraConfig.get().runtime.output_dir) / f"{file_stem(source.label)}.ply"
    return write_ply(out, xyz, rgb, comments)


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="export_ply")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    with hydra_task("export_ply", cfg):
        out = export(cfg)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
