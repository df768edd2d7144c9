"""Dataset readers on the real data in ../shared/data, their error paths and open_source."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from stereopath.device.formats import open_asl, open_kitti, open_source, parse_spec, register_source
from stereopath.device.errors import CalibrationError, DatasetError


@pytest.fixture(scope="module")
def kitti(data_dir):
    return open_kitti(data_dir / "kitti_odometry" / "sequences" / "06")


def test_kitti_06_frames_sizes_calibration(kitti):
    assert len(kitti) == 51
    assert kitti.rig.cam0.size == (1226, 370)
    assert abs(kitti.rig.baseline_m - 0.537) < 1e-3
    assert kitti.rig.cam0.fx == pytest.approx(707.0912)
    assert kitti.imu is None
    f = kitti.frame(50)
    assert f.left.shape == (370, 1226) and f.right.shape == (370, 1226)
    assert f.left.dtype == np.uint8
    assert f.t_ns == kitti.t_ns[50] and f.seq == 50
    assert kitti.t_ns[0] == 0 and kitti.t_ns[1] == 104_498_900
    assert np.all(np.diff(kitti.t_ns) > 0)
    assert not np.array_equal(f.left, f.right)


def test_kitti_06_poses(kitti, data_dir):
    gt = kitti.groundtruth
    assert len(gt) == 51
    np.testing.assert_array_equal(gt.t_ns, kitti.t_ns)
    np.testing.assert_allclose(gt.T_world_cam[0], np.eye(4), atol=1e-5)
    last = np.loadtxt(data_dir / "kitti_odometry" / "poses" / "06.txt")[50].reshape(3, 4)
    np.testing.assert_allclose(gt.T_world_cam[50][:3], last)
    assert 50.0 < gt.path_length_m() < 70.0  # "about 60 m of driving"


def test_kitti_missing_image_dropped_with_one_warning(data_dir, tmp_path, caplog):
    src = data_dir / "kitti_odometry" / "sequences" / "06"
    seq = tmp_path / "sequences" / "06"
    for sub in ("image_0", "image_1"):
        (seq / sub).mkdir(parents=True)
        for i in range(3):
            shutil.copy(src / sub / f"{i:06d}.png", seq / sub)
    (seq / "image_1" / "000001.png").unlink()
    shutil.copy(src / "calib.txt", seq)
    (seq / "times.txt").write_text("0.0\n0.1\n0.2\n")
    with caplog.at_level(logging.WARNING):
        s = open_kitti(seq)
    assert len(s) == 2 and s.index == [0, 2]
    assert list(s.t_ns) == [0, 200_000_000]
    assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1
    assert s.groundtruth is None  # no poses/06.txt two levels up


def test_euroc_head_pairs_and_one_warning(data_dir, caplog):
    with caplog.at_level(logging.WARNING):
        s = open_asl(data_dir / "euroc_v1_01_head" / "mav0")
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1
    msg = warnings[0].getMessage()
    assert "99" in msg and "95" in msg
    assert len(s) == 95
    assert s.rig.cam0.size == (752, 480)
    assert abs(s.rig.baseline_m - 0.110) < 2e-3
    f = s.frame(94)
    assert f.left.shape == (480, 752) and f.left.dtype == np.uint8
    assert f.t_ns == 1403715277962142976
    assert s.frame(-1).t_ns == f.t_ns


def test_euroc_imu_and_groundtruth(data_dir):
    s = open_asl(data_dir / "euroc_v1_01_head")  # the folder containing mav0 works too
    imu = s.imu
    assert len(imu) == 29120
    assert imu.t_ns[0] == 1403715273262142976
    np.testing.assert_allclose(imu.gyro_rad_s[0], [-0.0020943951023931952, 0.017453292519943295, 0.07749261878854824])
    g = np.linalg.norm(imu.accel_m_s2[:200], axis=1).mean()
    assert 9.6 < g < 10.0
    gt = s.groundtruth
    assert len(gt) == 2895
    # camera pose = body pose @ T_BS(cam0)
    from stereopath.device.formats.tum import read_tum

    body = read_tum(data_dir / "euroc_v1_01_head" / "groundtruth_tum.txt")
    np.testing.assert_allclose(gt.T_world_cam[10], body.T_world_cam[10] @ s.rig.T_body_cam0)
    # the camera sits at the lever arm of T_BS from the body origin (about 6.9 cm)
    lever = np.linalg.norm(gt.positions[0] - body.positions[0])
    assert lever == pytest.approx(np.linalg.norm(s.rig.T_body_cam0[:3, 3])) and 0.06 < lever < 0.08


def _mini_euroc(data_dir: Path, dst: Path, n: int = 3) -> Path:
    """A small copy of the EuRoC head: n frames, 50 IMU rows (the shared data stays untouched)."""
    src = data_dir / "euroc_v1_01_head" / "mav0"
    m = dst / "mav0"
    for cam in ("cam0", "cam1"):
        (m / cam / "data").mkdir(parents=True)
        shutil.copy(src / cam / "sensor.yaml", m / cam)
        lines = (src / cam / "data.csv").read_text().splitlines(keepends=True)[: n + 1]
        (m / cam / "data.csv").write_text("".join(lines))
        for line in lines[1:]:
            shutil.copy(src / cam / "data" / line.strip().split(",")[1], m / cam / "data")
    (m / "imu0").mkdir()
    shutil.copy(src / "imu0" / "sensor.yaml", m / "imu0")
    lines = (src / "imu0" / "data.csv").read_text().splitlines(keepends=True)[:51]
    (m / "imu0" / "data.csv").write_text("".join(lines))
    return m


def test_mini_copy_reads_cleanly(data_dir, tmp_path, caplog):
    m = _mini_euroc(data_dir, tmp_path)
    with caplog.at_level(logging.WARNING):
        s = open_asl(m)
        assert len(s.imu) == 50
        frames = list(s.frames())
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(frames) == 3 and s.groundtruth is None


def test_missing_folders_raise(data_dir, tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        open_asl(tmp_path / "nope")
    m = _mini_euroc(data_dir, tmp_path)
    shutil.rmtree(m / "cam1")
    with pytest.raises(DatasetError, match="cam1"):
        open_asl(m)
    with pytest.raises(DatasetError, match="image_0"):
        open_kitti(tmp_path)
    with pytest.raises(DatasetError, match="not found"):
        open_kitti(tmp_path / "nope")


def test_malformed_csv_row_names_file_and_line(data_dir, tmp_path):
    m = _mini_euroc(data_dir, tmp_path)
    p = m / "cam0" / "data.csv"
    lines = p.read_text().splitlines(keepends=True)
    lines[2] = "1403715273312143104;1403715273312143104.png\n"
    p.write_text("".join(lines))
    with pytest.raises(DatasetError, match=r"cam0/data\.csv:3: expected 2"):
        open_asl(m)
    lines[2] = "14037152733x2143104,1403715273312143104.png\n"
    p.write_text("".join(lines))
    with pytest.raises(DatasetError, match=r"data\.csv:3: timestamp is not an integer"):
        open_asl(m)


def test_malformed_imu_row(data_dir, tmp_path):
    m = _mini_euroc(data_dir, tmp_path)
    p = m / "imu0" / "data.csv"
    lines = p.read_text().splitlines(keepends=True)
    lines[5] = lines[5].replace(",", ",abc", 1)
    p.write_text("".join(lines))
    s = open_asl(m)
    with pytest.raises(DatasetError, match=r"imu0/data\.csv:6: column 2 is not a number"):
        _ = s.imu


def test_torn_final_line_is_ignored_but_not_a_broken_middle_line(data_dir, tmp_path, caplog):
    m = _mini_euroc(data_dir, tmp_path)
    p = m / "imu0" / "data.csv"
    text = p.read_text()
    p.write_text(text + "1403715273512142976,-0.0013962634015954637,0.01954")  # no newline
    with caplog.at_level(logging.WARNING):
        assert len(open_asl(m).imu) == 50
    assert any("no newline" in r.getMessage() for r in caplog.records)
    lines = text.splitlines(keepends=True)
    lines[10] = lines[10][:30] + "\n"  # a complete but cut line in the middle is an error
    p.write_text("".join(lines))
    with pytest.raises(DatasetError, match=r"data\.csv:11: expected 7"):
        _ = open_asl(m).imu


def test_undecodable_image_raises(data_dir, tmp_path):
    m = _mini_euroc(data_dir, tmp_path)
    name = sorted((m / "cam1" / "data").iterdir())[1]
    name.write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")
    s = open_asl(m)
    s.frame(0)
    with pytest.raises(DatasetError, match="cannot be decoded"):
        s.frame(1)


def test_image_size_must_match_calibration(data_dir, tmp_path):
    import cv2

    m = _mini_euroc(data_dir, tmp_path)
    name = sorted((m / "cam0" / "data").iterdir())[0]
    cv2.imwrite(str(name), np.zeros((10, 20), np.uint8))
    with pytest.raises(DatasetError, match="20x10"):
        open_asl(m).frame(0)


def test_broken_sensor_yaml_raises_calibration_error(data_dir, tmp_path):
    m = _mini_euroc(data_dir, tmp_path)
    (m / "cam0" / "sensor.yaml").write_text("%YAML:1.0\nintrinsics: [1, 2, 3, 4]\n")
    with pytest.raises(CalibrationError, match="T_BS"):
        open_asl(m)


def test_kitti_bad_times(data_dir, tmp_path):
    src = data_dir / "kitti_odometry" / "sequences" / "06"
    seq = tmp_path / "06"
    for sub in ("image_0", "image_1"):
        (seq / sub).mkdir(parents=True)
        shutil.copy(src / sub / "000000.png", seq / sub)
    shutil.copy(src / "calib.txt", seq)
    (seq / "times.txt").write_text("0.0\nzero\n")
    with pytest.raises(DatasetError, match=r"times\.txt:2"):
        open_kitti(seq)


def test_open_source_specs(data_dir):
    k = open_source(f"kitti:{data_dir / 'kitti_odometry' / 'sequences' / '06'}")
    assert len(k) == 51 and k.spec.startswith("kitti:")
    e = open_source(f"euroc:{data_dir / 'euroc_v1_01_head' / 'mav0'}")
    assert len(e) == 95
    assert parse_spec("session:/a:b") == ("session", "/a:b")
    with pytest.raises(DatasetError, match="unknown scheme"):
        open_source("tape:/x")
    with pytest.raises(DatasetError, match="SCHEME:ARG"):
        open_source("/just/a/path")
    with pytest.raises(DatasetError, match="needs a folder"):
        open_source("kitti:")
    with pytest.raises(DatasetError, match="not found"):
        open_source("session:/nonexistent/session")


def test_register_source_hook():
    calls = []
    register_source("fake", lambda arg: calls.append(arg) or "SEQ")
    try:
        assert open_source("fake:7") == "SEQ" and calls == ["7"]
    finally:
        from stereopath.device.formats import source

        source._OPENERS.pop("fake")
