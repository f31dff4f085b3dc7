"""The structured schema of a component config (a mapping with ``_target_``): its target's named arguments, typed
as their annotations say, as a dataclass OmegaConf validates against.

An argument whose annotation OmegaConf cannot type (a module, a union of unlike types, a ``Literal``, a tensor)
takes any value; a target that passes ``**kwargs`` on to a base class takes the base's named arguments too, and one
that takes ``**kwargs`` all the way up (a W&B logger) takes any other key. Hydra's reserved keys (``_target_``,
``_partial_``, ...) belong to every component.
"""

from __future__ import annotations

import collections.abc as abc
import dataclasses
import enum
import functools
import inspect
import pathlib
import types
import typing
from typing import Any, Dict, List, Optional, Union

import torch
from omegaconf import MISSING

RESERVED: dict[str, Any] = {"_target_": str, "_partial_": bool, "_recursive_": bool, "_convert_": Any,
                            "_args_": List[Any]}
_PRIMITIVE = (bool, int, float, str)
_SEQUENCES = (list, tuple, abc.Sequence, abc.MutableSequence, abc.Collection, abc.Iterable)
_MAPPINGS = (dict, abc.Mapping, abc.MutableMapping)
_ROOTS = (object, torch.nn.Module)


@dataclasses.dataclass(frozen=True)
class ComponentSchema:
    """What a component config may hold: ``schema`` (a dataclass, every field MISSING), and ``open``: other keys."""

    target: str
    schema: type
    open: bool

    @property
    def names(self) -> list[str]:
        return [f.name for f in dataclasses.fields(self.schema)]


def omegaconf_type(annotation: Any) -> Any:
    """The type OmegaConf validates for a Python annotation: a primitive, an Enum, ``Optional``, ``List`` of a
    primitive or ``Dict[str, Any]``; ``Any`` for what it cannot type. A union of numbers is a number (``float``)."""
    if annotation is inspect.Parameter.empty or annotation is Any or isinstance(annotation, (str, typing.TypeVar)):
        return Any
    if annotation in _PRIMITIVE:
        return annotation
    if inspect.isclass(annotation):
        if issubclass(annotation, enum.Enum):
            return annotation
        if issubclass(annotation, pathlib.PurePath):
            return str
        if annotation in _SEQUENCES:
            return List[Any]
        if annotation in _MAPPINGS:
            return Dict[str, Any]
        return Any
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is Union or origin is types.UnionType:
        inner = [a for a in args if a is not type(None)]
        kinds = {omegaconf_type(a) for a in inner}
        if kinds and kinds <= {int, float}:
            kind = float if float in kinds else int
        elif len(kinds) == 1:
            kind = kinds.pop()
        else:
            return Any
        return Any if kind is Any else (Optional[kind] if len(inner) < len(args) else kind)
    if origin in _SEQUENCES:
        items = {omegaconf_type(a) for a in args if a is not Ellipsis}
        item = items.pop() if len(items) == 1 else Any
        return List[item if item in _PRIMITIVE or item is Any else Any]
    if origin in _MAPPINGS:
        return Dict[str, Any]
    return Any


def _hints(fn) -> dict[str, Any]:
    """The evaluated annotations of ``fn``; one that does not evaluate (a name only a type checker sees) is Any."""
    try:
        return typing.get_type_hints(fn)
    except Exception:  # noqa: BLE001 - some annotation does not evaluate: each on its own
        pass
    out = {}
    for name, ann in getattr(fn, "__annotations__", {}).items():
        try:
            out[name] = eval(ann, getattr(fn, "__globals__", {})) if isinstance(ann, str) else ann  # noqa: S307
        except Exception:  # noqa: BLE001
            out[name] = Any
    return out


def _arguments(target) -> tuple[dict[str, Any], bool]:
    """(name -> annotation of every named argument, takes any other keyword): the target's own, and for a class
    whose ``__init__`` passes ``**kwargs`` on, its bases' until one that does not."""
    if inspect.isclass(target):
        # object and torch's Module take (*args, **kwargs) only to refuse them: a class ends there
        chain = [vars(c)["__init__"] for c in target.__mro__ if "__init__" in vars(c) and c not in _ROOTS]
        bound = True
    else:
        chain, bound = [target], False
    names: dict[str, Any] = {}
    for fn in chain:
        try:
            params = list(inspect.signature(fn).parameters.values())
        except (TypeError, ValueError):  # a builtin without a signature: anything goes
            return names, True
        hints = _hints(fn)
        for p in params[1:] if bound else params:
            if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
                names.setdefault(p.name, hints.get(p.name, p.annotation))
        if not any(p.kind is p.VAR_KEYWORD for p in params):
            return names, False
    return names, bool(chain)


@functools.lru_cache(maxsize=None)
def component_schema(target: str, extra: tuple[tuple[str, Any], ...] = ()) -> ComponentSchema | None:
    """The schema of a ``_target_`` (a dotted path as Hydra locates it), with the ``extra`` (name, type) fields a
    config holds beside the arguments (the model's ``name``); None if it cannot be located (the build reports it)."""
    from hydra.utils import get_object

    try:
        obj = get_object(target)
    except Exception:  # noqa: BLE001 - an unknown target is instantiate's error to report
        return None
    if not callable(obj):
        return None
    arguments, open_ = _arguments(obj)
    fields = [(name, kind, dataclasses.field(default=MISSING)) for name, kind in RESERVED.items()]
    fields += [(name, omegaconf_type(ann), dataclasses.field(default=MISSING)) for name, ann in arguments.items()
               if name not in RESERVED and name.isidentifier()]
    fields += [(name, kind, dataclasses.field(default=MISSING)) for name, kind in extra if name not in arguments]
    schema = dataclasses.make_dataclass(f"{getattr(obj, '__name__', 'Component')}Arguments", fields)
    return ComponentSchema(target, schema, open_)
