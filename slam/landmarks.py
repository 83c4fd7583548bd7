"""Known landmark maps: where a trial log keeps them, and a file format for them.

A landmark map is {id: (x, y)} in the map frame. A simulated trial has its tags in the
"world" metadata; a dataset import has "landmarks" ({"id": [x, y]}); a user may give a
JSON file of the same {"id": [x, y]} form (`walkerslam replay --landmark-map`), e.g. the
landmarks.json a SLAM replay writes (`save`), to localize in that map.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from hardware.errors import ConfigError

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
        raise ConfigError(f'{source}: a landmark map is an object {{"id": [x, y], ...}}')
    out: LandmarkMap = {}
    for key, value in obj.items():
        try:
            xy = np.array([float(v) for v in value])
            lid = int(key)
        except (TypeError, ValueError):
            raise ConfigError(
                f"{source}: landmark {key!r} must be an integer id with [x, y]"
            ) from None
        if xy.shape != (2,) or not np.all(np.isfinite(xy)):
            raise ConfigError(f"{source}: landmark {key!r} must be [x, y], got {value!r}")
        out[lid] = xy
    return out


def load(path: str | Path) -> LandmarkMap:
    """A landmark map from a JSON file {"id": [x, y], ...}."""
    p = Path(path)
    try:
        obj = json.loads(p.read_text())
    except OSError as e:
        raise ConfigError(f"{p}: cannot read landmark map ({e.strerror})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        why = f"{e.msg} at line {e.lineno}" if isinstance(e, json.JSONDecodeError) else "binary"
        raise ConfigError(f"{p}: not JSON ({why})") from None
    out = parse(obj, str(p))
    if not out:
        raise ConfigError(f"{p}: the landmark map is empty")
    return out


def save(path: str | Path, landmark_map: dict[int, Any]) -> Path:
    """Write {id: (x, y, ...)} as the JSON file `load` reads (ids in order, x and y only)."""
    p = Path(path)
    obj = {str(k): [float(v[0]), float(v[1])] for k, v in sorted(landmark_map.items())}
    p.write_text(json.dumps(obj, indent=1) + "\n")
    return p
