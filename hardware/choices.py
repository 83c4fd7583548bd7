"""Closed sets of choices as string Enums.

A config field that takes one of a few named modes (a smoother, a robust kernel, an
observation model) is typed with a `Choice` subclass: its members compare equal to their
strings and write to JSON as them, so configs written before keep reading, and
`experiments.config` parses `--set` values (and `walkerslam list NAME` shows the
choices) from the type. `Choice.parse` turns a string into a member or raises one
ConfigError naming the field and the valid values; configs call it in `__post_init__`
through `coerce`, so a config built from a plain string holds the member.
"""

from __future__ import annotations

import enum
from typing import Any, TypeVar

from hardware.errors import ConfigError

C = TypeVar("C", bound="Choice")


class Choice(enum.StrEnum):
    """A closed set of string choices (a str: == "value", json.dumps as "value")."""

    @classmethod
    def parse(cls: type[C], value: Any, name: str) -> C:
        if isinstance(value, cls):
            return value
        try:
            return cls(value)
        except ValueError:
            valid = ", ".join(m.value for m in cls)
            raise ConfigError(f"{name} must be one of {valid}; got {value!r}") from None

    @classmethod
    def values(cls) -> tuple[str, ...]:
        return tuple(m.value for m in cls)


def coerce(config: Any, **fields: type[Choice]) -> None:
    """Replace each named field of a (frozen) dataclass by its Choice member."""
    for name, kind in fields.items():
        object.__setattr__(config, name, kind.parse(getattr(config, name), name))
