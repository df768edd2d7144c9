import numpy as np
import pytest

from stereopath.device.errors import DatasetError
from stereopath.device.core.geometry import make_pose, so3_exp
from stereopath.device.formats.tum import (
    Trajectory, ns_to_seconds_str, read_kitti_poses, read_trajectory, read_tum, seconds_to_ns, write_tum,
)


def test_seconds_ns_exact():
    assert seconds_to_ns("1403715273.262142976") == 1403715273262142976
    assert ns_to_seconds_str(1403715273262142976) == "1403715273.262142976"
    assert seconds_to_ns(ns_to_seconds_str(-5)) == -5


def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    Ts = np.array([make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3)) for _ in range(20)])
    t = 1_000_000_000 + np.arange(20, dtype=np.int64) * 50_000_001
    write_tum(tmp_path / "a.tum", Trajectory(t, Ts))
    back = read_tum(tmp_path / "a.tum")
    assert np.array_equal(back.t_ns, t)
    assert np.allclose(back.T_world_cam, Ts, atol=1e-8)
    assert read_trajectory(tmp_path / "a.tum").t_ns[0] == t[0]


def test_kitti_poses(data_dir):
    tr = read_kitti_poses(data_dir / "kitti_odometry/poses/06.txt")
    assert len(tr) == 51 and np.allclose(tr.T_world_cam[0], np.eye(4), atol=1e-6)
    assert tr.path_length_m() == pytest.approx(59.9, abs=0.5)


@pytest.mark.parametrize("text, match", [
    ("1 2 3\n", ":1: expected 8"),
    ("# c\n0 0 0 0 0 0 0 1\n0 0 x 0 0 0 0 1\n", ":3: non-numeric"),
    ("0 0 0 0 0 0 0 0\n", "zero quaternion"),
    ("# only a comment\n", "no poses"),
])
def test_malformed_tum(tmp_path, text, match):
    (tmp_path / "b.tum").write_text(text)
    with pytest.raises(DatasetError, match=match):
        read_tum(tmp_path / "b.tum")


def test_missing_file(tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        read_trajectory(tmp_path / "nope.txt")


KITTI_ROW = "1 0 0 0.0 0 1 0 0 0 0 1 0\n"


def test_kitti_poses_reject_non_finite_values(tmp_path):
    (tmp_path / "k.txt").write_text(KITTI_ROW + "1 0 0 nan 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match=r"k\.txt:2: non-finite value"):
        read_kitti_poses(tmp_path / "k.txt")
    (tmp_path / "k.txt").write_text(KITTI_ROW + "1 0 0 0.1 0 1 0 0 0 0 1 -inf\n")
    with pytest.raises(DatasetError, match=r"k\.txt:2: non-finite value"):
        read_trajectory(tmp_path / "k.txt")


@pytest.mark.parametrize("stamp", ["inf", "-Infinity", "nan", "1e30", "1e999999999"])
def test_tum_timestamp_must_be_finite_and_fit_int64_ns(tmp_path, stamp):
    (tmp_path / "t.tum").write_text(f"0 0 0 0 0 0 0 1\n{stamp} 0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"t\.tum:2: time .* not finite or outside"):
        read_trajectory(tmp_path / "t.tum")


def test_seconds_to_ns_range():
    assert seconds_to_ns("9223372036.854775807") == 2**63 - 1
    assert seconds_to_ns("-9223372036.854775808") == -2**63
    with pytest.raises(ValueError):
        seconds_to_ns("9223372036.854775808")
    with pytest.raises(ValueError):
        seconds_to_ns("inf")


@pytest.mark.parametrize("reader", [read_trajectory, read_kitti_poses, read_tum])
def test_folder_or_binary_pose_file_is_a_dataset_error(tmp_path, reader):
    with pytest.raises(DatasetError, match="is a directory"):
        reader(tmp_path)
    (tmp_path / "b.tum").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe" * 8)
    with pytest.raises(DatasetError, match="not a UTF-8 text file"):
        reader(tmp_path / "b.tum")
