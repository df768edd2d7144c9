"""Integers in the ASL CSV files must fit int64 (the arrays they go into), with file and line in the error."""

from __future__ import annotations

from pathlib import Path

import pytest

from stereopath.device.errors import DatasetError
from stereopath.device.formats.asl import open_asl
from stereopath.device.formats.csvrows import parse_int
from tests.device.test_datasets import _mini_euroc


def test_parse_int_bounds_to_int64():
    p = Path("cam0/data.csv")
    assert parse_int(p, 2, "9223372036854775807") == 2**63 - 1
    assert parse_int(p, 2, "-9223372036854775808") == -2**63
    for text in ("9223372036854775808", "-9223372036854775809", "99999999999999999999999"):
        with pytest.raises(DatasetError, match=r"cam0/data\.csv:2: timestamp is out of the 64-bit integer range"):
            parse_int(p, 2, text)


@pytest.mark.parametrize("sensor", ["cam0", "imu0"])
def test_huge_timestamp_in_asl_csv_is_a_dataset_error(data_dir, tmp_path, sensor):
    m = _mini_euroc(data_dir, tmp_path)
    p = m / sensor / "data.csv"
    lines = p.read_text().splitlines(keepends=True)
    lines[1] = "99999999999999999999999," + lines[1].split(",", 1)[1]
    p.write_text("".join(lines))
    with pytest.raises(DatasetError, match=rf"{sensor}/data\.csv:2: timestamp is out of the 64-bit integer range"):
        open_asl(m).imu  # the IMU file is read on first use
