"""depthai backend against the fake: Sync groups, mid-exposure time, factory calibration, IMU, loss."""

from __future__ import annotations

import importlib.util
import logging
import time

import numpy as np
import pytest

from stereopath.device.errors import CaptureError
from stereopath.device.capture.sources import create_source
from stereopath.device.capture.sources.oak import DEPTHAI_NAMES, DepthaiSource, rig_from_calibration, timedelta_to_ns
from tests.fakes.standins import source_settings, take
from tests.fakes.fake_depthai import FakeOakWorld

pytestmark = pytest.mark.timeout(30)


def settings(**kw):
    return source_settings("depthai", [64, 40], 1000, **kw)



def index_of(img):
    return int.from_bytes(bytes(img[0, :4]), "little")


def test_frames_at_mid_exposure_with_sequence_gaps_counted():
    world = FakeOakWorld(right_skew_ns=30_000, drop_left=frozenset({3, 4}), drop_right=frozenset({8}))
    src = create_source(settings(depthai={"queue_size": 64}), dai=world.module())  # no host-side drops
    with src:
        frames = take(src, 12)
        imu = src.imu.read()
        st = src.stats
    idx = [index_of(f.left) for f in frames]
    assert idx == [index_of(f.right) for f in frames]
    assert not {3, 4, 8} & set(idx) and idx == sorted(idx)
    assert st.dropped_sensor == 3 and st.delivered == 12
    for f in frames:
        # fake: exposure ends at t0 + k*period + exposure; MIDDLE = end - exposure/2
        assert f.meta["t_right_ns"] - f.meta["t_left_ns"] == 30_000
        assert f.t_ns == (f.meta["t_left_ns"] + f.meta["t_right_ns"]) // 2
        assert f.left.dtype == np.uint8 and f.left.shape == (40, 64)
    dts = np.diff([f.meta["t_left_ns"] for f in frames])
    assert set(dts) <= {10_000_000, 20_000_000, 30_000_000}
    assert len(imu) > 0 and np.all(np.diff(imu.t_ns) > 0)
    assert np.allclose(imu.accel_m_s2[0], [0, -9.81, 0]) and np.allclose(imu.gyro_rad_s[0], [0.01, -0.02, 0.005])
    assert world.errors == [] and not world.pipelines[0].isRunning()


def test_pipeline_graph_matches_the_oak_d_mono_pair():
    world = FakeOakWorld(max_frames=3)
    with DepthaiSource(settings(depthai={"iso": 800, "sync_threshold_ms": 3.0}), dai=world.module()) as src:
        take(src, 1)
    p = world.pipelines[0]
    cams = [n for n in p._nodes if type(n).__name__ == "_Camera"]
    assert [c.socket.name for c in cams] == ["CAM_B", "CAM_C"]
    assert all(c.outputs[0][1] == (64, 40) and c.outputs[0][2].name == "GRAY8" and c.outputs[0][3] == 100.0
               for c in cams)
    assert all((c.initialControl.exposure_us, c.initialControl.iso) == (2000, 800) for c in cams)
    sync = [n for n in p._nodes if type(n).__name__ == "_Sync"][0]
    assert sync.threshold.total_seconds() == pytest.approx(0.003)
    assert set(sync.inputs) == {"left", "right"}
    imu = [n for n in p._nodes if type(n).__name__ == "_IMU"][0]
    assert imu.rate == 200 and {s.name for s in imu.sensors} == {"ACCELEROMETER_RAW", "GYROSCOPE_RAW"}


def test_factory_calibration_in_metres_as_T_cam1_cam0():
    world = FakeOakWorld()
    dai = world.module()
    rig = rig_from_calibration(dai.CalibrationHandler(world), dai, (640, 400))
    assert np.allclose(rig.T, [-0.075, 0, 0]) and rig.baseline_m == pytest.approx(0.075)
    assert np.allclose(rig.cam0.K, [[400, 0, 320], [0, 400, 200], [0, 0, 1]])
    assert rig.cam1.K[0, 0] == pytest.approx(401.0) and rig.cam0.dist.size == 14
    assert rig.T_body_cam0 is not None


def test_reversed_extrinsics_are_inverted_with_a_warning(caplog):
    from stereopath.device.core.geometry import so3_exp

    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.0, 0.0, 0.02]))
    T[:3, 3] = [0.075, 0.001, 0.0]  # a calibration whose CAM_B->CAM_C goes the other way
    world = FakeOakWorld(T_C_B_m=T.tolist())
    dai = world.module()
    with caplog.at_level(logging.WARNING, logger="stereopath.device.capture.sources.oak"):
        rig = rig_from_calibration(dai.CalibrationHandler(world), dai, (640, 400))
    assert "inverting" in caplog.text
    Ti = np.linalg.inv(T)
    assert np.allclose(rig.R, Ti[:3, :3], atol=1e-9) and np.allclose(rig.T, Ti[:3, 3]) and rig.T[0] < 0


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


def test_device_lost_mid_run_and_no_device():
    world = FakeOakWorld(disappear_after=6)
    src = DepthaiSource(settings(depthai={"queue_size": 64}), dai=world.module())
    got = []
    t0 = time.monotonic()
    with pytest.raises(CaptureError, match="lost the device|pipeline stopped"):
        with src:
            for f in src:
                got.append(f)
    assert time.monotonic() - t0 < 5 and len(got) == 6
    with pytest.raises(CaptureError, match="no OAK device"):
        DepthaiSource(settings(), dai=FakeOakWorld(device_present=False).module()).open()


def test_timedelta_conversion_is_exact():
    import datetime as dt

    assert timedelta_to_ns(dt.timedelta(days=2, seconds=3, microseconds=7)) == (2 * 86400 + 3) * 10**9 + 7000


def _resolve(root, dotted):
    obj = root
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def test_fake_offers_every_name_the_backend_uses():
    mod = FakeOakWorld().module()
    for name in DEPTHAI_NAMES:
        _resolve(mod, name)


@pytest.mark.skipif(importlib.util.find_spec("depthai") is None, reason="depthai not installed")
def test_real_depthai_has_the_names_we_use():  # pragma: no cover - needs the wheel
    import depthai

    for name in DEPTHAI_NAMES:
        _resolve(depthai, name)
