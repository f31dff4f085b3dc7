"""Typed schemas for YAML files: a frozen dataclass built from a mapping, every problem one error with file, line, key.

``build(cls, raw, source)`` checks each key of ``raw`` against the fields of dataclass ``cls`` (nested dataclasses,
``tuple[X, ...]``, ``dict[str, X]``, ``Literal[...]``, ``X | None``, ``Any``, ``bool``/``int``/``float``/``str``):
an unknown key, a missing required key or a value of the wrong type is one ``UserError`` such as
``sweeps/x.yaml:14: rows[2]: unknown key 'colour'; expected one of [...]``. A null value means the field's default.
Booleans are YAML's true/false only (the string ``"yes"`` is not one), integers are not booleans.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, Literal, Union

import yaml

from nvs.core.errors import UserError

Loc = tuple  # a key path: ("rows", 2, "paper", "l1")


def dotted(loc: Loc) -> str:
    """("rows", 2, "paper", "l1") -> 'rows[2].paper.l1'."""
    out = ""
    for k in loc:
        out += f"[{k}]" if isinstance(k, int) else (f".{k}" if out else str(k))
    return out


class Source:
    """A YAML file: its name in messages and the line of every key path in it."""

    def __init__(self, path: str | Path, text: str | None = None):
        self.path = Path(path)
        self.lines: dict[Loc, int] = {}
        try:
            self._walk(yaml.compose(self.path.read_text() if text is None else text), ())
        except (OSError, yaml.YAMLError):
            pass  # no line numbers; the loader reports the unreadable file itself

    def _walk(self, node, loc: Loc) -> None:
        if isinstance(node, yaml.MappingNode):
            for key, value in node.value:
                child = (*loc, key.value)
                self.lines[child] = key.start_mark.line + 1
                self._walk(value, child)
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                self.lines[(*loc, i)] = item.start_mark.line + 1
                self._walk(item, (*loc, i))

    def where(self, loc: Loc = (), line_of: Loc | None = None) -> str:
        """``file:line: key.path`` (the line of ``line_of``, default ``loc``; the file alone for the top level)."""
        line = self.lines.get(loc if line_of is None else line_of)
        head = f"{self.path}:{line}" if line else str(self.path)
        return f"{head}: {dotted(loc)}" if loc else head


def _type_text(tp) -> str:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is bool:
        return "true or false"
    if tp in (int, float, str):
        return {int: "an integer", float: "a number", str: "a string"}[tp]
    if origin is Literal:
        return f"one of {list(args)}"
    if origin in (tuple, dict):
        item = _type_text(args[0] if origin is tuple else args[1]).removeprefix("an ").removeprefix("a ")
        return f"a {'list' if origin is tuple else 'mapping'} of {item}s"
    if origin in (Union, types.UnionType):
        return " or ".join("null" if a is type(None) else _type_text(a) for a in args)
    if dataclasses.is_dataclass(tp):
        return f"a mapping ({', '.join(f.name for f in dataclasses.fields(tp))})"
    return str(tp)


class _Mismatch(Exception):
    pass


def _scalar(tp, value):
    if tp is bool and isinstance(value, bool):
        return value
    if tp in (int, float) and isinstance(value, (int, float)) and not isinstance(value, bool):
        if tp is float:
            return float(value)
        if isinstance(value, int):
            return value
    if tp is str and isinstance(value, str):
        return value
    raise _Mismatch


def _convert(tp, value, source: Source, loc: Loc):
    """``value`` as type ``tp``; _Mismatch when it is not one (a UserError for a problem deeper inside)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any:
        return value
    if tp is type(None) or origin is Literal:
        if value in ((None,) if tp is type(None) else args):
            return value
        raise _Mismatch
    if origin in (Union, types.UnionType):
        for a in args:
            try:
                return _convert(a, value, source, loc)
            except _Mismatch:
                continue
        raise _Mismatch
    if tp in (bool, int, float, str):
        return _scalar(tp, value)
    if origin is tuple and isinstance(value, list):
        return tuple(field_value(args[0], v, source, (*loc, i)) for i, v in enumerate(value))
    if origin is dict and isinstance(value, dict):
        return {str(k): field_value(args[1], v, source, (*loc, k)) for k, v in value.items()}
    if dataclasses.is_dataclass(tp) and isinstance(value, dict):
        return build(tp, value, source, loc)
    if origin in (tuple, dict) or dataclasses.is_dataclass(tp):
        raise _Mismatch
    raise TypeError(f"unsupported schema type {tp}")


def field_value(tp, value, source: Source, loc: Loc):
    """``value`` converted to ``tp``, or one UserError naming the file, line and key."""
    try:
        return _convert(tp, value, source, loc)
    except _Mismatch:
        raise UserError(f"{source.where(loc)} must be {_type_text(tp)}, got {value!r}") from None


def _accepts_none(tp) -> bool:
    return tp is Any or (typing.get_origin(tp) in (Union, types.UnionType) and type(None) in typing.get_args(tp))


def build(cls, raw: dict, source: Source, loc: Loc = ()):
    """An instance of dataclass ``cls`` from mapping ``raw`` found at ``loc`` in ``source``."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    unknown = [k for k in raw if k not in fields]
    if unknown:
        plural = "s" if len(unknown) > 1 else ""
        raise UserError(f"{source.where(loc, (*loc, unknown[0]))}: unknown key{plural} "
                        f"{', '.join(repr(k) for k in unknown)}; expected one of {sorted(fields)}")
    given = {k: v for k, v in raw.items() if v is not None or _accepts_none(hints[k])}
    for name, f in fields.items():
        if name not in given and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise UserError(f"{source.where(loc)}: '{name}' is missing")
    return cls(**{k: field_value(hints[k], v, source, (*loc, k)) for k, v in given.items()})
