"""Registries name every member their entry points declare, and import a member's module
only when that member is asked for (a dead-reckoning replay does not import gtsam)."""

import subprocess
import sys

import pytest

from hardware.errors import UnknownNameError
from hardware.registry import Registry, Spec

PROBE = """
import sys
from slam.base import LOCALIZERS
names = LOCALIZERS.names()
assert {"dead-reckoning", "gtsam", "fastslam", "grid-rbpf"} <= set(names), names
assert "slam.gtsam_smoother" not in sys.modules
spec = LOCALIZERS.spec("dead-reckoning")
assert spec.name == "dead-reckoning"
heavy = sorted(m for m in ("gtsam", "slam.gtsam_smoother", "slam.scan_matching",
                           "slam.fastslam", "slam.grid_rbpf", "scipy.stats") if m in sys.modules)
print(",".join(heavy))
"""


def test_naming_one_localizer_imports_only_its_module():
    res = subprocess.run(
        [sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120, check=False
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == ""


def test_members_added_in_code_and_unknown_names():
    reg: Registry = Registry("widget", "walker_slam.no_such_group")
    assert reg.names() == []
    reg.register("w", None, "a widget")(lambda: "made")
    assert reg.names() == ["w"] and reg.create("w") == "made"
    assert isinstance(reg.spec("w"), Spec)
    with pytest.raises(UnknownNameError, match="valid: w"):
        reg.spec("x")
