"""A name → factory registry with typed configs (localizers, controllers, ...)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class UnknownNameError(ValueError):
    """A name that is not registered; the message lists the valid names."""

    def __init__(self, kind: str, name: str, valid: list[str]) -> None:
        super().__init__(f"unknown {kind} '{name}'; valid: {', '.join(valid)}")
        self.valid = valid


@dataclass(frozen=True)
class Spec(Generic[T]):
    name: str
    config_type: type
    factory: Callable[..., T]
    summary: str


class Registry(Generic[T]):
    """Factories registered by name; `loader` imports the built-in modules on first use."""

    def __init__(self, kind: str, loader: Callable[[], None]) -> None:
        self.kind = kind
        self._loader = loader
        self._loaded = False
        self._specs: dict[str, Spec[T]] = {}

    def register(self, name: str, config_type: type, summary: str):
        def deco(factory: Callable[..., T]) -> Callable[..., T]:
            self._specs[name] = Spec(name, config_type, factory, summary)
            return factory

        return deco

    def _load(self) -> None:
        if not self._loaded:
            self._loaded = True
            self._loader()

    def names(self) -> list[str]:
        self._load()
        return sorted(self._specs)

    def spec(self, name: str) -> Spec[T]:
        self._load()
        if name not in self._specs:
            raise UnknownNameError(self.kind, name, sorted(self._specs))
        return self._specs[name]

    def create(self, name: str, *args: Any, config: Any = None) -> T:
        """Build `name` with `config` (its defaults when None) and the given arguments."""
        spec = self.spec(name)
        cfg = spec.config_type() if config is None else config
        if not isinstance(cfg, spec.config_type):
            raise TypeError(f"{name} takes a {spec.config_type.__name__}, got {type(cfg).__name__}")
        return spec.factory(cfg, *args)
