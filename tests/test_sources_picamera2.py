"""picamera2 backend against the fake: two callback threads, sync, skew, drops, lost cameras."""

from __future__ import annotations

import importlib.util
import logging
import threading
import time

import pytest

from stereopath.device.errors import CaptureError
from stereopath.device.capture.sources import create_source
from stereopath.device.capture.sources.csi import LIBCAMERA_NAMES, PICAMERA2_NAMES, Picamera2Source
from tests.fakes.standins import source_settings, take
from tests.fakes.fake_picamera2 import FakeCameraSpec, FakeCameraWorld, decode_slot

pytestmark = pytest.mark.timeout(30)


def settings(**kw):
    return source_settings("picamera2", [64, 48], 500, **kw)



def assert_all_threads_stopped(world):
    for cam in world.instances:
        assert cam._thread is None or not cam._thread.is_alive()
    assert world.errors == []
    assert all(v == 0 for v in world.outstanding.values())  # every request buffer went back


def test_pairs_one_exposure_on_two_threads_and_releases_every_buffer():
    world = FakeCameraWorld(sync_ready_after=4)
    world.cameras[1].skew_ns = 40_000
    world.cameras[1].drop = frozenset({9, 10})
    world.cameras[0].drop = frozenset({14})
    src = create_source(settings(), api=world.api())
    with src:
        frames = take(src, 20)
        stats = src.stats
    assert [f.seq for f in frames] == list(range(20))
    slots = []
    for f in frames:
        (sl, side_l), (sr, side_r) = decode_slot(f.left), decode_slot(f.right)
        assert sl == sr and (side_l, side_r) == (0, 1)  # never across exposures, never swapped
        slots.append(sl)
        assert f.left.shape == (48, 64) and f.left.flags.owndata or f.left.base is not None
        # mid-exposure: SensorTimestamp taken as readout start, exposure 2 ms before
        assert f.meta["t_left_ns"] == f.meta["sensor_timestamp_left"] - 1_000_000
        assert f.t_ns == (f.meta["t_left_ns"] + f.meta["t_right_ns"]) // 2
        assert f.meta["skew_ns"] == 40_000
    assert slots[0] >= 4 and not {9, 10, 14} & set(slots)
    assert all(b > a for a, b in zip(slots, slots[1:]))
    assert stats.dropped_presync >= 2 * 4 - 2          # SyncReady false for the first grid slots
    assert stats.dropped_unpaired >= 3                 # partners of 9, 10 and 14
    assert stats.dropped_sensor >= 3                   # timestamp gaps seen per camera
    assert stats.max_skew_ns == 40_000
    # two different camera threads, neither of them ours
    t0, t1 = world.callback_threads[0], world.callback_threads[1]
    assert len(t0) == 1 and len(t1) == 1 and t0 != t1 and threading.get_ident() not in t0 | t1
    assert world.start_order[:2] == [1, 0]             # sync client (right) first
    c0, c1 = ({k: v for k, v in world.applied_controls[i].items() if k != "SyncMode"} for i in (0, 1))
    assert c0 == c1 and c0["ExposureTime"] == 2000 and c0["FrameDurationLimits"] == (10000, 10000)
    roles = [cam.camera_config["controls"]["SyncMode"].name for cam in world.instances]
    assert roles == ["Server", "Client"]
    assert_all_threads_stopped(world)


def test_exposure_start_convention_and_colour_lock():
    world = FakeCameraWorld()
    for c in world.cameras:
        c.mono = False
    src = Picamera2Source(settings(picamera2={"timestamp_is": "exposure_start", "colour_gains": [2.0, 1.5]}),
                          api=world.api())
    with src:
        f = take(src, 2)[-1]
    assert f.meta["t_left_ns"] == f.meta["sensor_timestamp_left"] + 1_000_000
    ctrl = world.applied_controls[0]
    assert ctrl["AwbEnable"] is False and ctrl["ColourGains"] == (2.0, 1.5) and ctrl["AeEnable"] is False
    assert_all_threads_stopped(world)


def test_cameras_chosen_by_id():
    world = FakeCameraWorld()
    ids = [c.id for c in world.cameras]
    src = Picamera2Source(settings(picamera2={"left_id": ids[1], "right_id": ids[0]}), api=world.api())
    with src:
        f = take(src, 2)[-1]
    assert decode_slot(f.left)[1] == 1 and decode_slot(f.right)[1] == 0
    with pytest.raises(CaptureError, match="not found"):
        Picamera2Source(settings(picamera2={"left_id": "/no/such"}), api=FakeCameraWorld().api()).open()


def test_missing_or_busy_camera_is_a_capture_error():
    world = FakeCameraWorld(cameras=[FakeCameraSpec("only")])
    with pytest.raises(CaptureError, match="need two cameras"):
        Picamera2Source(settings(), api=world.api()).open()
    world = FakeCameraWorld()
    world.cameras[1].present = False
    with pytest.raises(CaptureError, match="cannot open camera 1"):
        Picamera2Source(settings(), api=world.api()).open()
    assert world.instances[0].closed


def test_camera_disappearing_mid_run_raises_without_hanging():
    world = FakeCameraWorld(sync_ready_after=0)
    world.cameras[1].disappear_after = 8
    src = Picamera2Source(settings(), api=world.api())
    got = []
    t0 = time.monotonic()
    with pytest.raises(CaptureError, match=r"right camera .* (delivered no frame|never delivered)"):
        with src:
            for f in src:
                got.append(f)
    assert time.monotonic() - t0 < 5.0
    assert 5 <= len(got) <= 8
    assert_all_threads_stopped(world)


def test_free_running_cameras_out_of_tolerance_are_reported():
    world = FakeCameraWorld(free_run_phase_ns=4_000_000)
    for c in world.cameras:
        c.has_sync = False
    src = Picamera2Source(settings(), api=world.api())
    with pytest.raises(CaptureError, match="none pair within"):
        with src:
            take(src, 5)
    st = src.stats
    assert st.paired == 0 and st.dropped_unpaired > 0
    assert all("SyncMode" not in cam.camera_config["controls"] for cam in world.instances)
    assert_all_threads_stopped(world)


def test_free_running_cameras_within_tolerance_pair(caplog):
    world = FakeCameraWorld(free_run_phase_ns=100_000)
    for c in world.cameras:
        c.has_sync = False
    with caplog.at_level(logging.WARNING, logger="stereopath.device.capture.sources.csi"):
        with Picamera2Source(settings(), api=world.api()) as src:
            frames = take(src, 5)
    assert "no SyncMode" in caplog.text
    assert all(decode_slot(f.left)[0] == decode_slot(f.right)[0] for f in frames)


def test_slow_consumer_drops_oldest_pairs_and_buffers_stay_bounded():
    world = FakeCameraWorld(sync_ready_after=0)
    src = Picamera2Source(settings(queue_size=2), api=world.api())
    with src:
        it = iter(src)
        next(it)
        time.sleep(0.15)   # ~15 frames arrive meanwhile
        assert max(src._pairer.pending()[:2]) <= 8 and src._pairer.pending()[2] <= 2
        f = next(it)
        st = src.stats
    assert st.dropped_overflow >= 10
    assert f.seq == 1
    assert_all_threads_stopped(world)


def test_callback_error_reaches_the_consumer():
    world = FakeCameraWorld(sync_ready_after=0)
    src = Picamera2Source(settings(), api=world.api())

    class Broken:
        def __init__(self, *a, **k):
            raise ValueError("mapping failed")

    src._api_arg = world.api()
    src._api_arg.MappedArray = Broken
    with pytest.raises(CaptureError, match="callback failed.*mapping failed"):
        with src:
            take(src, 3)
    assert_all_threads_stopped(world)


def test_iterating_before_open_is_an_error():
    with pytest.raises(CaptureError, match="open"):
        iter(Picamera2Source(settings(), api=FakeCameraWorld().api()))


def _resolve(root, dotted):
    obj = root
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def test_fake_offers_every_name_the_backend_uses():
    api = FakeCameraWorld().api()
    for name in PICAMERA2_NAMES:
        _resolve(api, name)
    for name in LIBCAMERA_NAMES:
        _resolve(api, name)


@pytest.mark.skipif(importlib.util.find_spec("picamera2") is None, reason="picamera2 not installed")
def test_real_picamera2_has_the_names_we_use():  # pragma: no cover - only on a Pi
    import libcamera
    import picamera2

    for name in PICAMERA2_NAMES:
        _resolve(picamera2, name)
    for name in LIBCAMERA_NAMES:
        _resolve(libcamera, name)
