"""The structured schema of a component config (a mapping with ``_target_``): its target's named arguments, typed
as their annotations say, as a dataclass OmegaConf validates against.

An argument whose annotation OmegaConf cannot type (a module, a union of unlike types, a ``Literal``, a tensor)
takes any value; a target that passes ``**kwargs`` on to a base class takes the base's named arguments too, and one
that takes ``**kwargs`` all the way up (a W&B logger) takes any other key. Hydra's reserved keys (``_target_``,
``_partial_``, ...) belong to every component.

Schemas of targets in nvs, torch, Lightning, torchmetrics and kornia are kept across processes
(``$NVS_CACHE_DIR/component_schemas.json``, else ``$XDG_CACHE_HOME/nvs`` or ``~/.cache/nvs``), valid while nvs's
source files and those packages' versions are as they were: a command line whose config is wrong says so without
importing torch and Lightning first (~5 s of CPU on a small machine). Other targets (a user's own package) are read
from their code each time.
"""

from __future__ import annotations

import collections.abc as abc
import dataclasses
import enum
import functools
import hashlib
import importlib
import inspect
import json
import pathlib
import sys
import types
import typing
from typing import Any, Dict, List, Optional, Union

from omegaconf import MISSING

from nvs.core.atomic import cache_dir, write_json

RESERVED: dict[str, Any] = {"_target_": str, "_partial_": bool, "_recursive_": bool, "_convert_": Any,
                            "_args_": List[Any]}
_PRIMITIVE = (bool, int, float, str)
_SEQUENCES = (list, tuple, abc.Sequence, abc.MutableSequence, abc.Collection, abc.Iterable)
_MAPPINGS = (dict, abc.Mapping, abc.MutableMapping)


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
        # object and torch's Module take (*args, **kwargs) only to refuse them: a class ends there (a Module's
        # subclass has loaded torch already)
        torch = sys.modules.get("torch")
        roots = (object, torch.nn.Module) if torch is not None else (object,)
        chain = [vars(c)["__init__"] for c in target.__mro__ if "__init__" in vars(c) and c not in roots]
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
    found = _cached(target) or _read_arguments(target)
    if found is None:
        return None
    name, open_, arguments = found
    fields = [(n, kind, dataclasses.field(default=MISSING)) for n, kind in RESERVED.items()]
    fields += [(n, kind, dataclasses.field(default=MISSING)) for n, kind in arguments]
    fields += [(n, kind, dataclasses.field(default=MISSING)) for n, kind in extra if n not in dict(arguments)]
    return ComponentSchema(target, dataclasses.make_dataclass(f"{name}Arguments", fields), open_)


Found = tuple[str, bool, list[tuple[str, Any]]]  # (the target's name, takes other keys, (argument, OmegaConf type))


def _read_arguments(target: str) -> Found | None:
    """The target's arguments from its code (importing it), and kept in the cache where it is one of its packages."""
    from hydra.utils import get_object

    try:
        obj = get_object(target)
    except Exception:  # noqa: BLE001 - an unknown target is instantiate's error to report
        return None
    if not callable(obj):
        return None
    arguments, open_ = _arguments(obj)
    found = (getattr(obj, "__name__", "Component"), open_,
             [(n, omegaconf_type(ann)) for n, ann in arguments.items() if n not in RESERVED and n.isidentifier()])
    codes = [_encode(kind) for _, kind in found[2]]
    if target.split(".")[0] in CACHED_PACKAGES and None not in codes:
        _remember(target, {"name": found[0], "open": open_,
                           "arguments": [[n, c] for (n, _), c in zip(found[2], codes)]})
    return found


# -- kept across processes -------------------------------------------------------------------------------------------
CACHED_PACKAGES = {"nvs": "nvs", "torch": "torch", "lightning": "lightning", "torchmetrics": "torchmetrics",
                   "kornia": "kornia"}  # top-level module -> distribution
_CACHE_FORMAT = 1
_PRIMITIVES = {"any": Any, "bool": bool, "int": int, "float": float, "str": str}


def cache_file() -> pathlib.Path:
    return cache_dir() / "component_schemas.json"


@functools.lru_cache(maxsize=None)
def source_state() -> str:
    """What a kept schema depends on: the cache's format, Python, the cached packages' and Hydra's/OmegaConf's versions,
    and every nvs source file (path, size, mtime): an edited, added or removed file is another state."""
    import importlib.metadata as metadata

    package = pathlib.Path(__file__).resolve().parents[1]
    digest = hashlib.sha256(f"{_CACHE_FORMAT} {sys.version} {package}".encode())
    for dist in sorted({*CACHED_PACKAGES.values(), "hydra-core", "omegaconf"} - {"nvs"}):
        try:
            digest.update(f"{dist}={metadata.version(dist)};".encode())
        except metadata.PackageNotFoundError:
            digest.update(f"{dist}=-;".encode())
    for path in sorted(package.rglob("*.py")):
        st = path.stat()
        digest.update(f"{path.relative_to(package)}:{st.st_size}:{st.st_mtime_ns};".encode())
    return digest.hexdigest()[:20]


def _read_cache() -> dict:
    try:
        data = json.loads(cache_file().read_text())
    except (OSError, ValueError):
        return {}
    ok = isinstance(data, dict) and data.get("state") == source_state() and isinstance(data.get("schemas"), dict)
    return data["schemas"] if ok else {}


def _cached(target: str) -> Found | None:
    entry = _read_cache().get(target) if target.split(".")[0] in CACHED_PACKAGES else None
    try:
        return entry["name"], bool(entry["open"]), [(n, _decode(c)) for n, c in entry["arguments"]]
    except Exception:  # noqa: BLE001 - no entry, or one this code cannot read: the target's code is read instead
        return None


def _remember(target: str, entry: dict) -> None:
    """Add one schema to the file (other processes' entries kept; a write that fails only costs the next run time)."""
    schemas = {**_read_cache(), target: entry}
    try:
        cache_file().parent.mkdir(parents=True, exist_ok=True)
        write_json(cache_file(), {"state": source_state(), "schemas": schemas})
    except Exception:  # noqa: BLE001 - a cache is never a reason to fail
        pass


def _encode(kind: Any) -> str | None:
    """An OmegaConf type (what :func:`omegaconf_type` returns) as text; None for one the cache does not keep."""
    for code, primitive in _PRIMITIVES.items():
        if kind is primitive:
            return code
    if inspect.isclass(kind) and issubclass(kind, enum.Enum):
        return f"enum:{kind.__module__}:{kind.__qualname__}"
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin is Union and len(args) == 2 and type(None) in args:
        inner = _encode(next(a for a in args if a is not type(None)))
        return None if inner is None else f"?{inner}"
    if origin is list and len(args) == 1:
        inner = _encode(args[0])
        return None if inner is None else f"list:{inner}"
    if origin is dict and args == (str, Any):
        return "dict"
    return None


def _decode(code: str) -> Any:
    if code in _PRIMITIVES:
        return _PRIMITIVES[code]
    if code.startswith("?"):
        return Optional[_decode(code[1:])]
    if code.startswith("list:"):
        return List[_decode(code[5:])]
    if code == "dict":
        return Dict[str, Any]
    if code.startswith("enum:"):
        _, module, qualname = code.split(":")
        obj = importlib.import_module(module)
        for part in qualname.split("."):
            obj = getattr(obj, part)
        return obj
    raise ValueError(f"unknown type code {code!r}")
