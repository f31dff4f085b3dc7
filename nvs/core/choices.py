"""The one check of a build-time switch: a value it does not know is one clear error naming the config key."""

from __future__ import annotations

from collections.abc import Collection
from typing import TypeVar

T = TypeVar("T")


def check_choice(value: T, choices: Collection, name: str) -> T:
    """``value`` if it is one of ``choices``, else a ValueError naming ``name`` (the config key to fix)."""
    if value not in choices:
        raise ValueError(f"{name}={value!r}: choose one of {list(choices)}")
    return value
