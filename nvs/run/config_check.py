"""The composed config checked against its typed schema (``nvs.run.config_schema``): a wrong type or an unknown key,
on the command line or in a YAML file, is one UserError naming every such key and where it was set.

OmegaConf validates the config merged into the schema (its structured-config typing: ``int``, ``float``, ``bool``,
``str``, Enums, ``Optional``, lists and mappings, closed dataclasses); each error is one line naming the key, the
type its field declares and the value, and the merge is repeated without that key, so that every problem is listed.
Two things OmegaConf's merge does not do are done here: a string is not read as a number or a bool (OmegaConf
converts ``'yes'`` to true; the config keeps the string), and a component (a mapping with ``_target_``) is checked
against its target's arguments (``nvs.run.component_schema``). Values that are interpolations are checked where
they are written. The config itself is never changed: the run records what Hydra composed.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import enum
import functools
import re
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, ValidationError

from nvs.core.errors import UserError
from nvs.run.component_schema import RESERVED, component_schema
from nvs.run.compose import CONF_DIR, compose_raw, merged_files
from nvs.run.config_schema import SCHEMAS

Problem = tuple[str, str]  # (dotted key, why)
_PART = re.compile(r"([^.\[\]]+)|\[(\d+)\]")


def _parts(key: str) -> list[str | int]:
    return [int(i) if i else name for name, i in _PART.findall(key)]


def _unwrap(kind: Any) -> tuple[Any, bool]:
    """(the type inside Optional, whether null is allowed)."""
    args = typing.get_args(kind)
    if typing.get_origin(kind) is typing.Union and type(None) in args:
        inner = [a for a in args if a is not type(None)]
        return (inner[0] if len(inner) == 1 else Any), True
    return kind, kind is Any


@functools.lru_cache(maxsize=None)  # per schema: a study's plan checks dozens of configs
def _fields(schema: type) -> Mapping[str, Any]:
    return types.MappingProxyType(typing.get_type_hints(schema))


@functools.lru_cache(maxsize=None)
def _structured(schema: type, open_: bool) -> DictConfig:
    base = OmegaConf.structured(schema)  # made once: OmegaConf.merge copies its first argument, never edits it
    if open_:
        OmegaConf.set_struct(base, False)
    return base


def _declared(schema: type, parts: Sequence[str | int]) -> Any:
    """The type the schema declares at ``parts`` (Any below an untyped node; None: no such field)."""
    kind = schema
    for part in parts:
        kind, _ = _unwrap(kind)
        origin = typing.get_origin(kind)
        if dataclasses.is_dataclass(kind):
            kind = _fields(kind).get(part)
            if kind is None:
                return None
        elif origin is list:
            kind = typing.get_args(kind)[0]
        elif origin is dict:
            kind = typing.get_args(kind)[1]
        else:
            return Any
    return kind


def _describe(kind: Any) -> str:
    inner, nullable = _unwrap(kind)
    if inner is bool:
        text = "true or false"
    elif inner is int:
        text = "an integer"
    elif inner is float:
        text = "a number"
    elif inner is str:
        text = "a string"
    elif isinstance(inner, type) and issubclass(inner, enum.Enum):
        text = "one of " + ", ".join(inner.__members__)
    elif typing.get_origin(inner) is list:
        item = typing.get_args(inner)[0]
        text = "a list [...]" + ("" if item is Any else f" of {_describe(item).removeprefix('a ').removeprefix('an ')}s")
    elif typing.get_origin(inner) is dict or dataclasses.is_dataclass(inner):
        text = "a mapping {...}"
    else:
        return "another value"
    return text + (" or null" if nullable and inner is not Any else "")


def _shown(value: Any) -> str:
    return "null" if value is None else repr(value)


def _get(data: Any, parts: Sequence[str | int]) -> Any:
    for part in parts:
        data = data[part]
    return data


def _drop(data: Any, parts: list[str | int]) -> bool:
    """Remove the mapping key at (or holding the list at) ``parts``; False when there is none."""
    while parts and isinstance(parts[-1], int):
        parts = parts[:-1]
    try:
        parent = _get(data, parts[:-1])
        del parent[parts[-1]]
        return True
    except (KeyError, IndexError, TypeError):
        return False


def _is_interpolation(value: Any) -> bool:
    return isinstance(value, str) and "${" in value


def _merge_problems(data: dict, schema: type, prefix: str, open_: bool, unknown: str) -> list[Problem]:
    """Every key of ``data`` OmegaConf refuses to merge into ``schema`` (``open_``: other keys are allowed)."""
    base, out, copied = _structured(schema, open_), [], False
    for _ in range(100):  # one key dropped per round
        try:
            OmegaConf.merge(base, data)
            break
        except (ValidationError, ConfigKeyError) as err:
            if not copied:  # the refused keys are dropped from a copy: the caller's data stays as it was
                data, copied = copy.deepcopy(data), True
            parts = _parts(str(err.full_key))
            if isinstance(err, ConfigKeyError) and not isinstance(err, ValidationError):
                names = list(_fields(_unwrap(_declared(schema, parts[:-1]))[0]))
                hint = difflib.get_close_matches(str(parts[-1]), [n for n in names if n not in RESERVED], n=1)
                parent = prefix + ".".join(str(p) for p in parts[:-1]) + "." if len(parts) > 1 else prefix
                out.append((f"{prefix}{err.full_key}", unknown + (f"; did you mean {parent}{hint[0]}?" if hint else "")))
            else:
                try:
                    value = _get(data, parts)
                except (KeyError, IndexError, TypeError):
                    value = getattr(err, "value", None)
                out.append((f"{prefix}{err.full_key}",
                            f"expected {_describe(_declared(schema, parts))}, got {_shown(value)}"))
            if not _drop(data, parts):
                break
    return out


def _string_problems(data: Any, kind: Any, key: str) -> list[Problem]:
    """Strings where the schema declares a number or a bool (OmegaConf would convert them; the run would not)."""
    inner, _ = _unwrap(kind)
    if isinstance(data, str) and not _is_interpolation(data) and inner in (bool, int, float):
        return [(key, f"expected {_describe(kind)}, got {data!r}")]
    if isinstance(data, Mapping) and (dataclasses.is_dataclass(inner) or typing.get_origin(inner) is dict):
        return [p for k, v in data.items() for p in _string_problems(v, _declared(inner, [k]), f"{key}.{k}".lstrip("."))]
    if isinstance(data, list) and typing.get_origin(inner) is list:
        return [p for i, v in enumerate(data) for p in _string_problems(v, typing.get_args(inner)[0], f"{key}[{i}]")]
    return []


def _nested(value: Any, key: str) -> list[tuple[str, dict]]:
    """The components inside a value (``model.skips``, ``model.depth``, a list of them), with their keys."""
    if isinstance(value, Mapping):
        if "_target_" in value:
            return [(key, value)]
        return [c for k, v in value.items() for c in _nested(v, f"{key}.{k}")]
    if isinstance(value, list):
        return [c for i, v in enumerate(value) for c in _nested(v, f"{key}[{i}]")]
    return []


def component_problems(node: Any, key: str, target: str | None = None, extra: Mapping[str, Any] = {}
                        ) -> list[Problem]:
    """A component checked against its target's arguments (``target``: of this callable, for a node without
    ``_target_``), and the components inside it."""
    if node is None or _is_interpolation(node):
        return []
    target = target or (node.get("_target_") if isinstance(node, Mapping) else None)
    if not isinstance(node, Mapping) or not isinstance(target, str):
        return [(key, f"expected a component (a mapping with _target_), got {_shown(node)}")]
    schema = None if _is_interpolation(target) else component_schema(target, tuple(extra.items()))
    if schema is None:  # an interpolated or unknown _target_: instantiate reports it
        return []
    out = _merge_problems(dict(node), schema.schema, f"{key}.", schema.open, f"not an argument of {target}")
    reported = {k for k, _ in out}
    out += [p for p in _string_problems(node, schema.schema, key) if p[0] not in reported]
    for name, value in node.items():
        if name not in RESERVED:
            out += [p for k, c in _nested(value, f"{key}.{name}") for p in component_problems(c, k)]
    return out


def config_problems(data: Mapping, schema: type) -> list[Problem]:
    """Every (key, why) of a plain config ``data`` (interpolations unresolved) that ``schema`` refuses."""
    out = _merge_problems(dict(data), schema, "", False, "no such key")
    reported = {k for k, _ in out}
    return out + [p for p in _string_problems(data, schema, "") if p[0] not in reported] + _components(data, schema)


def _components(data: Mapping, schema: type, prefix: str = "") -> list[Problem]:
    """The problems of the components in the fields ``component()`` marks, at any depth of ``schema``."""
    out = []
    for field in dataclasses.fields(schema):
        value, key = data.get(field.name), f"{prefix}{field.name}"
        meta = field.metadata.get("component")
        inner, _ = _unwrap(_fields(schema)[field.name])
        if meta and meta["each"]:
            if isinstance(value, Mapping):
                out += [p for k, v in value.items()
                        for p in component_problems(v, f"{key}.{k}", meta["target"], meta["extra"])]
        elif meta and field.name in data:
            out += component_problems(value, key, meta["target"], meta["extra"])
        elif dataclasses.is_dataclass(inner) and isinstance(value, Mapping):
            out += _components(value, inner, f"{key}.")
    return out


def check_config(config_name: str, cfg: DictConfig, overrides: Sequence[str] = ()) -> None:
    """Raise one UserError naming every key of the composed ``cfg`` (of ``conf/<config_name>.yaml``) its schema
    refuses, and where it was set: ``overrides`` (the command line) or the last config file that sets it."""
    schema = SCHEMAS.get(config_name)
    if schema is None:
        return
    data = OmegaConf.to_container(cfg, resolve=False)
    data.pop("hydra", None)
    problems = config_problems(data, schema)
    if problems:
        where = set_where(config_name, overrides, [k for k, _ in problems])
        raise UserError("; ".join(f"config '{k}': {why}{where.get(k, '')}" for k, why in problems))


def unknown_override(config_name: str, argv: Sequence[str], hydra_message: str) -> UserError | None:
    """The error for Hydra's "Could not override 'key'" (``key=v`` on the command line, where the composed config
    has no ``key``): the schema's reason (not an argument of the target, the closest name), or for a key the schema
    takes, how to add it (``+key=v``). None for another message."""
    found = re.match(r"Could not override '([^']+)'", hydra_message.strip())
    if not found:
        return None
    key = found.group(1)
    line = next((a for a in argv if a.split("=", 1)[0] == key), f"{key}=...")
    problems: list[Problem] = []
    try:
        cfg = compose_raw(config_name, [f"+{a}" if a == line else a for a in argv])
        data = OmegaConf.to_container(cfg, resolve=False)
        problems = [p for p in config_problems(data, SCHEMAS[config_name]) if p[0] == key]
    except Exception:  # noqa: BLE001 - not composable even with the key added: Hydra's hint below
        pass
    if problems:
        return UserError("; ".join(f"config '{k}': {why} (on the command line: {line})" for k, why in problems))
    return UserError(f"config '{key}': no such key in conf/{config_name}.yaml (a new key is added with +{line})")


def set_where(config_name: str, overrides: Sequence[str], keys: Sequence[str]) -> dict[str, str]:
    """key -> ' (on the command line: k=v)' or ' (in conf/<file>.yaml)': where each key got its value."""
    try:
        files, assigned = merged_files(config_name, list(overrides))
    except Exception:  # noqa: BLE001 - where a key was set is a courtesy; the error stands without it
        return {}
    out = {}
    for key in keys:
        lines = [line for k, line in assigned if key == k or key.startswith((f"{k}.", f"{k}["))]
        if lines:
            out[key] = f" (on the command line: {lines[-1]})"
            continue
        for config_path, package in reversed(files):
            rel = key if not package else key[len(package) + 1:] if key.startswith(f"{package}.") else None
            if key == package:
                rel = ""
            if rel is not None and _sets(CONF_DIR / f"{config_path}.yaml", rel):
                out[key] = f" (in conf/{config_path}.yaml)"
                break
    return out


def _sets(path: Path, rel: str) -> bool:
    """Whether the YAML file at ``path`` sets the dotted key ``rel`` (relative to its package; '' the whole)."""
    try:
        node: Any = OmegaConf.to_container(OmegaConf.load(path))
    except Exception:  # noqa: BLE001 - a file Hydra read but we cannot: not named
        return False
    if isinstance(node, dict):
        node.pop("defaults", None)
    if not node:
        return False
    for part in [p for p in _parts(rel) if isinstance(p, str)]:
        if not isinstance(node, Mapping) or part not in node:
            return False
        node = node[part]
    return True
