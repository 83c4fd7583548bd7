"""The dataset registry, the text-file reader and the MCAP import (synthetic files only)."""

from __future__ import annotations

import gzip
import itertools
import json

import numpy as np
import pytest
from datasets_testdata import (
    assert_same_messages,
    write_carmen,
    write_mrclam,
    write_mtrx5700,
    write_text,
    write_victoria_park,
)

from hardware.datasets import (
    DatasetError,
    UnknownNameError,
    available_formats,
    import_dataset,
    import_to_log,
    open_dataset,
)
from hardware.datasets.textio import find_file, read_table
from hardware.log import read_log
from hardware.messages import GroundTruthPose, LaserScan, RangeBearing, VelocityOdometry


def test_formats_are_registered():
    assert available_formats() == ["carmen", "mrclam", "mtrx5700", "victoria-park"]


def test_unknown_format_lists_the_valid_ones(tmp_path):
    with pytest.raises(UnknownNameError, match="carmen, mrclam, mtrx5700, victoria-park"):
        open_dataset("kitti", tmp_path)


def test_unknown_option_lists_the_valid_ones(tmp_path):
    with pytest.raises(DatasetError, match=r"unknown option 'robt' for mrclam; valid: robot"):
        open_dataset("mrclam", write_mrclam(tmp_path), robt=1)


def test_bad_option_value_is_a_dataset_error(tmp_path):
    with pytest.raises(DatasetError, match="groundtruth must be one of"):
        open_dataset("mrclam", write_mrclam(tmp_path), groundtruth="perfect")
    with pytest.raises(DatasetError, match="robot must be an integer"):
        open_dataset("mrclam", tmp_path, robot="one")


def test_int_option_from_a_command_line_string(tmp_path):
    ds = open_dataset("mrclam", write_mrclam(tmp_path), robot="2")
    assert ds.metadata["config"]["robot"] == 2


@pytest.mark.parametrize("gz", [False, True])
def test_read_table_plain_and_gzip(tmp_path, gz):
    p = write_text(tmp_path / "t.dat", "# header\r\n  1 \t 2.5 \r\n\r\n3\t-4e-1\r\n", gz)
    t = read_table(p, 2)
    assert np.array_equal(t.data, [[1.0, 2.5], [3.0, -0.4]])
    assert t.lines.tolist() == [2, 4]


def test_gzip_is_detected_from_the_content_not_the_name(tmp_path):
    p = tmp_path / "plain_name.dat"
    p.write_bytes(gzip.compress(b"1 2\n"))
    assert read_table(p, 2).data.tolist() == [[1.0, 2.0]]


def test_find_file_takes_the_gz_variant(tmp_path):
    write_text(tmp_path / "X.dat.gz", "1\n", gz=True)
    assert find_file(tmp_path, "X.dat") == tmp_path / "X.dat.gz"
    with pytest.raises(DatasetError, match=r"Y\.dat: missing file \(also looked for Y\.dat\.gz\)"):
        find_file(tmp_path, "Y.dat")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1 2\n3\n", r"line 2: expected 2 columns, got 1"),
        ("1 2\n3 x\n", r"line 2: not a number: 'x'"),
        ("1 2\n3 nan\n", r"line 2: not a finite number: 'nan'"),
        ("# only a header\n", r"no data rows"),
    ],
)
def test_malformed_tables_name_file_and_line(tmp_path, text, message):
    p = write_text(tmp_path / "bad.dat", text)
    with pytest.raises(DatasetError, match=message) as e:
        read_table(p, 2)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


def test_truncated_gzip_is_a_dataset_error(tmp_path):
    data = gzip.compress(("1 2\n" * 5000).encode())
    p = tmp_path / "cut.dat.gz"
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match="truncated or corrupt gzip"):
        read_table(p, 2)


def test_binary_file_is_a_dataset_error(tmp_path):
    p = tmp_path / "bin.dat"
    p.write_bytes(b"1 2\n\xff\xfe\x00\x01\n")
    with pytest.raises(DatasetError, match=r"bin\.dat: not a text file"):
        read_table(p, 2)


def _synthetic(kind: str, tmp_path):
    if kind == "mrclam":
        return open_dataset("mrclam", write_mrclam(tmp_path / "m"), robot=1)
    if kind == "carmen":
        return open_dataset("carmen", write_carmen(tmp_path / "c.log", gz=True))
    if kind == "mtrx5700":
        return open_dataset("mtrx5700", write_mtrx5700(tmp_path / "x", rows=120))
    return open_dataset("victoria-park", write_victoria_park(tmp_path / "v"))


@pytest.mark.parametrize("kind", ["mrclam", "carmen", "victoria-park", "mtrx5700"])
def test_import_to_log_round_trip(tmp_path, kind):
    ds = _synthetic(kind, tmp_path)
    out = tmp_path / "out" / "trial.mcap"
    summary = import_to_log(ds, out)
    messages = list(ds.messages())
    assert summary.messages == len(messages) == sum(ds.counts().values())
    assert summary.counts == {k: v for k, v in ds.counts().items() if v}
    trial = read_log(out)
    assert_same_messages(list(trial.messages()), messages)
    assert trial.calibration == ds.calibration
    assert trial.metadata == json.loads(json.dumps(ds.metadata))
    assert summary.to_dict()["path"] == str(out)


def test_messages_are_in_time_order_motion_first(tmp_path):
    ds = _synthetic("carmen", tmp_path)
    msgs = list(ds.messages())
    t = [m.t for m in msgs]
    assert t == sorted(t)
    rank = {VelocityOdometry: 0, GroundTruthPose: 1, LaserScan: 2, RangeBearing: 2}
    for a, b in itertools.pairwise(msgs):
        if a.t == b.t:
            assert rank[type(a)] <= rank[type(b)]
    # messages() can be iterated again, and filtered by type
    assert len(list(ds.messages())) == len(msgs)
    only = list(ds.messages([LaserScan]))
    assert only and all(isinstance(m, LaserScan) for m in only)


def test_import_dataset_opens_and_writes(tmp_path):
    folder = write_victoria_park(tmp_path / "v", gz=False)
    summary = import_dataset("victoria-park", folder, tmp_path / "vp.mcap")
    assert summary.counts == {"VelocityOdometry": 5, "RangeBearing": 3}
    assert read_log(tmp_path / "vp.mcap").metadata["config"]["format"] == "victoria-park"


def test_read_table_reads_a_number_as_python_does_in_every_form(tmp_path):
    """The compiled pass and the line-by-line one agree: spaces around delimiters, a
    trailing delimiter (dropped), underscores and exponents, bits as float() gives."""
    rows = ["0.1 , 2.5e-3 ,", " 3,1_0", "-0.30000000000000004,7.000000000000001e+300"]
    p = write_text(tmp_path / "t.csv", "\n".join(rows) + "\n")
    t = read_table(p, 2, delimiter=",")
    want = [[float(v) for v in r.split(",") if v.strip()] for r in rows]
    assert t.data.tobytes() == np.array(want).tobytes()
    assert t.lines.tolist() == [1, 2, 3]
    q = write_text(tmp_path / "t.dat", "\ufeff1 2\r\n\r\n# note\r\n0.1 1e-5\n")
    t = read_table(q, 2)
    assert t.data.tolist() == [[1.0, 2.0], [0.1, 1e-5]] and t.lines.tolist() == [1, 4]
