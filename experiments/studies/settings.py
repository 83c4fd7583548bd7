"""`NAME.FIELD=VALUE` overrides of registered configs (controllers, localizers).

A study names controllers and localizers by their registry names; `--set
open-loop.d_max_m=1.75` changes one field of that controller's typed config (applied
with `dataclasses.replace`, so the config's own validation runs), and `--sweep
closed-loop.D=9,16,23,30` lists several values of one field. Values are converted to the
field's declared type (float, int, bool or str).
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Iterable, Mapping
from typing import Any

from hardware.errors import ConfigError
from hardware.registry import Registry
from hardware.source import PROPOSED_SETTINGS


def _field_types(config_type: type) -> dict[str, Any]:
    try:
        hints = typing.get_type_hints(config_type)
    except Exception:  # unresolvable annotations: fall back to the defaults' types
        hints = {}
    out = {}
    for f in dataclasses.fields(config_type):
        t = hints.get(f.name)
        if t is None and f.default is not dataclasses.MISSING:
            t = type(f.default)
        out[f.name] = t
    return out


def convert(value: str, typ: Any, where: str) -> Any:
    """`value` (text) as `typ`; ValueError naming `where` when it does not fit."""
    if isinstance(value, str):
        text = value.strip()
    else:
        return value
    try:
        if typ is bool:
            low = text.lower()
            if low in ("1", "true", "yes", "on"):
                return True
            if low in ("0", "false", "no", "off"):
                return False
            raise ValueError  # (the caller turns it into a ConfigError)
        if typ is int:
            return int(text)
        if typ is float:
            return float(text)
    except ValueError:
        raise ConfigError(f"{where}: '{value}' is not a valid {typ.__name__}") from None
    if typ is str:
        return text
    # Other annotations (unions, tuples): try a number, else keep the text.
    try:
        return float(text) if any(c in text for c in ".eE") else int(text)
    except ValueError:
        return text


def split_key(key: str) -> tuple[str, str]:
    """'open-loop.d_max_m' → ('open-loop', 'd_max_m'); a field of a nested config keeps
    its path: 'gtsam.noise.brake_aware' → ('gtsam', 'noise.brake_aware')."""
    name, dot, field = key.strip().partition(".")
    if not dot or not name or not field:
        raise ConfigError(f"expected NAME.FIELD (e.g. open-loop.d_max_m), got '{key}'")
    return name, field


def parse_assignment(text: str) -> tuple[str, str, list[str]]:
    """'closed-loop.D=9,16' → ('closed-loop', 'D', ['9', '16'])."""
    key, eq, values = text.partition("=")
    if not eq or not values.strip():
        raise ConfigError(f"expected NAME.FIELD=VALUE[,VALUE...], got '{text}'")
    name, field = split_key(key)
    vals = [v.strip() for v in values.split(",") if v.strip()]
    return name, field, vals


def field_type(registry: Registry, name: str, field: str) -> Any:
    """The declared type of `field` (a dotted path into nested configs) in `name`'s
    config (UnknownNameError / ValueError)."""
    typ: Any = registry.spec(name).config_type
    path = field.split(".")
    for depth, part in enumerate(path):
        types = _field_types(typ) if dataclasses.is_dataclass(typ) else {}
        if part not in types:
            where = ".".join(path[:depth]) or "config"
            raise ConfigError(
                f"{registry.kind} '{name}' has no field '{part}' in its {where}; fields: "
                + (", ".join(types) or "(none)")
            )
        typ = types[part]
    return typ


def _replace_path(cfg: Any, path: list[str], value: Any) -> Any:
    """`cfg` with the field at `path` (nested dataclasses) replaced by `value`."""
    head, rest = path[0], path[1:]
    new = _replace_path(getattr(cfg, head), rest, value) if rest else value
    return dataclasses.replace(cfg, **{head: new})


def typed_overrides(registry: Registry, name: str, overrides: Mapping[str, Any]) -> dict[str, Any]:
    """`overrides` ({field: text or value}) converted to the fields' types."""
    return {
        f: convert(v, field_type(registry, name, f), f"{name}.{f}") for f, v in overrides.items()
    }


def build_config(registry: Registry, name: str, overrides: Iterable[tuple[str, Any]] = ()) -> Any:
    """`name`'s default config with `overrides` ((field, value) pairs) replaced; runs the
    config's validation (ValueError)."""
    cfg = registry.spec(name).config_type()
    over = typed_overrides(registry, name, dict(overrides))
    try:
        for field, value in over.items():
            cfg = _replace_path(cfg, field.split("."), value)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{name}: {e}") from None
    return cfg


SOURCE_SETTINGS = PROPOSED_SETTINGS


def source_settings(registry: Registry, name: str, metadata: Mapping[str, Any]) -> dict[str, Any]:
    """The settings a recorded source proposes for `name`'s config: its metadata
    "localizer_settings" ({field path: value}, e.g. a dataset importer's noise levels
    fitted to that dataset), keeping the fields `name`'s config has. Apply them before
    the user's --set overrides: `build_config(reg, name, [*settings.items(), *sets])`."""
    proposed = metadata.get(SOURCE_SETTINGS) or {}
    out = {}
    for field, value in proposed.items():
        try:
            field_type(registry, name, field)
        except ValueError:
            continue
        out[field] = value
    return out


def parse_sets(
    texts: Iterable[str], registries: Mapping[str, Registry], allowed: Iterable[str]
) -> dict[str, dict[str, Any]]:
    """`--set NAME.FIELD=VALUE` options → {name: {field: value}} with typed values.

    `registries` maps each allowed name to its registry (controller or localizer)."""
    allowed = list(allowed)
    out: dict[str, dict[str, Any]] = {}
    for text in texts:
        name, field, vals = parse_assignment(text)
        if len(vals) != 1:
            raise ConfigError(f"--set takes one value, got '{text}' (use --sweep for several)")
        if name not in registries:
            raise ConfigError(
                f"--set {text}: '{name}' is not in this study; names: {', '.join(allowed)}"
            )
        reg = registries[name]
        out.setdefault(name, {})[field] = convert(
            vals[0], field_type(reg, name, field), f"{name}.{field}"
        )
    return out
