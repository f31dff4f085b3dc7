"""The model options the precision and training sections build, and their configs (the real train.yaml)."""

from __future__ import annotations

from omegaconf import DictConfig

from nvs.models.reference import REFERENCE_MODELS as NO_TRAINING_MODELS  # evaluated without training: nothing to stress
from nvs.run.compose import CONF_DIR, compose


def train_config(overrides: list[str], work: str) -> DictConfig:
    """conf/train.yaml with ``overrides``, resolved, every path under the scratch directory ``work``."""
    return compose("train", [*overrides, f"paths.root_dir={work}", f"paths.output_dir={work}"], resolve=True)


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def other_models() -> list[tuple[str, list[str]]]:
    """(name, overrides) of every conf/model option but nvs and the reference rows, with its chairs experiment (its
    losses) when there is one."""
    opts = []
    for name in _options("model"):
        if name in NO_TRAINING_MODELS or name == "nvs":
            continue
        exp = f"{name}_chairs"
        opts.append((name, [f"experiment={exp}"] if exp in _options("experiment") else [f"model={name}"]))
    return opts


def model_options() -> list[tuple[str, list[str], str]]:
    """(label, overrides, data kind) for every model option: nvs with each skip and depth option and the scenes'
    disparity head, and every other conf/model option."""
    opts = [(f"nvs, skips={s}", ["model=nvs", f"model/skips={s}"], "objects") for s in _options("model/skips")]
    opts += [(f"nvs, depth={d}", ["model=nvs", f"model/depth={d}"], "objects") for d in _options("model/depth")
             if d != "predicted"]
    opts.append(("nvs, data=drive (disparity head)", ["experiment=nvs_drive"], "scenes"))
    return opts + [(name, ov, "objects") for name, ov in other_models()]
