"""The one config path: a localizer's or controller's config from its defaults, then the
settings its source proposes, then the user's `--set`.

    sets = parse_sets(["gtsam.prior_sigma=0.1,0.1,0.05"], {"gtsam": LOCALIZERS})
    built = configure(LOCALIZERS, "gtsam", trial.metadata, sets.get("gtsam", {}))
    built.config, built.proposed, built.skipped      # what was applied, what was not

Every command (replay, compare, simulate, live, the studies) builds its configs here.

- A `--set NAME.FIELD=VALUE` names a field by its path into nested configs
  (`ekf-slam.noise.brake_aware=true`). A field the config lacks, a group of fields set
  as if it were one (`ekf-slam.noise=1`), or a value of the wrong type is a
  `ConfigError` when the options are parsed, before any work starts.
- Values take the field's declared type: bool (true/false, yes/no, on/off, 1/0), int,
  float, str, an Enum (by value or name), `X | None` ("none" for None), and tuples of
  those, written with commas (`--set gtsam.prior_sigma=0.1,0.1,0.05`; the count must
  match).
- A source proposes settings in its metadata (`hardware.source.PROPOSED_SETTINGS`: a
  dataset importer's fitted noise levels, a simulated trial's encoder noise, CARMEN's
  laser settings); those its config has are applied before the `--set`, the others are
  skipped and reported (`Configured.skipped`, written into each run's config.json).
- The config's own validation (`__post_init__`) runs on the result; its ValueError or
  TypeError becomes a `ConfigError` naming the config, before the run begins.
"""

from __future__ import annotations

import dataclasses
import enum
import types
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from hardware.errors import ConfigError
from hardware.registry import Registry
from hardware.source import PROPOSED_SETTINGS

_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")


@dataclass(frozen=True)
class Configured:
    """A config built by `configure`, with where its values came from."""

    config: Any
    proposed: dict[str, Any] = field(default_factory=dict)  # applied from the source
    skipped: dict[str, Any] = field(default_factory=dict)  # proposed, but no such field
    overrides: dict[str, Any] = field(default_factory=dict)  # the user's --set


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


def field_type(registry: Registry, name: str, path: str) -> Any:
    """The declared type of the field at `path` (dotted, into nested configs) of `name`'s
    config; ConfigError naming the valid fields when there is none."""
    return _path_type(registry.spec(name).config_type, path, name, f"{registry.kind} '{name}'")


def _path_type(config_type: type, path: str, name: str, owner: str) -> Any:
    """field_type's walk through `config_type` (`owner` and `name` for its errors)."""
    typ: Any = config_type
    parts = path.split(".")
    for depth, part in enumerate(parts):
        fields = _field_types(typ) if dataclasses.is_dataclass(typ) else {}
        if part not in fields:
            where = ".".join(parts[:depth]) or "config"
            raise ConfigError(
                f"{owner} has no field '{part}' in its {where}; fields: "
                + (", ".join(fields) or "(none)")
            )
        typ = fields[part]
    if dataclasses.is_dataclass(typ):
        inner = ", ".join(f"{path}.{f}" for f in _field_types(typ))
        raise ConfigError(f"{name}.{path} is a group of settings; set one of: {inner}")
    return typ


def propose(config: Any, proposed: Mapping[str, Any], name: str) -> Any:
    """`config` (a dataclass, e.g. the mapper's) with the settings a source proposes for
    it ({field path: value}, typed as the field) applied where it still has its type's
    default, so that a value the caller chose stands; a ConfigError naming `name` for a
    path the config lacks or a value that does not fit."""
    default = type(config)()
    for path, value in proposed.items():
        parts = path.split(".")
        typed = convert(value, _path_type(type(config), path, name, name), f"{name}.{path}")
        here, there = config, default
        for part in parts:
            here, there = getattr(here, part), getattr(there, part)
        if here == there:
            config = _replace_path(config, parts, typed)
    return config


def convert(value: Any, typ: Any, where: str) -> Any:
    """`value` (text from the command line, or a JSON value from a source) as `typ`;
    ConfigError naming `where` when it does not fit."""
    origin, args = typing.get_origin(typ), typing.get_args(typ)
    if origin in (typing.Union, types.UnionType):
        kinds = [a for a in args if a is not type(None)]
        if type(None) in args and (value is None or str(value).strip().lower() in ("none", "null")):
            return None
        if len(kinds) == 1:
            return convert(value, kinds[0], where)
        return value  # an open union: the config's own validation decides
    if origin is tuple:
        items = value.split(",") if isinstance(value, str) else list(value)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(convert(v, args[0], where) for v in items)
        if len(items) != len(args):
            raise ConfigError(
                f"{where}: takes {len(args)} values separated by commas, got {value!r}"
            )
        return tuple(convert(v, a, where) for v, a in zip(items, args, strict=True))
    text = value.strip() if isinstance(value, str) else value
    try:
        if typ is bool:
            if isinstance(text, bool):
                return text
            if str(text).lower() in _TRUE:
                return True
            if str(text).lower() in _FALSE:
                return False
            raise ValueError(text)
        if typ is int:
            if isinstance(text, float) and not text.is_integer():
                raise ValueError(text)
            return int(text)
        if typ is float:
            return float(text)
        if typ is str:
            return str(text)
        if isinstance(typ, type) and issubclass(typ, enum.Enum):
            try:
                return typ(text)
            except ValueError:
                return typ[str(text)]
    except (ValueError, TypeError, KeyError):
        expected = (
            ", ".join(str(m.value) for m in typ)
            if isinstance(typ, type) and issubclass(typ, enum.Enum)
            else f"a {getattr(typ, '__name__', typ)}"
        )
        raise ConfigError(f"{where}: {value!r} is not {expected}") from None
    return value  # annotations without a conversion (dicts, callables): as given


def split_key(key: str) -> tuple[str, str]:
    """'open-loop.d_max_m' → ('open-loop', 'd_max_m'); a field of a nested config keeps
    its path: 'gtsam.noise.brake_aware' → ('gtsam', 'noise.brake_aware')."""
    name, dot, path = key.strip().partition(".")
    if not dot or not name or not path:
        raise ConfigError(f"expected NAME.FIELD (e.g. open-loop.d_max_m), got '{key}'")
    return name, path


def parse_assignment(text: str) -> tuple[str, str, str]:
    """'closed-loop.D=9' → ('closed-loop', 'D', '9')."""
    key, eq, value = text.partition("=")
    if not eq or not value.strip():
        raise ConfigError(f"expected NAME.FIELD=VALUE, got '{text}'")
    name, path = split_key(key)
    return name, path, value.strip()


def parse_sets(
    texts: Iterable[str], registries: Mapping[str, Registry], allowed: Iterable[str] = ()
) -> dict[str, dict[str, Any]]:
    """`--set NAME.FIELD=VALUE` options → {name: {field path: typed value}}; every error
    (unknown name or field, a group set as a value, a value of the wrong type) now.

    `registries` maps each name the command runs to its registry (localizer or
    controller)."""
    allowed = list(allowed) or list(registries)
    out: dict[str, dict[str, Any]] = {}
    for text in texts:
        name, path, value = parse_assignment(text)
        if name not in registries:
            raise ConfigError(
                f"--set {text}: '{name}' is not run here; names: {', '.join(allowed)}"
            )
        reg = registries[name]
        out.setdefault(name, {})[path] = convert(
            value, field_type(reg, name, path), f"{name}.{path}"
        )
    return out


def _replace_path(cfg: Any, path: list[str], value: Any) -> Any:
    """`cfg` with the field at `path` (nested dataclasses) replaced by `value`."""
    head, rest = path[0], path[1:]
    new = _replace_path(getattr(cfg, head), rest, value) if rest else value
    return dataclasses.replace(cfg, **{head: new})


def proposals(registry: Registry, name: str, metadata: Mapping[str, Any] | None) -> tuple:
    """(the settings a source's metadata proposes that `name`'s config has, typed; the
    ones it does not have)."""
    proposed = (metadata or {}).get(PROPOSED_SETTINGS) or {}
    applied, skipped = {}, {}
    for path, value in proposed.items():
        try:
            typ = field_type(registry, name, path)
        except ConfigError:
            skipped[path] = value
            continue
        applied[path] = convert(value, typ, f"{name}.{path} (proposed by the source)")
    return applied, skipped


def configure(
    registry: Registry,
    name: str,
    metadata: Mapping[str, Any] | None = None,
    overrides: Mapping[str, Any] | Iterable[tuple[str, Any]] = (),
) -> Configured:
    """`name`'s config: its defaults, then what the source (its `metadata`) proposes,
    then `overrides` ({field path: value}, e.g. from `parse_sets`); validated."""
    over = dict(overrides)
    applied, skipped = proposals(registry, name, metadata)
    cfg = registry.spec(name).config_type()
    try:
        for path, value in [*applied.items(), *over.items()]:
            typed = convert(value, field_type(registry, name, path), f"{name}.{path}")
            cfg = _replace_path(cfg, path.split("."), typed)
    except (TypeError, ValueError) as e:
        if isinstance(e, ConfigError):
            raise
        raise ConfigError(f"{name}: {e}") from None
    return Configured(cfg, applied, skipped, over)


def checked(build, what: str):
    """`build()` (a config's construction from a user's values), its ValueError or
    TypeError as a ConfigError naming `what`."""
    try:
        return build()
    except (TypeError, ValueError) as e:
        if isinstance(e, ConfigError):
            raise
        raise ConfigError(f"{what}: {e}") from None


def describe(
    config_type: type | None, prefix: str = "", defaults: Any = None
) -> list[tuple[str, str, str]]:
    """(field path, default, type) of every setting of a config, nested groups
    flattened (what `walkerslam list NAME` shows)."""
    if config_type is None:
        return []
    out = []
    defaults = config_type() if defaults is None else defaults
    for name, typ in _field_types(config_type).items():
        value = getattr(defaults, name)
        if dataclasses.is_dataclass(typ):
            out += [(f"{prefix}{name}.{p}", d, t) for p, d, t in describe(typ, "", value)]
            continue
        shown = value.value if isinstance(value, enum.Enum) else value
        out.append((f"{prefix}{name}", repr(shown), _type_name(typ)))
    return out


def explained_in(config_type: type | None, prefix: str = "") -> list[tuple[str, str]]:
    """(group of settings, the config class whose docstring explains it) for a config and
    each nested group in it, in field order: ("", "slam.gtsam_smoother.GtsamConfig"),
    ("scan.", "slam.scan_graph.SequentialScans"), ... (what `walkerslam list NAME` shows
    below the settings)."""
    if config_type is None:
        return []
    out = [(prefix, f"{config_type.__module__}.{config_type.__qualname__}")]
    for name, typ in _field_types(config_type).items():
        if dataclasses.is_dataclass(typ):
            out += explained_in(typ, f"{prefix}{name}.")
    return out


def _type_name(typ: Any) -> str:
    if typing.get_origin(typ) is not None:
        return str(typ).replace("typing.", "")
    if isinstance(typ, type):
        if issubclass(typ, enum.Enum):
            return " | ".join(repr(m.value) for m in typ)
        return typ.__name__
    return str(typ).replace("typing.", "")
