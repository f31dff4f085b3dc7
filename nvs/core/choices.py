"""The checks of a build-time setting: a value it does not know, or a count that builds nothing, is one clear error
naming the config key."""

from __future__ import annotations

from collections.abc import Collection
from typing import TypeVar

T = TypeVar("T")


def check_choice(value: T, choices: Collection, name: str) -> T:
    """``value`` if it is one of ``choices``, else a ValueError naming ``name`` (the config key to fix)."""
    if value not in choices:
        raise ValueError(f"{name}={value!r}: choose one of {list(choices)}")
    return value


def check_count(value: int, name: str) -> int:
    """``value`` if it is a positive integer (a layer width, a number of points), else a ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}={value!r}: expected a positive integer")
    return value
