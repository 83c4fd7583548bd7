"""Name → factory registries with typed configs, found through Python entry points.

A registry (localizers, controllers, dataset formats, depth cameras) lists what the
installed packages declare in its entry-point group: walker-slam's own members are in
its `pyproject.toml` (`[project.entry-points."walker_slam.localizers"]` …), and another
package adds one by declaring an entry point in the same group, without editing
walker-slam:

    [project.entry-points."walker_slam.localizers"]
    my-filter = "my_package.my_filter:SPEC"

where `SPEC = Spec("my-filter", MyFilterConfig, MyFilter, "one line on what it does")`;
the factory is called as `factory(config, *args)` (a localizer: `(config, calibration)`).
A member module imports the registry's base module, never the other way round, so the
packages have no import circles. `Registry.register` adds a member in code (tests,
notebooks).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Generic, TypeVar

from hardware.errors import UnknownNameError

__all__ = ["Registry", "Spec", "UnknownNameError"]

T = TypeVar("T")


@dataclass(frozen=True)
class Spec(Generic[T]):
    """A registry member: its name, its config dataclass (or None when it takes none),
    the factory, and a one-line summary."""

    name: str
    config_type: type | None
    factory: Callable[..., T]
    summary: str


class Registry(Generic[T]):
    """The members of entry-point group `group`. Their names come from the entry points'
    declarations; a member's module is imported when that member is first asked for, so
    naming one localizer does not import every other (gtsam, SciPy's image and tree code)."""

    def __init__(self, kind: str, group: str) -> None:
        self.kind = kind
        self.group = group
        self._declared: dict[str, EntryPoint] | None = None
        self._specs: dict[str, Spec[T]] = {}

    def register(self, name: str, config_type: type | None, summary: str):
        """Decorator adding `factory` under `name` (members added in code)."""

        def deco(factory: Callable[..., T]) -> Callable[..., T]:
            self._specs[name] = Spec(name, config_type, factory, summary)
            return factory

        return deco

    def _entry_points(self) -> dict[str, EntryPoint]:
        """The group's entry points by name (the first one declared of a name)."""
        if self._declared is None:
            self._declared = {}
            for ep in entry_points(group=self.group):
                self._declared.setdefault(ep.name, ep)
        return self._declared

    def names(self) -> list[str]:
        return sorted(set(self._specs) | set(self._entry_points()))

    def spec(self, name: str) -> Spec[T]:
        if name not in self._specs:
            ep = self._entry_points().get(name)
            if ep is None:
                raise UnknownNameError(self.kind, name, self.names())
            spec = ep.load()
            if not isinstance(spec, Spec) or spec.name != ep.name:
                raise TypeError(
                    f"entry point {ep.name} = {ep.value} in {self.group} must name a "
                    f"Spec called {ep.name!r}, got {spec!r}"
                )
            self._specs[name] = spec
        return self._specs[name]

    def create(self, name: str, *args: Any, config: Any = None) -> T:
        """Build `name` with `config` (its defaults when None) and the given arguments."""
        spec = self.spec(name)
        if spec.config_type is None:
            return spec.factory(*args)
        cfg = spec.config_type() if config is None else config
        if not isinstance(cfg, spec.config_type):
            raise TypeError(f"{name} takes a {spec.config_type.__name__}, got {type(cfg).__name__}")
        return spec.factory(cfg, *args)
