"""Known landmark maps: where a trial log keeps them, and a file format for them.

A landmark map is {id: (x, y)} in the map frame. A simulated trial has its tags in the
"world" metadata; a dataset import has "landmarks" ({"id": [x, y]}); a user may give a
JSON file of the same {"id": [x, y]} form.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

LandmarkMap = dict[int, np.ndarray]


def from_metadata(metadata: dict[str, Any]) -> LandmarkMap | None:
    """The true landmark map of a trial log, or None when it has none."""
    if "landmarks" in metadata:
        return parse(metadata["landmarks"], "landmarks metadata")
    world = metadata.get("world")
    if world and world.get("tags"):
        return {int(t["id"]): np.array([float(t["x"]), float(t["y"])]) for t in world["tags"]}
    return None


def parse(obj: Any, source: str) -> LandmarkMap:
    if not isinstance(obj, dict):
        raise ValueError(f'{source}: a landmark map is an object {{"id": [x, y], ...}}')
    out: LandmarkMap = {}
    for key, value in obj.items():
        try:
            xy = np.array([float(v) for v in value])
            lid = int(key)
        except (TypeError, ValueError):
            raise ValueError(
                f"{source}: landmark {key!r} must be an integer id with [x, y]"
            ) from None
        if xy.shape != (2,) or not np.all(np.isfinite(xy)):
            raise ValueError(f"{source}: landmark {key!r} must be [x, y], got {value!r}")
        out[lid] = xy
    return out


def load(path: str | Path) -> LandmarkMap:
    """A landmark map from a JSON file {"id": [x, y], ...}."""
    p = Path(path)
    try:
        obj = json.loads(p.read_text())
    except OSError as e:
        raise ValueError(f"{p}: cannot read landmark map ({e.strerror})") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{p}: not JSON ({e.msg} at line {e.lineno})") from None
    return parse(obj, str(p))
