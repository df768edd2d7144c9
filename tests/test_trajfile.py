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
