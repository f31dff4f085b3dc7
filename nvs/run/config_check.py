"""Type check of command-line overrides against the composed defaults: ``trainer.max_steps=abc`` is one clear error.

Hydra accepts any value for an existing key; a wrong type then surfaces deep inside a library (a DataLoader, the
Trainer) as a traceback. ``check_cli_overrides`` composes the config with the group selections only (``model=chen``,
``loss=[recon]``, ...), so an experiment's own defaults count, and compares each ``key=value`` with the value it
replaces. The rule is by kind, not exact type: a number may replace a number (``val_check_interval`` takes 500 or
0.5), a bool only a bool, a string any scalar (``trainer.precision=16``), a list a list, a mapping a mapping, and
``null`` anything; keys whose default is null, an unresolvable interpolation or absent are not checked.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from nvs.core.errors import UserError
from nvs.run.compose import CONF_DIR
# Keys under these roots belong to Hydra itself (run directory, launcher) and are not ours to check.
_SKIPPED_ROOTS = ("hydra",)


def _kind(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, (int, float)):
        return "number"
    if isinstance(value, str):
        return "string"
    if isinstance(value, (list, tuple, ListConfig)):
        return "list"
    if isinstance(value, (dict, DictConfig)):
        return "mapping"
    return type(value).__name__


_EXPECTED = {"bool": "true or false", "number": "a number", "string": "a scalar", "list": "a list [...]",
             "mapping": "a mapping {...}"}


def _mismatch(default: Any, value: Any) -> str | None:
    """Why ``value`` cannot replace ``default`` (None if it can)."""
    want, got = _kind(default), _kind(value)
    if want == "null" or got == "null":
        return None
    if want == "string":
        return None if got in ("string", "number", "bool") else f"expected {_EXPECTED[want]}"
    if want != got:
        return f"expected {_EXPECTED.get(want, want)}"
    if want == "list" and len(default) and len({_kind(x) for x in default}) == 1:
        for i, item in enumerate(value):
            why = _mismatch(default[0], item)
            if why:
                return f"item {i} ({item!r}): {why}"
    return None


def split_overrides(overrides: Sequence[str], groups: Collection[str]) -> tuple[list[str], list[tuple[str, Any]]]:
    """CLI overrides -> (group selections, kept verbatim for composing; (key, parsed value) assignments to check).

    ``groups`` are the config group names (``model``, ``model/skips``, ``loss``, ...). Additions (``+key``),
    deletions (``~key``), sweeps (``a=1,2``) and Hydra's own keys are neither.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    selections, assignments = [], []
    for line in overrides:
        try:
            (ov,) = parser.parse_overrides([line])
        except HydraException:
            continue  # Hydra reports malformed overrides itself, before any entry point runs
        key = ov.key_or_group
        if key in groups:
            selections.append(line)
        elif ov.is_sweep_override() or ov.is_delete() or ov.is_add() or key.split(".")[0] in _SKIPPED_ROOTS:
            continue
        else:
            assignments.append((key, ov.value()))
    return selections, assignments


def check_types(defaults: DictConfig, assignments: Sequence[tuple[str, Any]]) -> None:
    """Raise one UserError naming every ``key`` whose value is of another kind than its default in ``defaults``."""
    problems = []
    for key, value in assignments:
        try:
            default = OmegaConf.select(defaults, key, throw_on_missing=False)
        except Exception:  # noqa: BLE001 - an interpolation only the running app can resolve: not checked
            continue
        why = _mismatch(default, value)
        if why:
            shown = OmegaConf.to_container(default) if isinstance(default, (DictConfig, ListConfig)) else default
            problems.append(f"config '{key}': {why} (default {shown!r}), got {value!r}")
    if problems:
        raise UserError("; ".join(problems))


def config_groups(conf_dir: str | Path) -> set[str]:
    """Names of the config groups under ``conf_dir``: every folder holding options, as ``model/skips``."""
    conf_dir = Path(conf_dir)
    return {p.relative_to(conf_dir).as_posix() for p in conf_dir.rglob("*") if p.is_dir() and any(p.glob("*.yaml"))}


def check_cli_overrides(config_name: str, overrides: Sequence[str], conf_dir: str | Path = CONF_DIR) -> None:
    """Inside a Hydra app (GlobalHydra initialised): check ``overrides`` (``HydraConfig.get().overrides.task``).

    Raises UserError naming each key with a value of the wrong kind.
    """
    from hydra import compose

    selections, assignments = split_overrides(overrides, config_groups(conf_dir))
    if not assignments:
        return
    check_types(compose(config_name=config_name, overrides=selections), assignments)


def model_mismatch(asked: Mapping, held: Mapping, prefix: str = "model") -> str | None:
    """First difference between the model config a command asks for and the one a checkpoint was trained with.

    ``asked``, ``held``: plain containers (``OmegaConf.to_container``). ``image_size`` follows the checkpoint's data
    and values still holding an interpolation (``${data.depth_head}``) are the data's business; both are skipped.
    Returns 'key: the checkpoint has X, the command asks for Y', or None when they agree.
    """
    for key in sorted(set(asked) | set(held)):
        if key == "image_size":
            continue
        a, h = asked.get(key, "<absent>"), held.get(key, "<absent>")
        if isinstance(a, str) and "${" in a:
            continue
        if isinstance(a, Mapping) and isinstance(h, Mapping):
            inner = model_mismatch(a, h, f"{prefix}.{key}")
            if inner:
                return inner
        elif a != h:
            return f"{prefix}.{key}: the checkpoint has {h!r}, the command asks for {a!r}"
    return None


def hydra_value(value: str) -> str:
    """``value`` written for the right-hand side of a Hydra override: as is where Hydra's grammar reads it back
    unchanged, else single-quoted (a path with spaces, non-ASCII letters or quotes: the bare form fails to parse)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    try:
        if parser.parse_overrides([f"k={value}"])[0].value() == value:
            return value
    except HydraException:
        pass
    # Inside quotes a run of backslashes is literal unless it precedes a quote: there each one is doubled.
    body = re.sub(r"(\\*)'", lambda m: m[1] * 2 + "\\'", value)
    body = re.sub(r"(\\+)$", lambda m: m[1] * 2, body)
    return f"'{body}'"


# Trainer arguments that conf/trainer/default.yaml leaves at Lightning's default are still ``trainer.<arg>=...``
_TRAINER_ARG = re.compile(r"^trainer\.(\w+)=")


def trainer_arguments(argv: Sequence[str], conf_dir: str | Path = CONF_DIR) -> list[str]:
    """Command-line arguments with ``trainer.<arg>=v`` for a Lightning Trainer argument that conf/trainer does not
    list rewritten to ``++trainer.<arg>=v``, so every Trainer argument is set without '+'. A ``trainer.<key>`` that
    is no Trainer argument is a UserError naming the closest one (instead of Hydra's hint to append it)."""
    import inspect

    import lightning as L

    listed = set(OmegaConf.load(Path(conf_dir) / "trainer" / "default.yaml"))
    known = set(inspect.signature(L.Trainer.__init__).parameters) - {"self", "logger", "callbacks"}
    out = []
    for arg in argv:
        m = _TRAINER_ARG.match(arg)
        if m and m.group(1) not in listed:
            name = m.group(1)
            if name not in known:
                hint = difflib.get_close_matches(name, known | listed, n=1)
                raise UserError(f"config 'trainer.{name}': not an argument of lightning.Trainer"
                                + (f"; did you mean trainer.{hint[0]}?" if hint else ""))
            arg = "++" + arg
        out.append(arg)
    return out
