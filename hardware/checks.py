"""Checks that configs run on their numbers in `__post_init__` (a ValueError naming the
field, which the commands turn into one line naming the config)."""

from __future__ import annotations

import math
from typing import Any


def require_non_negative(config: Any, names: tuple[str, ...], where: str) -> None:
    """Each named field of `config` is a finite number >= 0; else ValueError naming it
    as `where`.NAME."""
    for name in names:
        value = getattr(config, name)
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{where}.{name} must be finite and >= 0, got {value}")
