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
    world = FakeCameraWorld()
    world.cameras[1].skew_ns = 40_000
    # grid slots after SyncReady (30 frames, tests/fakes/standins.py)
    world.cameras[1].drop = frozenset({42, 43})
    world.cameras[0].drop = frozenset({48})
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
        assert f.left.shape == (48, 64) and f.left.flags.owndata  # a copy, not a view of a released buffer
        # mid-exposure: SensorTimestamp taken as readout start, exposure 2 ms before
        assert f.meta["t_left_ns"] == f.meta["sensor_timestamp_left"] - 1_000_000
        assert f.t_ns == (f.meta["t_left_ns"] + f.meta["t_right_ns"]) // 2
        assert f.meta["skew_ns"] == 40_000
    assert slots[0] >= 30 and not {42, 43, 48} & set(slots)
    assert all(b > a for a, b in zip(slots, slots[1:]))
    assert stats.dropped_presync >= 2 * 30 - 2         # SyncReady false for the first SyncFrames frames
    assert stats.dropped_unpaired >= 3                 # partners of 42, 43 and 48
    assert stats.dropped_sensor >= 3                   # timestamp gaps seen per camera
    assert stats.max_skew_ns == 40_000
    # two different camera threads, neither of them ours
    t0, t1 = world.callback_threads[0], world.callback_threads[1]
    assert len(t0) == 1 and len(t1) == 1 and t0 != t1 and threading.get_ident() not in t0 | t1
    assert world.start_order[:2] == [1, 0]             # sync client (right) first
    c0, c1 = ({k: v for k, v in world.applied_controls[i].items() if k not in ("SyncMode", "SyncFrames")}
              for i in (0, 1))
    assert c0 == c1 and c0["ExposureTime"] == 2000 and c0["FrameDurationLimits"] == (10000, 10000)
    roles = [cam.configured["controls"]["SyncMode"].name for cam in world.instances]
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
    busy_id = world.cameras[1].id
    # picamera2 says only "Camera __init__ sequence did not complete."; the reason is its __cause__
    with pytest.raises(CaptureError, match=r"cannot open the right camera .*imx296.*did not complete: "
                                           r"Failed to acquire camera: Device or resource busy") as info:
        Picamera2Source(settings(), api=world.api()).open()
    assert busy_id in str(info.value)
    assert world.instances[0].closed


def _libcamera_order_differs():
    """libcamera enumerates i2c@80000 first (Num 0); global_camera_info() sorts it second."""
    a = FakeCameraSpec("/base/axi/pcie@120000/rp1/i2c@80000/imx296@1a")
    b = FakeCameraSpec("/base/axi/pcie@120000/rp1/i2c@88000/imx296@1a")
    world = FakeCameraWorld(cameras=[a, b])
    info = world.api().Picamera2.global_camera_info()
    assert [i["Num"] for i in info] == [1, 0]  # position and Num differ
    return world, a.id, b.id


def test_cameras_are_opened_by_position_in_global_camera_info_not_by_num():
    world, id_num0, id_num1 = _libcamera_order_differs()
    src = Picamera2Source(settings(picamera2={"left_id": id_num0, "right_id": id_num1}), api=world.api())
    with src:
        f = take(src, 3)[-1]
    # the left frames come from the camera whose Id was configured as left (libcamera Num 0)
    assert decode_slot(f.left)[1] == 0 and decode_slot(f.right)[1] == 1
    assert [cam.spec.id for cam in world.instances] == [id_num0, id_num1]
    # unspecified ids: left is the first camera of global_camera_info(), right the second
    world, id_num0, id_num1 = _libcamera_order_differs()
    with Picamera2Source(settings(), api=world.api()) as src:
        f = take(src, 3)[-1]
    assert [cam.spec.id for cam in world.instances] == [id_num1, id_num0]
    assert decode_slot(f.left)[1] == 1 and decode_slot(f.right)[1] == 0


def test_fake_mirrors_picamera2_numbering_and_errors():
    world, id_num0, _ = _libcamera_order_differs()
    api = world.api()
    cam = api.Picamera2(world.position_of(id_num0))
    assert cam.num == 0 and cam.spec.id == id_num0
    with pytest.raises(RuntimeError, match="No camera number 2 found"):
        api.Picamera2(2)
    world.cameras[1].present = False
    with pytest.raises(RuntimeError, match=r"^Camera __init__ sequence did not complete\.$") as info:
        api.Picamera2(world.position_of(world.cameras[1].id))
    assert "Device or resource busy" in str(info.value.__cause__)
    cam.close()


def test_luma_is_cut_at_the_size_libcamera_chose(caplog):
    # libcamera adjusts 64x48 down to 48x40 (Status.Adjusted); the luma must come from that size,
    # never from rows of the chroma planes below it
    world = FakeCameraWorld(adjust_size=lambda s: (s[0] - 16, s[1] - 8))
    with caplog.at_level(logging.WARNING, logger="stereopath.device.capture.sources.csi"):
        with Picamera2Source(settings(), api=world.api()) as src:
            frames = take(src, 3)
    assert "adjusted the main stream from 64x48 to 48x40" in caplog.text
    for f in frames:
        assert f.left.shape == (40, 48) and f.right.shape == (40, 48)
        assert not (f.left[1:] == 128).all(axis=1).any()  # no chroma row (all 128) inside the luma
    assert_all_threads_stopped(world)


def test_cameras_configured_at_different_sizes_are_refused():
    world = FakeCameraWorld()
    sizes = iter([(64, 48), (48, 48)])
    world.adjust_size = lambda s: next(sizes)
    with pytest.raises(CaptureError, match="left camera at 64x48 and the right one at 48x48"):
        Picamera2Source(settings(), api=world.api()).open()
    assert all(cam.closed for cam in world.instances)


def test_frames_without_sync_ready_are_not_taken_as_synchronised():
    world = FakeCameraWorld()
    api = world.api()
    real_process = api.Picamera2._process_request

    def strip_sync_ready(self, req, tid):  # a platform whose metadata lacks SyncReady
        req._metadata.pop("SyncReady", None)
        return real_process(self, req, tid)

    api.Picamera2._process_request = strip_sync_ready
    src = Picamera2Source(settings(), api=api)
    with pytest.raises(CaptureError, match="never reported SyncReady"):
        with src:
            take(src, 2)
    assert src.stats.delivered == 0 and src.stats.dropped_presync > 0


def test_failed_buffers_never_reach_the_callback_and_callbacks_hold_the_camera_lock():
    world = FakeCameraWorld()
    world.cameras[0].failed = frozenset({44, 45})  # after SyncReady (about slot 34)
    with Picamera2Source(settings(), api=world.api()) as src:
        frames = take(src, 16)
        st = src.stats
    slots = [decode_slot(f.left)[0] for f in frames]
    assert not {44, 45} & set(slots) and world.failed_released[0] == 2
    assert st.dropped_sensor >= 2 and st.dropped_unpaired >= 2
    assert world.callback_lock_held == {0: True, 1: True}
    assert_all_threads_stopped(world)


def test_camera_disappearing_mid_run_raises_without_hanging():
    world = FakeCameraWorld()
    world.cameras[1].disappear_after = 40  # frames delivered, the ~30 before SyncReady included
    src = Picamera2Source(settings(), api=world.api())
    got = []
    t0 = time.monotonic()
    with pytest.raises(CaptureError, match=r"right camera .* (delivered no frame|never delivered)"):
        with src:
            for f in src:
                got.append(f)
    assert time.monotonic() - t0 < 5.0
    assert 3 <= len(got) <= 10
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
    assert all("SyncMode" not in cam.configured["controls"] for cam in world.instances)
    assert_all_threads_stopped(world)


def test_free_running_cameras_within_tolerance_pair(caplog):
    world = FakeCameraWorld(free_run_phase_ns=100_000)
    for c in world.cameras:
        c.has_sync = False
    with caplog.at_level(logging.WARNING, logger="stereopath.device.capture.sources.csi"):
        with Picamera2Source(settings(), api=world.api()) as src:
            frames = take(src, 5)
    assert "no SyncMode" in caplog.text
    assert len(frames) == 5
    assert all(decode_slot(f.left)[0] == decode_slot(f.right)[0] for f in frames)


def test_slow_consumer_drops_oldest_pairs_and_buffers_stay_bounded():
    world = FakeCameraWorld()
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
    world = FakeCameraWorld()
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
