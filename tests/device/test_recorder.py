"""Session recorder: layout, round trip, crash safety, disk reserve."""

from __future__ import annotations

import errno
import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections import namedtuple

import numpy as np
import pytest

from stereopath.device.formats import recorder as recmod
from stereopath.device.formats import open_session, open_source
from stereopath.device.errors import CaptureError
from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.core.geometry import make_pose, rot_x, rot_z
from stereopath.device.formats.recorder import RecorderHooks, SessionRecorder, record_sequence
from stereopath.device.core.rig import make_camera, make_rig, paper_rig
from stereopath.device.formats.rig_files import load_euroc_rig
from stereopath.device.formats.tum import Trajectory

Usage = namedtuple("Usage", "total used free")
PLENTY = lambda _p: Usage(10**12, 0, 10**12)  # noqa: E731


def small_rig():
    K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    cam = make_camera("cam0", K, [0.01, -0.002, 0.0005, 0.0001, 0.0], (64, 48))
    return make_rig(cam, cam, rot_z(0.01), [-0.05, 0.001, 0.002], name="small",
                    T_body_cam0=make_pose(rot_x(0.2), [0.01, -0.02, 0.03]))


def make_frames(n, rng, shape=(48, 64)):
    return [StereoFrame(i, 10**18 + i * 50_000_000, rng.integers(0, 256, shape, dtype=np.uint8),
                        rng.integers(0, 256, shape, dtype=np.uint8)) for i in range(n)]


def make_imu(n, rng, temp=True):
    return ImuSamples(10**18 + np.arange(n, dtype=np.int64) * 5_000_000, rng.normal(size=(n, 3)) * 0.1,
                      rng.normal(size=(n, 3)) + [0, 0, 9.81], 25 + rng.normal(size=n) if temp else None)


def clocked_recorder(out, chunk_s=1.0):
    """A recorder on a plentiful disk whose flush clock the test sets (``t[0]``): rows are written when it
    passes ``chunk_s``."""
    t = [0.0]
    return SessionRecorder(out, small_rig(), chunk_s=chunk_s, hooks=RecorderHooks(disk_usage=PLENTY, clock=lambda: t[0])), t



def test_round_trip_layout_and_manifest(tmp_path):
    rng = np.random.default_rng(1)
    rig = small_rig()
    frames, imu = make_frames(6, rng), make_imu(61, rng)
    out = tmp_path / "s"
    with SessionRecorder(out, rig, {"estimator": "stereo", "n": 3}, session_id="abc", hooks=RecorderHooks(disk_usage=PLENTY)) as rec:
        assert rec.state == "recording" and rec.session_id == "abc"
        for k, f in enumerate(frames):
            rec.add_imu(imu.between(f.t_ns - 50_000_000 if k else -1, f.t_ns))
            assert rec.add_frame(f)
            rec.add_pose(f.t_ns, make_pose(rot_z(0.1 * k), [k * 0.1, 0, 0]))
        rec.add_imu(imu.between(frames[-1].t_ns, 2 * 10**18))
        rec.write_groundtruth(Trajectory([f.t_ns for f in frames], np.repeat(np.eye(4)[None], 6, axis=0)))
    assert rec.state == "closed"
    header = (out / "mav0" / "imu0" / "data.csv").read_text().splitlines()[0]
    assert header == ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                      "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
    assert (out / "mav0" / "cam0" / "data.csv").read_text().splitlines()[1] == f"{10**18},{10**18}.png"
    assert (out / "mav0" / "cam1" / "data" / f"{10**18}.png").is_file()
    assert not list(out.rglob("*.tmp"))
    man = json.loads((out / "manifest.json").read_text())
    from stereopath.device import __version__

    assert man["session_id"] == "abc" and man["status"] == "closed" and man["software_version"] == __version__
    assert man["rig"] == "small" and man["configuration"] == {"estimator": "stereo", "n": 3}
    assert man["counts"]["frames"] == 6 and man["counts"]["imu_samples"] == 61 and man["counts"]["poses"] == 6

    s = open_source(f"session:{out}")
    assert len(s) == 6 and s.manifest["session_id"] == "abc"
    for a, b in zip(frames, s.frames()):
        assert a.t_ns == b.t_ns
        np.testing.assert_array_equal(a.left, b.left)
        np.testing.assert_array_equal(a.right, b.right)
    np.testing.assert_array_equal(s.imu.t_ns, imu.t_ns)
    np.testing.assert_array_equal(s.imu.gyro_rad_s, imu.gyro_rad_s)  # repr precision: exact
    np.testing.assert_array_equal(s.imu.accel_m_s2, imu.accel_m_s2)
    np.testing.assert_array_equal(s.imu.temp_c, imu.temp_c)
    assert len(s.groundtruth) == 6
    est = s.trajectory
    assert len(est) == 6
    np.testing.assert_allclose(est.T_world_cam[3], make_pose(rot_z(0.3), [0.3, 0, 0]), atol=1e-8)
    # the rig: our rig.yaml exactly, and the EuRoC sensor.yaml files agree with it
    np.testing.assert_array_equal(s.rig.R, rig.R)
    np.testing.assert_array_equal(s.rig.cam0.dist, rig.cam0.dist)
    e = load_euroc_rig(out / "mav0")
    np.testing.assert_allclose(e.R, rig.R, atol=1e-12)
    np.testing.assert_allclose(e.T, rig.T, atol=1e-12)
    np.testing.assert_allclose(e.T_body_cam0, rig.T_body_cam0, atol=1e-12)
    np.testing.assert_allclose(e.cam0.K, rig.cam0.K)


def test_refuses_non_empty_folder(tmp_path):
    (tmp_path / "x").write_text("hello")
    with pytest.raises(CaptureError, match="not empty"):
        SessionRecorder(tmp_path, small_rig(), hooks=RecorderHooks(disk_usage=PLENTY))


def test_refuses_to_start_below_reserve(tmp_path):
    out = tmp_path / "s"
    with pytest.raises(CaptureError, match="below the reserve"):
        SessionRecorder(out, small_rig(), reserve_bytes=100 * 2**20, hooks=RecorderHooks(disk_usage=lambda p: Usage(1, 1, 50 * 2**20)))
    assert not out.exists()


def test_stops_cleanly_when_disk_runs_low(tmp_path, caplog):
    free = [10**9]
    rng = np.random.default_rng(2)
    out = tmp_path / "s"
    rec = SessionRecorder(out, small_rig(), reserve_bytes=10**8, hooks=RecorderHooks(disk_usage=lambda p: Usage(0, 0, free[0])))
    frames = make_frames(8, rng)
    for f in frames[:4]:
        assert rec.add_frame(f)
    rec.add_imu(make_imu(20, rng))
    free[0] = 10**8 - 1
    with caplog.at_level(logging.WARNING):
        assert rec.add_frame(frames[4]) is False
        assert rec.state == "stopped_low_disk"
        assert rec.add_frame(frames[5]) is False
        assert rec.add_imu(make_imu(3, rng)) is False
        assert rec.add_pose(1, np.eye(4)) is False
    rec.close()
    assert rec.state == "stopped_low_disk"
    assert any("below the reserve" in r.getMessage() for r in caplog.records)
    s = open_session(out)
    assert len(s) == 4 and len(s.imu) == 20
    assert s.manifest["status"] == "stopped_low_disk"
    assert s.manifest["counts"]["frames"] == 4 and s.manifest["counts"]["dropped_frames"] == 2


def test_disk_full_during_flush_stops(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    rec, t = clocked_recorder(tmp_path / "s")
    frames = make_frames(3, rng)
    rec.add_frame(frames[0])
    real = recmod._write_all

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(recmod, "_write_all", full)
    t[0] = 2.0
    assert rec.add_frame(frames[1]) is False
    assert rec.state == "stopped_low_disk"
    monkeypatch.setattr(recmod, "_write_all", real)
    rec.close()
    assert json.loads((tmp_path / "s" / "manifest.json").read_text())["status"] == "stopped_low_disk"


def test_other_io_error_is_a_capture_error(tmp_path, monkeypatch):
    rec = SessionRecorder(tmp_path / "s", small_rig(), hooks=RecorderHooks(disk_usage=PLENTY))
    rec.add_frame(make_frames(1, np.random.default_rng(0))[0])

    def broken(fd, data):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(recmod, "_write_all", broken)
    with pytest.raises(CaptureError, match="Input/output error"):
        rec.flush()
    assert rec.state == "error"


def test_chunked_flush_by_clock(tmp_path):
    t = [0.0]
    rng = np.random.default_rng(4)
    out = tmp_path / "s"
    rec = SessionRecorder(out, small_rig(), chunk_s=1.0, hooks=RecorderHooks(disk_usage=PLENTY, clock=lambda: t[0]))
    csv = out / "mav0" / "cam0" / "data.csv"
    frames = make_frames(4, rng)
    rec.add_frame(frames[0])
    rec.add_frame(frames[1])
    assert len(csv.read_text().splitlines()) == 1  # header only: rows wait for the chunk
    t[0] = 1.0
    rec.add_frame(frames[2])  # the chunk is due: all three rows become durable
    assert len(csv.read_text().splitlines()) == 4
    rec.add_frame(frames[3])
    rec.close()
    assert len(csv.read_text().splitlines()) == 5


def test_out_of_order_frames_and_imu_are_dropped(tmp_path):
    rng = np.random.default_rng(5)
    rec = SessionRecorder(tmp_path / "s", small_rig(), hooks=RecorderHooks(disk_usage=PLENTY))
    f = make_frames(2, rng)
    assert rec.add_frame(f[1])
    assert rec.add_frame(f[0]) is False
    imu = make_imu(10, rng)
    rec.add_imu(imu)
    rec.add_imu(imu.slice(5, 10))  # repeated samples
    rec.close()
    assert rec.counts["dropped_frames"] == 1 and rec.counts["dropped_imu_samples"] == 5
    s = open_session(tmp_path / "s")
    assert len(s) == 1 and len(s.imu) == 10


WRITER = textwrap.dedent("""
    import sys, numpy as np
    sys.path.insert(0, sys.argv[2])
    from tests.device.test_recorder import small_rig, make_imu, PLENTY
    from stereopath.device.formats.recorder import RecorderHooks
    from stereopath.device.core.frames import StereoFrame
    from stereopath.device.formats.recorder import SessionRecorder
    rng = np.random.default_rng(0)
    rec = SessionRecorder(sys.argv[1], small_rig(), chunk_s=0.02, hooks=RecorderHooks(disk_usage=PLENTY))
    i = 0
    while True:
        t = 10**18 + i * 50_000_000
        rec.add_imu(make_imu(10, rng).__class__(t - 50_000_000 + np.arange(1, 11) * 5_000_000,
                                                 rng.normal(size=(10, 3)), rng.normal(size=(10, 3))))
        rec.add_frame(StereoFrame(i, t, rng.integers(0, 256, (48, 64), dtype=np.uint8),
                                  rng.integers(0, 256, (48, 64), dtype=np.uint8)))
        rec.add_pose(t, np.eye(4))
        i += 1
""")


def test_crash_mid_chunk_leaves_parseable_files(tmp_path, repo_root, caplog):
    out = tmp_path / "crash"
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(out), str(repo_root)], cwd=repo_root)
    try:
        # cam1's rows are flushed after cam0's (FLUSH_ORDER): a kill between the two leaves cam0 ahead,
        # and a pair is listed only when both rows are durable, so wait on the later file
        csv = out / "mav0" / "cam1" / "data.csv"
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if csv.is_file() and csv.read_text().count("\n") > 41:
                break
            if proc.poll() is not None:
                pytest.fail(f"writer exited early with {proc.returncode}")
            time.sleep(0.05)
        else:
            pytest.fail("writer produced no rows")
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    with caplog.at_level(logging.WARNING):
        s = open_session(out)
        n = len(s)
        assert n >= 40
        for f in s.frames():  # every listed image exists and decodes
            assert f.left.shape == (48, 64)
        imu = s.imu
        est = s.trajectory
    assert s.manifest["status"] == "recording"
    assert any("not closed" in r.getMessage() for r in caplog.records)
    # IMU rows are made durable before the frame rows of the same chunk: every frame has its IMU
    assert len(imu) >= 10 * n and imu.t_ns[-1] >= s.t_ns[-1]
    assert np.all(np.diff(imu.t_ns) > 0)
    assert est is None or len(est) <= n + 1  # poses follow their frames (at most one chunk behind)


def test_record_sequence_converts_a_dataset(data_dir, tmp_path):
    src = open_source(f"kitti:{data_dir / 'kitti_odometry' / 'sequences' / '06'}")
    man = record_sequence(src, tmp_path / "k", max_frames=3, hooks=RecorderHooks(disk_usage=PLENTY))
    assert man["counts"]["frames"] == 3
    s = open_session(tmp_path / "k")
    assert len(s) == 3 and s.imu is not None and len(s.imu) == 0
    np.testing.assert_array_equal(s.frame(2).right, src.frame(2).right)
    np.testing.assert_allclose(s.groundtruth.T_world_cam, src.groundtruth.T_world_cam, atol=1e-8)
    assert abs(s.rig.baseline_m - src.rig.baseline_m) < 1e-12


def test_paper_rig_session_sensor_yaml_readable(tmp_path):
    rig = paper_rig()
    SessionRecorder(tmp_path / "p", rig, hooks=RecorderHooks(disk_usage=PLENTY)).close()
    e = load_euroc_rig(tmp_path / "p" / "mav0")
    np.testing.assert_allclose(e.T, rig.T, atol=1e-12)
    np.testing.assert_allclose(e.T_body_cam0, np.eye(4))


def test_disk_full_on_an_image_keeps_the_rows_of_the_frames_already_on_disk(tmp_path, monkeypatch):
    """ENOSPC while writing frame 5's image: frames 0-4 (images on disk, rows still queued) stay readable with
    their IMU samples and poses, and the manifest counts what the files hold."""
    rng = np.random.default_rng(5)
    rec, t = clocked_recorder(tmp_path / "s", chunk_s=100.0)
    frames = make_frames(6, rng)
    rec.add_imu(make_imu(30, rng))
    for f in frames[:5]:
        assert rec.add_frame(f)
        rec.add_pose(f.t_ns, np.eye(4))
    real = SessionRecorder._write_image

    def full(path, blob):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(SessionRecorder, "_write_image", staticmethod(full))
    assert rec.add_frame(frames[5]) is False
    monkeypatch.setattr(SessionRecorder, "_write_image", staticmethod(real))
    rec.close()
    s = open_session(tmp_path / "s")
    assert len(s) == 5 and len(s.imu) == 30 and len(s.trajectory) == 5
    m = s.manifest
    assert m["status"] == "stopped_low_disk" and m["counts"]["frames"] == 5 and m["counts"]["imu_samples"] == 30


@pytest.mark.parametrize("cam,cut_short", [("cam0", True), ("cam1", False)])
def test_rows_that_do_not_fit_are_cut_back_whole_and_taken_off_the_counts(tmp_path, monkeypatch, cam, cut_short):
    """A row write cut short by a full disk leaves no half row (a later row would be glued onto it and the whole
    file would no longer read); a frame is lost when either camera's row is (cam0's rows written, cam1's not),
    and the frames lost are taken off the manifest's counts."""
    rng = np.random.default_rng(6)
    rec, t = clocked_recorder(tmp_path / "s")
    frames = make_frames(4, rng)
    assert rec.add_frame(frames[0]) and rec.add_frame(frames[1])
    rec.flush()
    assert rec.add_frame(frames[2])
    real_write = os.write
    fd_full = rec._fds[cam]

    def full(fd, data):
        if fd != fd_full:
            return real_write(fd, data)
        if cut_short and len(data) > 8:
            return real_write(fd, bytes(data[: len(data) // 2]))
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(recmod.os, "write", full)
    t[0] = 2.0
    assert rec.add_frame(frames[3]) is False
    monkeypatch.setattr(recmod.os, "write", real_write)
    rec.close()
    text = (tmp_path / "s" / "mav0" / cam / "data.csv").read_text()
    assert text.endswith("\n") and all(len(line.split(",")) == 2 for line in text.splitlines()[1:])
    s = open_session(tmp_path / "s")
    assert len(s) == 2
    assert s.manifest["counts"]["frames"] == 2 and s.manifest["counts"]["frames_lost_disk_full"] == 2


def test_sensor_yaml_numbers_read_back_as_numbers(tmp_path, caplog):
    """Python writes 2e-05, which YAML 1.1 reads as text: the IMU noise and any tiny pose entry must be written
    so that they read back as numbers; sessions written before are still read (a numeric text is taken)."""
    import yaml

    from stereopath.device.formats.rig_files import MPU6050_NOISE, imu_sensor_yaml, load_imu_noise, yaml_float

    for v in (2e-05, 1e-17, -1.5e-300, 3.0, 200.0, 0.1, float("inf"), float("nan")):
        back = yaml.safe_load(yaml_float(v))
        assert isinstance(back, float) and (back == v or (v != v and back != back))
    p = tmp_path / "sensor.yaml"
    p.write_text(imu_sensor_yaml(200.0, MPU6050_NOISE))
    with caplog.at_level(logging.WARNING):
        assert load_imu_noise(p) == {k: float(v) for k, v in MPU6050_NOISE.items()}
    assert "not a positive number" not in caplog.text
    p.write_text(p.read_text().replace(yaml_float(MPU6050_NOISE["gyroscope_random_walk"]), "2e-05"))
    assert load_imu_noise(p)["gyroscope_random_walk"] == 2e-05  # an older session's text


def test_disk_full_on_an_image_fsync_writes_no_row_for_those_frames(tmp_path, monkeypatch):
    """A durable row always points at a durable image: when the images' fsync fails, their frames' rows are not
    written by the stop's salvage (the IMU rows are), and the counts say so."""
    rng = np.random.default_rng(7)
    rec, t = clocked_recorder(tmp_path / "s")
    frames = make_frames(3, rng)
    rec.add_imu(make_imu(10, rng))
    assert rec.add_frame(frames[0])
    rec.flush()
    assert rec.add_frame(frames[1])
    real_fsync = os.fsync
    row_fds = set(rec._fds.values())

    def fsync(fd):  # the images' fsync fails (a full disk found at write-back), the rows' would not
        if fd not in row_fds:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_fsync(fd)

    monkeypatch.setattr(recmod.os, "fsync", fsync)
    t[0] = 2.0
    assert rec.add_frame(frames[2]) is False  # its flush fsyncs frames 1 and 2's images: fails
    monkeypatch.setattr(recmod.os, "fsync", real_fsync)
    rec.close()
    s = open_session(tmp_path / "s")
    assert len(s) == 1 and len(s.imu) == 10
    assert s.manifest["counts"]["frames"] == 1 and s.manifest["counts"]["frames_lost_disk_full"] == 2
