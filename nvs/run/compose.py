"""The project's config directory and the one way a tool composes a config outside a Hydra run."""

from __future__ import annotations

import contextlib
import copy
from pathlib import Path

from omegaconf import DictConfig

import nvs

# nvs/conf: in a checkout a link to the top-level conf/, in an installed package the copy its wheel ships (found from
# the package, wherever this module sits in it); resolved so that a checkout's CONF_DIR.parent is the repository.
CONF_DIR = (Path(nvs.__file__).resolve().parent / "conf").resolve()


@contextlib.contextmanager
def _hydra_at_conf_dir():
    """Hydra's global state initialised at CONF_DIR for the block; an outer app's state is saved and restored."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    outer = GlobalHydra.instance().is_initialized()
    if outer:
        saved = GlobalHydra.instance().hydra
        GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            yield GlobalHydra.instance()
    finally:
        if outer:
            GlobalHydra.instance().clear()
            GlobalHydra.instance().initialize(saved)


# Composed configs of this process, keyed by the config, the overrides and the state of every file under CONF_DIR:
# one study's plan composes a dozen rows, the same rows recur across studies, and each composition costs 0.2-0.5 s.
_COMPOSED: dict[tuple, DictConfig] = {}
_COMPOSED_MAX = 256


def _conf_state() -> tuple:
    """Each config file's path, size and mtime: an edited, added or removed file is a different key."""
    return tuple(sorted((str(p.relative_to(CONF_DIR)), st.st_size, st.st_mtime_ns)
                        for p in CONF_DIR.rglob("*.yaml") for st in (p.stat(),)))


def compose_raw(config_name: str, overrides: list[str] | tuple[str, ...] = ()) -> DictConfig:
    """As :func:`compose`, but Hydra's own exception propagates (for callers that word the error themselves).

    A composition is kept for the process and handed out as a deep copy, so a caller that edits its config changes
    no other caller's; a failing composition is not kept (it raises each time).
    """
    from hydra import compose as hydra_compose

    overrides = [str(o) for o in overrides]
    key = (config_name, tuple(overrides), _conf_state())
    if key not in _COMPOSED:
        with _hydra_at_conf_dir():
            cfg = hydra_compose(config_name=config_name, overrides=overrides)
        if len(_COMPOSED) >= _COMPOSED_MAX:
            _COMPOSED.pop(next(iter(_COMPOSED)))
        _COMPOSED[key] = cfg
    return copy.deepcopy(_COMPOSED[key])


def merged_files(config_name: str, overrides: list[str] | tuple[str, ...] = ()
                 ) -> tuple[list[tuple[str, str]], list[tuple[str, str]]]:
    """What Hydra merges for ``conf/<config_name>.yaml`` with ``overrides``: the config files in merge order as
    (path under conf/ without .yaml, package: where its keys land, '' for the root), Hydra's own left out, and the
    overrides that set a key rather than choose a group option, as (key, the override as written)."""
    from hydra.types import RunMode

    with _hydra_at_conf_dir() as gh:
        found = gh.config_loader().compute_defaults_list(config_name, [str(o) for o in overrides], RunMode.RUN)
    files = [(d.config_path, d.package or "") for d in found.defaults
             if d.config_path and not (d.package or "").startswith("hydra") and not d.config_path.startswith("hydra/")]
    assigned = [(o.key_or_group, o.input_line) for o in found.overrides.config_overrides
                if not o.is_sweep_override()]
    return files, assigned


def compose(config_name: str, overrides: list[str] | tuple[str, ...] = (), resolve: bool = False) -> DictConfig:
    """``conf/<config_name>.yaml`` with ``overrides`` as Hydra composes it (the hydra node excluded).

    Works inside another Hydra app (a ``@hydra.main`` tool, a test): the outer global state is saved and restored.
    A composition error is one ``UserError`` naming the overrides.
    """
    from omegaconf import OmegaConf

    from nvs.core.errors import UserError

    try:
        cfg = compose_raw(config_name, overrides)
    except Exception as err:  # noqa: BLE001 - a composition error is a problem in the caller's overrides
        raise UserError(f"conf/{config_name}.yaml with overrides {[str(o) for o in overrides]} does not compose: "
                        f"{str(err).splitlines()[0]}") from None
    if resolve:
        OmegaConf.resolve(cfg)
    return cfg
