"""Live devices found through entry points: depth cameras and tag cameras.

A device is named on the command line as NAME or NAME:ARG (`--depth kinect:1`,
`--depth fakenect:DIR`, `--camera device:0`); the NAME is looked up in the device kind's
registry, whose members the installed packages declare in its entry-point group, as for
localizers (hardware.registry):

    [project.entry-points."walker_slam.depth_cameras"]
    oak-d = "my_package.oak:SPEC"

with `SPEC = DeviceSpec("oak-d", None, open_oak, "Luxonis OAK-D", forms=("oak-d",))`.
The factory is called with the ARG (None when the spec has no colon) and the kind's
arguments:

- depth cameras (`DEPTH_CAMERAS`, `hardware.depth.open_depth`):
  `factory(arg, calibration, clock, **options)` → a Source of DepthFrame;
- tag cameras (`TAG_CAMERAS`, `hardware.tags.open_tag_camera`): the frames a tag
  detector reads, `factory(arg, clock, width=, height=, fps=)` → a `FrameSource`.

A factory raises DeviceError (one line) for an ARG it cannot use; an unknown NAME is a
DeviceError listing every member's forms.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hardware.errors import DeviceError
from hardware.registry import Registry, Spec


@dataclass(frozen=True)
class DeviceSpec(Spec):
    """A device registry member; forms: how its spec is written (for help and errors)."""

    forms: tuple[str, ...] = ()


DEPTH_CAMERAS: Registry[Any] = Registry("depth camera", "walker_slam.depth_cameras")
TAG_CAMERAS: Registry[Any] = Registry("tag camera", "walker_slam.tag_cameras")


def split_spec(text: str) -> tuple[str, str | None]:
    """NAME[:ARG] → (NAME, ARG or None)."""
    name, colon, arg = str(text).partition(":")
    return name, (arg if colon else None)


def forms(registry: Registry[Any]) -> list[str]:
    """Every member's spec forms, in name order."""
    out: list[str] = []
    for name in registry.names():
        spec = registry.spec(name)
        out.extend(spec.forms if isinstance(spec, DeviceSpec) and spec.forms else [name])
    return out


def lookup(registry: Registry[Any], text: str, error: type[DeviceError] = DeviceError):
    """(the member named by spec `text`, its ARG); an unknown name raises `error`."""
    name, arg = split_spec(text)
    if name not in registry.names():
        raise error(f"unknown {registry.kind} {text!r}; valid: {', '.join(forms(registry))}")
    return registry.spec(name), arg
