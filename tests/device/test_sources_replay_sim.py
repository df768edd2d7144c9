"""Replay and sim sources: order, timestamps, pacing on an injected clock, IMU release."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.core.config import from_mapping
from stereopath.device.errors import CaptureError
from stereopath.device.settings import SourceSettings
from stereopath.device.capture.sources import create_source
from tests.fakes.fake_smbus import SimClock
from tests.fakes.standins import StandinSequence, image_index

pytestmark = pytest.mark.timeout(60)


def replay_settings(**kw):
    return from_mapping(SourceSettings, {"backend": "replay", "replay": kw})


def test_replay_at_max_speed_keeps_recorded_times_and_releases_imu_with_the_frames():
    seq = StandinSequence(n=12)
    clock = SimClock()
    src = create_source(replay_settings(start=2, count=6), sequence=seq, clock_ns=clock.now_ns, sleep=clock.sleep)
    with src:
        assert src.rig is seq.rig
        frames, imu_ends = [], []
        for f in src:
            frames.append(f)
            block = src.imu.read()
            imu_ends.append(int(block.t_ns[-1]))
    assert [f.seq for f in frames] == list(range(6))
    assert [image_index(f.left) for f in frames] == list(range(2, 8)) == [f.meta["index"] for f in frames]
    assert [f.t_ns for f in frames] == [int(t) for t in seq.t_ns[2:8]]
    assert clock.now_ns() == 1_000_000_000          # max speed never sleeps
    # IMU released up to the frame time plus the 100 ms look-ahead, never beyond
    for f, end in zip(frames, imu_ends):
        assert f.t_ns <= end <= f.t_ns + 100_000_000
    assert src.stats.delivered == 6


def test_replay_at_recorded_speed_sleeps_to_the_timestamps():
    seq = StandinSequence(n=10, fps=20.0)
    clock = SimClock()
    src = create_source(replay_settings(speed="recorded"), sequence=seq, clock_ns=clock.now_ns, sleep=clock.sleep)
    host = []
    with src:
        for f in src:
            host.append(clock.now_ns())
    assert np.all(np.diff(host) == np.diff(seq.t_ns))


def test_replay_errors():
    with pytest.raises(CaptureError, match="no sequence configured"):
        create_source(replay_settings()).open()
    with pytest.raises(CaptureError, match="start frame 50"):
        create_source(replay_settings(start=50), sequence=StandinSequence(n=5)).open()
    with pytest.raises(CaptureError, match="not found|ASL"):
        create_source(replay_settings(path="euroc:/nonexistent/folder")).open()


@pytest.mark.realdata
def test_replay_of_the_euroc_head(data_dir):
    src = create_source(replay_settings(path=f"euroc:{data_dir / 'euroc_v1_01_head'}", count=3))
    with src:
        frames = list(src)
        imu = src.imu.read()
    assert len(frames) == 3 and frames[0].left.shape == (480, 752)
    assert int(frames[0].t_ns) == 1403715273262142976
    assert len(imu) > 0 and imu.t_ns[-1] <= frames[-1].t_ns + 100_000_000


def sim_settings(**kw):
    return from_mapping(SourceSettings, {"backend": "sim", "sim": kw})


def test_sim_source_paced_at_a_rate():
    sess = StandinSequence(n=8, fps=20.0)
    clock = SimClock()
    src = create_source(sim_settings(frames=8, rate_hz=10.0), session=sess, clock_ns=clock.now_ns, sleep=clock.sleep)
    host = []
    with src:
        for f in src:
            host.append(clock.now_ns())
        assert src.imu is not None
    assert np.all(np.diff(host) == 100_000_000)
    assert sess.loaded == list(range(8))


def test_sim_source_with_the_real_simulator():
    src = create_source(sim_settings(frames=3, seed=1))
    with src:
        frames = list(src)
        imu = src.imu.read() if src.imu is not None else None
    assert len(frames) == 3 and np.all(np.diff([f.t_ns for f in frames]) > 0)
    assert frames[0].left.shape == frames[0].right.shape
    assert src.rig is not None
    assert imu is not None and len(imu) > 0  # the simulated rig has its IMU


def _rig_file_at(tmp_path, size):
    """The stand-in sequence's rig written as a rig YAML for cameras of ``size`` (same intrinsics)."""
    from stereopath.device.core.rig import make_camera, make_rig
    from stereopath.device.formats.rig_files import save_rig_yaml

    rig = StandinSequence(n=2).rig
    cams = [make_camera(n, c.K, c.dist, size) for n, c in (("cam0", rig.cam0), ("cam1", rig.cam1))]
    path = tmp_path / f"rig_{size[0]}x{size[1]}.yaml"
    save_rig_yaml(make_rig(*cams, rig.R, rig.T), path)
    return path


def test_replay_refuses_a_pinhole_rig_file_for_another_image_size(tmp_path):
    from stereopath.device.errors import CalibrationError

    seq = StandinSequence(n=4)
    w, h = seq.rig.cam0.size
    wrong = _rig_file_at(tmp_path, (2 * w, 2 * h))
    src = create_source(from_mapping(SourceSettings, {"backend": "replay", "rig_file": str(wrong), "replay": {}}),
                        sequence=seq)
    with pytest.raises(CalibrationError, match=f"cam0 is calibrated at {2 * w}x{2 * h} but the replay source delivers {w}x{h}"):
        src.open()
    right = _rig_file_at(tmp_path, (w, h))  # the same rig at the images' size is taken
    src = create_source(from_mapping(SourceSettings, {"backend": "replay", "rig_file": str(right), "replay": {}}),
                        sequence=seq)
    with src:
        assert src.rig.cam0.size == (w, h) and len(list(src)) == 4
