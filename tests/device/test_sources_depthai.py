"""depthai backend against the real depthai 3.x run host-side (Sync node, ImgFrame, MessageQueue,
CalibrationHandler, ImgTransformation), with only the device nodes stood in for (tests/fakes/fake_depthai.py)."""

from __future__ import annotations

import datetime as dt
import logging
import time

import numpy as np
import pytest

pytest.importorskip("depthai")

from stereopath.device.errors import CaptureError  # noqa: E402
from stereopath.device.capture.sources import create_source  # noqa: E402
from stereopath.device.capture.sources.oak import (  # noqa: E402
    DEPTHAI_NAMES, DepthaiImu, DepthaiSource, crop_scale_intrinsics, rig_from_calibration, timedelta_to_ns)
from tests.fakes.standins import source_settings, take  # noqa: E402
from tests.fakes.fake_depthai import FakeOakWorld  # noqa: E402

pytestmark = pytest.mark.timeout(60)


def settings(size=(64, 40), **kw):
    return source_settings("depthai", list(size), 1000, **kw)


def index_of(img):
    return int.from_bytes(bytes(img[0, :4]), "little")


def crop_and_scale_truth(K, out_size, sensor=(1280, 800)):
    """Independent truth for ImgResizeMode.CROP: centred crop to the output's aspect, then scale."""
    (sw, sh), (w, h) = sensor, out_size
    s = max(w / sw, h / sh)                     # the crop is what the scaled sensor overfills
    x0, y0 = (sw - w / s) / 2, (sh - h / s) / 2
    fx, fy, cx, cy = K[0][0], K[1][1], K[0][2], K[1][2]
    return np.array([[fx * s, 0, (cx - x0) * s], [0, fy * s, (cy - y0) * s], [0, 0, 1]])


def test_frames_at_mid_exposure_with_sequence_gaps_counted():
    world = FakeOakWorld(right_skew_ns=30_000, drop_left=frozenset({3, 4}), drop_right=frozenset({8}))
    src = create_source(settings(depthai={"queue_size": 64}), dai=world.module())  # no host-side drops
    with src:
        frames = take(src, 12)
        time.sleep(0.05)
        imu = src.imu.read()
        st = src.stats
    idx = [index_of(f.left) for f in frames]
    assert idx == [index_of(f.right) for f in frames]
    assert not {3, 4, 8} & set(idx) and idx == sorted(idx)
    assert st.dropped_sensor == 3 and st.delivered == 12
    for f in frames:
        # the real ImgFrame: timestamp = end of exposure, MIDDLE = end - exposure/2 (2 ms here)
        assert f.meta["t_right_ns"] - f.meta["t_left_ns"] == 30_000
        assert f.t_ns == (f.meta["t_left_ns"] + f.meta["t_right_ns"]) // 2
        assert f.left.dtype == np.uint8 and f.left.shape == (40, 64)
    dts = np.diff([f.meta["t_left_ns"] for f in frames])
    assert set(dts) <= {10_000_000, 20_000_000, 30_000_000}
    assert len(imu) > 0 and np.all(np.diff(imu.t_ns) > 0)
    assert all(not p.isRunning() for p in world.pipelines)


def test_pipeline_graph_matches_the_oak_d_mono_pair():
    import depthai as dai

    world = FakeOakWorld(max_frames=30)
    with DepthaiSource(settings(depthai={"iso": 800, "sync_threshold_ms": 3.0}), dai=world.module()) as src:
        take(src, 1)
        p = world.pipelines[0]
        syncs = [n for n in p.getAllNodes() if isinstance(n, dai.node.Sync)]
    assert sorted(world.cameras) == ["CAM_B", "CAM_C"]
    for cam in world.cameras.values():
        assert cam.request["size"] == (64, 40) and cam.request["type"] == dai.ImgFrame.Type.GRAY8
        assert cam.request["fps"] == 100.0 and cam.request["resizeMode"] == dai.ImgResizeMode.CROP
        assert cam.request["enableUndistortion"] is False     # the rig carries the distortion: raw images
        ctl = cam.initialControl
        assert ctl.getExposureTime() == dt.timedelta(microseconds=2000) and ctl.getSensitivity() == 800
    assert len(syncs) == 1 and syncs[0].getSyncThreshold() == dt.timedelta(milliseconds=3)
    imu = world.imus[0]
    assert imu.rate == 200
    # the reports in the IMU frame that getCameraToImuExtrinsics refers to, not the chip's native axes
    assert {s.name for s in imu.sensors} == {"ACCELEROMETER_CALIBRATED", "GYROSCOPE_CALIBRATED"}


@pytest.mark.parametrize("size", [(640, 480), (640, 400), (640, 360)])
def test_intrinsics_match_the_crop_and_scale_of_the_output(size):
    world = FakeOakWorld(max_frames=20)
    with DepthaiSource(settings(size=size), dai=world.module()) as src:
        rig = src.rig
    for cam, name in ((rig.cam0, "CAM_B"), (rig.cam1, "CAM_C")):
        truth = crop_and_scale_truth(world.K_full[name], size)
        # the device crops whole pixels (1067 of 1066.67 columns at 640x480): within 0.35 px
        assert np.allclose(cam.K, truth, atol=0.35), (size, cam.K, truth)
    if size == (640, 480):
        assert rig.cam0.K[0, 0] == pytest.approx(480.0, abs=0.2)   # not the 400 of a width-only scale


@pytest.mark.parametrize("size", [(640, 480), (640, 400), (640, 360)])
def test_crop_scale_fallback_matches_depthai_own_transformation(size):
    import depthai as dai

    from tests.fakes.fake_depthai import sensor_transformation

    K = FakeOakWorld().K_full["CAM_B"]
    ours = crop_scale_intrinsics(K, (1280, 800), size)
    assert np.allclose(ours, crop_and_scale_truth(K, size), atol=1e-9)
    theirs = np.asarray(sensor_transformation(K, size, dai.ImgResizeMode.CROP).getIntrinsicMatrix())
    assert np.allclose(ours, theirs, atol=0.35)


def test_frames_without_a_transformation_fall_back_to_the_cropped_calibration(caplog):
    world = FakeOakWorld(max_frames=20)
    world.K_full = dict(world.K_full)
    dai = world.module()
    cal = world.calibration()
    with caplog.at_level(logging.INFO):
        rig = rig_from_calibration(cal, dai, (640, 480))
    assert np.allclose(rig.cam0.K, crop_and_scale_truth(world.K_full["CAM_B"], (640, 480)), atol=1e-9)
    assert np.allclose(rig.T, [-0.075, 0, 0], atol=1e-6) and rig.baseline_m == pytest.approx(0.075, abs=1e-6)
    assert rig.cam0.dist.size == 14 and rig.cam0.dist[0] == pytest.approx(-0.1)
    assert rig.T_body_cam0 is not None


def test_camera_to_imu_extrinsics_come_from_the_real_handler():
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T[:3, 3] = [0.01, 0.02, 0.005]                     # IMU -> CAM_B, as setImuExtrinsics stores it
    world = FakeOakWorld(T_camB_imu_m=T.tolist())
    rig = rig_from_calibration(world.calibration(), world.module(), (640, 400))
    assert np.allclose(rig.T_body_cam0, np.linalg.inv(T), atol=1e-6)   # cam0 -> IMU = T_body_cam0
    rig = rig_from_calibration(FakeOakWorld(T_camB_imu_m=None).calibration(), world.module(), (640, 400))
    assert rig.T_body_cam0 is None


def test_imu_in_the_imu_frame_with_accelerometer_interpolated_to_gyro_times():
    world = FakeOakWorld(max_frames=40)
    samples = []
    with DepthaiSource(settings(), dai=world.module()) as src:
        for _ in take(src, 20):
            samples.append(src.imu.read())
        time.sleep(0.1)
        samples.append(src.imu.read())
    t = np.concatenate([s.t_ns for s in samples])
    g = np.concatenate([s.gyro_rad_s for s in samples])
    a = np.concatenate([s.accel_m_s2 for s in samples])
    assert t.size > 20 and np.all(np.diff(t) == 5_000_000) and src.imu.gaps == []
    truth = [world.imu_truth(x / 1e9) for x in t]
    # gyro and accel in the IMU frame (the chip's native axes would swap and negate x/y);
    # the accelerometer, reported 1.3 ms after each gyro sample, interpolated to the gyro's time
    assert np.allclose(g, [tr[0] for tr in truth], atol=1e-5)
    assert np.allclose(a, [tr[1] for tr in truth], atol=1e-5)


def test_imu_reader_holds_gyro_samples_until_the_accelerometer_covers_them():
    import depthai as dai

    def packet(tg, ta, gx, ax):
        pk = dai.IMUPacket()
        g, a = dai.IMUReportGyroscope(), dai.IMUReportAccelerometer()
        for rep, t, v in ((g, tg, gx), (a, ta, ax)):
            ts = dai.Timestamp()
            ts.sec, ts.nsec = t // 10**9, t % 10**9
            rep.timestamp, rep.x = ts, v
        pk.gyroscope, pk.acceleroMeter = g, a
        return pk

    class Q:
        def __init__(self):
            self.batches = []

        def tryGetAll(self):
            out, self.batches = self.batches, []
            return out

    q = Q()
    imu = DepthaiImu(q, 200.0)
    base = 10**9
    msg = dai.IMUData()
    msg.packets = [packet(base, base + 1_000_000, 1.0, 10.0), packet(base + 5_000_000, base + 6_000_000, 2.0, 20.0)]
    q.batches = [msg]
    s1 = imu.read()
    # t=base precedes the first accelerometer report: dropped; base+5 ms: accel interpolated 10..20 at 4/5
    assert s1.t_ns.tolist() == [base + 5_000_000] and s1.accel_m_s2[0, 0] == pytest.approx(18.0)
    msg = dai.IMUData()
    msg.packets = [packet(base + 10_000_000, base + 6_000_000, 3.0, 20.0)]  # stale accel report repeated
    q.batches = [msg]
    assert len(imu.read()) == 0                 # not covered by the accelerometer yet: held
    msg = dai.IMUData()
    msg.packets = [packet(base + 15_000_000, base + 16_000_000, 4.0, 40.0)]
    q.batches = [msg]
    s3 = imu.read()
    assert s3.t_ns.tolist() == [base + 10_000_000, base + 15_000_000]
    assert s3.gyro_rad_s[:, 0].tolist() == [3.0, 4.0]
    assert s3.accel_m_s2[:, 0] == pytest.approx([20.0 + 20.0 * 4 / 10, 20.0 + 20.0 * 9 / 10])


def test_a_group_missing_a_camera_is_counted_not_fatal():
    import depthai as dai

    world = FakeOakWorld(max_frames=30)
    src = DepthaiSource(settings(), dai=world.module())
    with src:
        partial = dai.MessageGroup()
        partial["left"] = src._first["left"]
        with pytest.raises(IndexError, match="map::at"):  # what the real MessageGroup raises
            partial["right"]
        src._first = partial                              # delivered next, as if from the Sync node
        frames = take(src, 2)
        st = src.stats
    assert len(frames) == 2 and st.dropped_unpaired == 1


def test_reversed_extrinsics_are_inverted_with_a_warning(caplog):
    from stereopath.device.core.geometry import so3_exp

    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.0, 0.0, 0.02]))
    T[:3, 3] = [0.075, 0.001, 0.0]  # a calibration whose CAM_B->CAM_C goes the other way
    world = FakeOakWorld(T_C_B_m=T.tolist())
    with caplog.at_level(logging.WARNING, logger="stereopath.device.capture.sources.oak"):
        rig = rig_from_calibration(world.calibration(), world.module(), (640, 400))
    assert "inverting" in caplog.text
    Ti = np.linalg.inv(T)
    assert np.allclose(rig.R, Ti[:3, :3], atol=1e-6) and np.allclose(rig.T, Ti[:3, 3], atol=1e-6) and rig.T[0] < 0


def test_implausible_baseline_is_rejected():
    world = FakeOakWorld(T_C_B_m=[[1, 0, 0, -7.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    with pytest.raises(CaptureError, match="baseline 7.5"):
        DepthaiSource(settings(), dai=world.module()).open()
    assert not world.pipelines[0].isRunning()


def test_skew_beyond_tolerance_is_dropped_not_paired():
    world = FakeOakWorld(right_skew_ns=2_000_000, max_frames=6)  # Sync threshold 5 ms lets it through
    src = DepthaiSource(settings(), dai=world.module())
    with pytest.raises(CaptureError, match="no synchronised frame pair"):
        with src:
            take(src, 3)
    assert src.stats.delivered == 0 and src.stats.dropped_unpaired == 12


def test_device_lost_mid_run_closes_the_real_queues_and_no_device():
    world = FakeOakWorld(disappear_after=6)
    src = DepthaiSource(settings(depthai={"queue_size": 64}), dai=world.module())
    got = []
    with pytest.raises(CaptureError, match="lost the device|pipeline stopped"):
        with src:
            for f in src:
                got.append(f)
    assert world.lost and 5 <= len(got) <= 6
    with pytest.raises(CaptureError, match="no OAK device.*No available devices"):
        DepthaiSource(settings(), dai=FakeOakWorld(device_present=False).module()).open()


def test_real_library_behaviours_the_backend_relies_on():
    """What the stand-in leaves to depthai itself, checked on the installed wheel."""
    import depthai as dai

    class Idle(dai.node.ThreadedHostNode):
        def __init__(self):
            super().__init__()
            self.out = self.createOutput()

        def run(self):
            while self.isRunning():
                time.sleep(0.005)

    p = dai.Pipeline(False)
    with pytest.raises(RuntimeError, match="host only"):
        p.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
    sync = p.create(dai.node.Sync)
    sync.setRunOnHost(True)
    p.create(Idle).out.link(sync.inputs["left"])   # a Sync node needs an input to run
    q = sync.out.createOutputQueue()
    assert q.getMaxSize() == 16 and q.getBlocking() is False      # createOutputQueue defaults
    assert q.get(timeout=dt.timedelta(milliseconds=10)) is None   # timeout -> None
    with pytest.raises(IndexError, match="map::at"):
        dai.MessageGroup()["left"]                                # a missing group key
    p.start()
    p.stop()
    p.wait()
    with pytest.raises(Exception, match="closed") as info:
        q.get()
    assert type(info.value).__name__ == "QueueException"          # stop() closes the queues
    cal = dai.CalibrationHandler()
    cal.setCameraIntrinsics(dai.CameraBoardSocket.CAM_B, [[800.0, 0, 640], [0, 800.0, 400], [0, 0, 1]], 1280, 800)
    # the width-only scaling that made the backend's K wrong at 640x480
    assert cal.getCameraIntrinsics(dai.CameraBoardSocket.CAM_B, 640, 480)[0][0] == pytest.approx(400.0)


def test_real_request_output_takes_enable_undistortion():
    import depthai as dai

    doc = dai.node.Camera.requestOutput.__doc__
    assert "enableUndistortion: Optional[bool] = None" in doc   # None leaves it to the device: we pass False


def test_host_clock_steps_are_counted_and_frame_times_stay_increasing(caplog):
    # at 100 fps: +25 ms from frame 10 on, then -35 ms from frame 20 on: frames 20-22 fall at or before
    # frame 19's time (190, 200, 210 against 215 ms)
    world = FakeOakWorld(clock_steps={10: 25_000_000, 20: -35_000_000})
    src = create_source(settings(depthai={"queue_size": 64}), dai=world.module())
    with caplog.at_level(logging.WARNING), src:
        frames = take(src, 28)
        st = src.stats
    t = [f.t_ns for f in frames]
    assert all(b > a for a, b in zip(t, t[1:]))
    idx = [index_of(f.left) for f in frames]
    assert idx == list(range(20)) + list(range(23, 31))
    assert st.clock_steps == 2 and st.dropped_clock == 6 and st.dropped_unpaired == 0
    steps = [r.getMessage() for r in caplog.records if "stepped by" in r.getMessage()]
    assert len(steps) == 2 and "+25.00 ms" in steps[0] and "-35.00 ms" in steps[1]


def test_timedelta_conversion_is_exact():
    assert timedelta_to_ns(dt.timedelta(days=2, seconds=3, microseconds=7)) == (2 * 86400 + 3) * 10**9 + 7000


def _resolve(root, dotted):
    obj = root
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def test_real_depthai_has_the_names_we_use():
    import depthai

    for name in DEPTHAI_NAMES:
        _resolve(depthai, name)
        _resolve(FakeOakWorld().module(), name)
