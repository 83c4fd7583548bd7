import json

import numpy as np
import pytest

from hardware.errors import ConfigError
from hardware.sim.world import load_world
from slam import landmarks


def test_from_world_metadata():
    world = load_world("corner")
    lm = landmarks.from_metadata({"world": world.to_dict()})
    assert set(lm) == {t.tag_id for t in world.tags}
    t = world.tags[0]
    assert np.allclose(lm[t.tag_id], [t.x, t.y])
    assert landmarks.from_metadata({}) is None


def test_file_round_trip_and_errors(tmp_path):
    p = tmp_path / "map.json"
    p.write_text(json.dumps({"6": [1.5, -2.0], "7": [0, 0]}))
    lm = landmarks.load(p)
    assert np.allclose(lm[6], [1.5, -2.0]) and set(lm) == {6, 7}
    p.write_text(json.dumps({"x": [1, 2]}))
    with pytest.raises(ValueError, match=r"map\.json: landmark 'x'"):
        landmarks.load(p)
    p.write_text("{")
    with pytest.raises(ValueError, match=r"map\.json: not JSON"):
        landmarks.load(p)
    with pytest.raises(ValueError, match="cannot read"):
        landmarks.load(tmp_path / "missing.json")
    p.write_text("{}")
    with pytest.raises(ConfigError, match=r"map\.json: the landmark map is empty"):
        landmarks.load(p)
    p.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ConfigError, match=r"map\.json: not JSON"):
        landmarks.load(p)


def test_saved_map_loads_back_the_same(tmp_path):
    marks = {1_000_003: np.array([12.25, -3.5]), 7: (0.1, 2e-9, 0.5)}  # (x, y[, yaw])
    back = landmarks.load(landmarks.save(tmp_path / "landmarks.json", marks))
    assert list(back) == [7, 1_000_003]
    assert back[7].tolist() == [0.1, 2e-9] and back[1_000_003].tolist() == [12.25, -3.5]
