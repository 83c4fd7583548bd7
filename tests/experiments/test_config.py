"""experiments.config.propose: a source's settings for a plain config (the mapper's)."""

from __future__ import annotations

import pytest

from experiments.config import propose
from hardware.errors import ConfigError
from mapping.mapper import MapperConfig
from mapping.scan_points import ScanConfig


def test_a_proposal_is_typed_and_applied_only_where_the_default_stands():
    got = propose(MapperConfig(), {"scan.max_range_m": "20", "scan.no_return_as_free": 1}, "mapper")
    assert got.scan == ScanConfig(max_range_m=20.0, no_return_as_free=True)
    chosen = MapperConfig(scan=ScanConfig(max_range_m=30.0))
    assert propose(chosen, {"scan.max_range_m": 20.0}, "mapper").scan.max_range_m == 30.0
    assert propose(chosen, {}, "mapper") is chosen


@pytest.mark.parametrize(
    ("proposed", "message"),
    [
        ({"scan.range": 20.0}, "mapper has no field 'range' in its scan"),
        ({"scan": 20.0}, "mapper.scan is a group of settings"),
        ({"scan.max_range_m": "far"}, "mapper.scan.max_range_m: 'far' is not a float"),
    ],
)
def test_a_bad_proposal_names_the_field(proposed, message):
    with pytest.raises(ConfigError, match=message):
        propose(MapperConfig(), proposed, "mapper")
