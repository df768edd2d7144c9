"""Time alignment: IMU blocks per frame, interpolation at frame times, offset, waiting, gaps, monitor."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.capture.imu.base import OfflineImu
from stereopath.device.capture.timealign import RateMonitor, TimeAligner, align_stream, interpolate

FRAME_NS = 33_333_333
IMU_NS = 5_000_000


def imu_ramp(t0, t1, period=IMU_NS, drop=None):
    t = np.arange(t0, t1, period, dtype=np.int64)
    if drop is not None:
        t = t[(t < drop[0]) | (t > drop[1])]
    gyro = np.stack([t / 1e9, 2 * t / 1e9, -t / 1e9], axis=1)     # linear in time: exact interpolation
    accel = np.tile([0.0, 0.0, 9.81], (len(t), 1))
    return ImuSamples(t, gyro, accel)


def frames(n, t0=1_000_000_000, period=FRAME_NS, skip=()):
    out = []
    for i in range(n):
        if i in skip:
            continue
        out.append(StereoFrame(i, t0 + i * period, np.zeros((2, 2), np.uint8), np.zeros((2, 2), np.uint8), {}))
    return out


def test_each_frame_gets_exactly_the_interval_since_the_previous_one():
    imu = imu_ramp(900_000_000, 1_500_000_000)
    aligner = TimeAligner()
    aligner.add_imu(imu)
    out = []
    for f in frames(10):
        out += aligner.add_frame(f)
    assert len(out) == 10
    first = out[0].imu
    # the first frame gets the pre-roll: every sample before it (here from 0.9 s), then its own time
    assert first.t_ns[-1] == out[0].t_ns
    assert set(first.t_ns[:-1]) == {t for t in imu.t_ns if t < out[0].t_ns}
    for prev, f in zip(out, out[1:]):
        b = f.imu
        assert b.t_ns[0] == prev.t_ns and b.t_ns[-1] == f.t_ns
        inner = b.t_ns[1:-1]
        assert np.all((inner > prev.t_ns) & (inner < f.t_ns))
        assert set(inner) == {t for t in imu.t_ns if prev.t_ns < t < f.t_ns}
        assert np.allclose(b.gyro_rad_s[:, 1], 2 * b.t_ns / 1e9)      # interpolated ends are exact
        assert f.meta["imu_complete"] and not f.meta["imu_gap"]
        # the block integrates exactly over [t_prev, t_k]
        area = np.trapezoid(b.gyro_rad_s[:, 0], b.t_ns / 1e9)
        assert area == pytest.approx(((f.t_ns / 1e9) ** 2 - (prev.t_ns / 1e9) ** 2) / 2, rel=1e-9)


def test_time_offset_moves_imu_onto_the_camera_clock():
    offset = 7_000_000                                   # t_imu = t_cam + 7 ms
    cam_t = 1_100_000_000
    imu = imu_ramp(900_000_000 + offset, 1_300_000_000 + offset)
    aligner = TimeAligner(time_offset_ns=offset)
    aligner.add_imu(imu)
    f = aligner.add_frame(StereoFrame(0, cam_t, None, None, {}))[0]
    # the sample at camera time t carries the IMU value recorded at t + offset
    assert f.imu.gyro_rad_s[-1, 0] == pytest.approx((cam_t + offset) / 1e9)


def test_frames_wait_for_imu_then_give_up_after_max_wait():
    aligner = TimeAligner(max_wait_ns=90_000_000)
    fs = frames(6)
    assert aligner.add_frame(fs[0]) == [] and aligner.add_frame(fs[1]) == []
    aligner.add_imu(imu_ramp(900_000_000, fs[0].t_ns + 20_000_000))   # covers frame 0 only
    out = aligner.add_frame(fs[2])
    assert [f.seq for f in out] == [0]
    out = aligner.add_frame(fs[3]) + aligner.add_frame(fs[4])         # frame 1 waited > 90 ms
    assert [f.seq for f in out] == [1]
    assert out[0].meta["imu_complete"] is False and out[0].meta["imu_gap"] is True
    rest = aligner.flush()
    assert [f.seq for f in rest] == [2, 3, 4]


def test_gap_in_the_imu_is_flagged_on_the_frames_it_touches():
    t0 = 1_000_000_000
    imu = imu_ramp(900_000_000, 1_500_000_000, drop=(t0 + 2 * FRAME_NS + 1, t0 + 3 * FRAME_NS + 10_000_000))
    mon = RateMonitor(nominal_fps=30.0, nominal_imu_hz=200.0)
    aligner = TimeAligner(nominal_imu_hz=200.0, monitor=mon)
    aligner.add_imu(imu)
    out = []
    for f in frames(8):
        out += aligner.add_frame(f)
    flags = [f.meta["imu_gap"] for f in out]
    # frames 2..4 interpolate at or integrate across the missing stretch
    assert flags == [False, False, True, True, True, False, False, False]
    rep = mon.report()
    assert rep.imu_gaps == 1 and rep.imu_gap_s == pytest.approx(0.045, abs=0.006)


def test_monitor_reports_rates_and_dropped_frames():
    mon = RateMonitor(nominal_fps=30.0)
    for f in frames(31, period=FRAME_NS, skip={5, 6, 20}):
        mon.frame(f.t_ns)
    mon.imu(imu_ramp(0, 1_000_000_000, period=5_000_000))
    rep = mon.report()
    assert rep.frames == 28 and rep.dropped_frames == 3
    assert rep.camera_fps == pytest.approx(27 / (30 * FRAME_NS / 1e9), rel=1e-6)
    assert rep.imu_hz == pytest.approx(200.0, rel=1e-6) and rep.imu_gaps == 0


def test_monitor_without_nominal_rate_uses_the_median_step():
    mon = RateMonitor()
    for f in frames(20, skip={10}):
        mon.frame(f.t_ns)
    assert mon.report().dropped_frames == 1


def test_align_stream_with_a_replayed_imu():
    fs = frames(12)
    offline = OfflineImu(imu_ramp(900_000_000, 1_600_000_000), lookahead_ns=50_000_000)

    def source():
        for f in fs:
            offline.advance(f.t_ns)
            yield f

    out = list(align_stream(source(), offline))
    assert [f.seq for f in out] == list(range(12))
    assert all(f.meta["imu_complete"] for f in out)
    assert sum(len(f.imu) for f in out[1:]) == sum(1 for t in offline.samples.t_ns if fs[0].t_ns < t < fs[-1].t_ns) + 2 * 11


def test_interpolate_holds_outside_the_span():
    imu = imu_ramp(0, 50_000_000)
    s = interpolate(imu, 10**12)
    assert s.gyro_rad_s[0, 0] == imu.gyro_rad_s[-1, 0] and len(s) == 1


def test_aligner_from_the_settings_section():
    from stereopath.device.core.config import from_mapping
    from stereopath.device.settings import TimeAlignSettings

    a = TimeAligner.from_settings(from_mapping(TimeAlignSettings, {"time_offset_us": -2500.0, "max_wait_ms": 50.0}))
    assert (a.time_offset_ns, a.max_wait_ns, a.gap_factor) == (-2_500_000, 50_000_000, 2.5)
