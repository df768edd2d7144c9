"""A fake of picamera2 + libcamera.controls with the real shapes, threads and failure modes.

``FakeCameraWorld(...)`` describes the cameras; ``world.api()`` returns the three names
the backend imports (``Picamera2``, ``MappedArray``, ``controls``).  Like the real
library:

* ``Picamera2.global_camera_info()`` lists dicts with ``Model``, ``Location``,
  ``Rotation``, ``Id``, ``Num``; ``Picamera2(num)`` indexes that list;
* ``create_video_configuration`` returns a configuration dict (``sensor`` accepts only
  ``output_size`` and ``bit_depth``); ``set_controls`` rejects controls not listed in
  ``camera_controls``;
* each started camera runs its own thread that calls ``post_callback(request)`` and then
  ``request.release()``; requests are reference counted (a release below zero raises
  ``RuntimeError`` like ``CompletedRequest``), and a camera whose ``buffer_count``
  requests are all held skips frames;
* metadata has ``SensorTimestamp`` (ns, ``time.monotonic_ns`` clock), ``ExposureTime``,
  ``FrameDuration``, ``AnalogueGain``, ``SyncReady``, ``FrameWallClock``;
* ``MappedArray(request, "main")`` maps the YUV420 buffer as ``(h*3//2, stride)``.

Emulated faults (per camera spec): a timestamp skew, frames that never arrive (``drop``),
``SyncReady`` false for the first ``sync_ready_after`` frames of the synchronised grid,
and a camera that disappears after ``disappear_after`` frames (its thread stops calling
back, as when a cable comes loose).  Each frame's luma encodes its grid slot in the first
row (``decode_slot``) so tests can check that a pair came from one exposure.
"""

from __future__ import annotations

import enum
import threading
import time
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np


class _SyncModeEnum(enum.Enum):
    Off = 0
    Server = 1
    Client = 2


controls = SimpleNamespace(rpi=SimpleNamespace(SyncModeEnum=_SyncModeEnum))


def encode_slot(img: np.ndarray, slot: int, side: int) -> None:
    row = np.frombuffer(int(slot).to_bytes(4, "little") + bytes([side]), np.uint8)
    img[0, :5] = row


def decode_slot(img: np.ndarray) -> tuple[int, int]:
    b = bytes(np.asarray(img[0, :5], np.uint8))
    return int.from_bytes(b[:4], "little"), b[4]


@dataclass
class FakeCameraSpec:
    id: str
    model: str = "imx296"
    location: int = 2
    mono: bool = True
    has_sync: bool = True
    skew_ns: int = 0                       # added to this camera's timestamps
    drop: frozenset[int] = frozenset()     # grid slots never delivered by this camera
    disappear_after: int | None = None     # stop calling back after this many delivered frames
    present: bool = True                   # False: Picamera2(num) fails (camera in use / broken)
    callback_delay_s: float = 0.0          # time the fake's thread spends before the callback


@dataclass
class FakeCameraWorld:
    cameras: list[FakeCameraSpec] = field(default_factory=lambda: [
        FakeCameraSpec("/base/axi/pcie@120000/rp1/i2c@88000/imx296@1a", location=2),
        FakeCameraSpec("/base/axi/pcie@120000/rp1/i2c@80000/imx296@1a", location=2),
    ])
    sync_ready_after: int = 5              # SyncReady false for the first N grid slots
    images: list[tuple[np.ndarray, np.ndarray]] | None = None  # pre-rendered (left, right) luma
    free_run_phase_ns: int = 7_000_000     # phase of the second camera when not synchronised
    max_frames: int | None = None          # stop every camera after this many slots

    def __post_init__(self) -> None:
        self.lock = threading.Lock()
        self.grid_t0: int | None = None
        self.start_order: list[int] = []
        self.callback_threads: dict[int, set[int]] = {}
        self.delivered: dict[int, int] = {}
        self.outstanding: dict[int, int] = {}
        self.skipped_no_buffer: dict[int, int] = {}
        self.errors: list[str] = []
        self.instances: list["_FakePicamera2"] = []
        self.applied_controls: dict[int, dict[str, Any]] = {}
        self._yuv_cache: dict[tuple[int, int, int, int], np.ndarray] = {}

    def api(self) -> SimpleNamespace:
        world = self

        class Picamera2(_FakePicamera2):
            _world = world

        return SimpleNamespace(Picamera2=Picamera2, MappedArray=MappedArray, controls=controls)

    # frame content ----------------------------------------------------------------------
    def yuv_buffer(self, num: int, slot: int, w: int, h: int, stride: int) -> np.ndarray:
        side = 0 if num == 0 else 1
        if self.images is not None:  # pre-rendered: build each YUV buffer once
            idx = slot % len(self.images)
            key = (num, idx, w, h)
            buf = self._yuv_cache.get(key)
            if buf is None:
                buf = np.full((h * 3 // 2, stride), 128, np.uint8)
                buf[:h, :w] = self.images[idx][side][:h, :w]
                buf.setflags(write=False)
                self._yuv_cache[key] = buf
            return buf
        buf = np.full((h * 3 // 2, stride), 128, np.uint8)
        ramp = ((np.arange(w) + slot * 3) % 256).astype(np.uint8)
        buf[:h, :w] = ramp[None, :]
        encode_slot(buf, slot, side)
        return buf


class _FakeRequest:
    def __init__(self, cam: "_FakePicamera2", metadata: dict[str, Any], buffer: np.ndarray) -> None:
        self.picam2 = cam
        self.request: Any = object()
        self.ref_count = 1
        self.config = cam.camera_config
        self._metadata = metadata
        self._buffer = buffer
        with cam._world.lock:
            cam._world.outstanding[cam.num] = cam._world.outstanding.get(cam.num, 0) + 1

    def acquire(self) -> None:
        with self.picam2._world.lock:
            if self.ref_count == 0:
                raise RuntimeError("CompletedRequest: acquiring lock with ref_count 0")
            self.ref_count += 1

    def release(self) -> None:
        world = self.picam2._world
        with world.lock:
            self.ref_count -= 1
            if self.ref_count < 0:
                world.errors.append("negative ref_count")
                raise RuntimeError("CompletedRequest: lock now has negative ref_count")
            if self.ref_count == 0:
                world.outstanding[self.picam2.num] -= 1
                self.request = None
                self.config = None

    def get_metadata(self) -> dict[str, Any]:
        if self.request is None:
            raise RuntimeError("request used after release")
        return dict(self._metadata)

    def make_array(self, name: str) -> np.ndarray:
        if self.request is None:
            raise RuntimeError("request used after release")
        if name != "main":
            raise RuntimeError(f"Stream {name!r} is not defined")
        return self._buffer.copy()


class MappedArray:
    def __init__(self, request: _FakeRequest, stream: str, reshape: bool = True, write: bool = True) -> None:
        self._request = request
        self._stream = stream
        self._write = write
        self._array: np.ndarray | None = None

    def __enter__(self) -> "MappedArray":
        if self._request.request is None:
            raise RuntimeError("MappedArray on a released request")
        if self._stream != "main":
            raise RuntimeError(f"Stream {self._stream!r} is not defined")
        a = self._request._buffer.view()
        if not self._write:
            a.setflags(write=False)
        self._array = a
        return self

    def __exit__(self, *exc: Any) -> None:
        self._array = None

    @property
    def array(self) -> np.ndarray | None:
        return self._array


class _FakePicamera2:
    _world: FakeCameraWorld

    @classmethod
    def global_camera_info(cls) -> list[dict[str, Any]]:
        return [{"Model": c.model, "Location": c.location, "Rotation": 0, "Id": c.id, "Num": i}
                for i, c in enumerate(cls._world.cameras)]

    def __init__(self, camera_num: int = 0) -> None:
        world = self._world
        if camera_num >= len(world.cameras):
            raise IndexError("list index out of range")
        self.spec = world.cameras[camera_num]
        if not self.spec.present:
            raise RuntimeError("Failed to acquire camera: Device or resource busy")
        self.num = camera_num
        self.camera_config: dict[str, Any] | None = None
        self.post_callback: Callable[[Any], None] | None = None
        self.pre_callback = None
        self.started = False
        self.closed = False
        self.controls: dict[str, Any] = {}
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        world.instances.append(self)
        cc: dict[str, Any] = {
            "ExposureTime": (14, 15534385, None), "AnalogueGain": (1.0, 251.1886444091797, None),
            "FrameDurationLimits": (16562, 15534444, None), "AeEnable": (False, True, None),
        }
        if self.spec.has_sync:
            cc["SyncMode"] = (0, 2, 0)
            cc["SyncFrames"] = (1, 1000000, 100)
        if not self.spec.mono:
            cc["AwbEnable"] = (False, True, None)
            cc["ColourGains"] = (0.0, 32.0, None)
        self.camera_controls = cc
        self.sensor_modes = [{"format": "R10_CSI2P", "size": (1456, 1088), "bit_depth": 10, "fps": 60.38,
                              "exposure_limits": (29, 15534385, None), "crop_limits": (0, 0, 1456, 1088)}]

    def create_video_configuration(self, main: dict[str, Any] | None = None, lores: Any = None, raw: Any = None,
                                   transform: Any = None, colour_space: Any = None, buffer_count: int = 6,
                                   controls: dict[str, Any] | None = None, display: Any = "main",
                                   encode: Any = "main", queue: bool = True, sensor: dict[str, Any] | None = None,
                                   use_case: str = "video") -> dict[str, Any]:
        main = dict(main or {})
        size = tuple(main.get("size", (1280, 720)))
        fmt = main.get("format", "XBGR8888")
        sensor = dict(sensor or {})
        bad = set(sensor) - {"output_size", "bit_depth"}
        if bad:
            raise RuntimeError(f"Unexpected sensor configuration keys {sorted(bad)}")
        stride = (size[0] + 63) // 64 * 64 if fmt in ("YUV420", "YVU420") else size[0] * 4
        return {"use_case": use_case, "main": {"size": size, "format": fmt, "stride": stride},
                "buffer_count": buffer_count, "queue": queue, "controls": dict(controls or {}),
                "sensor": sensor}

    def configure(self, config: dict[str, Any]) -> None:
        if self.started:
            raise RuntimeError("Camera must be stopped before configuring")
        self._check_controls(config.get("controls", {}))
        self.camera_config = config
        self.controls = dict(config.get("controls", {}))

    def _check_controls(self, ctrl: dict[str, Any]) -> None:
        for name in ctrl:
            if name not in self.camera_controls:
                raise RuntimeError(f"Control {name} is not advertised by libcamera")

    def set_controls(self, ctrl: dict[str, Any]) -> None:
        self._check_controls(ctrl)
        self.controls.update(ctrl)
        with self._world.lock:
            self._world.applied_controls[self.num] = dict(self.controls)

    def start(self) -> None:
        if self.camera_config is None:
            raise RuntimeError("Camera has not been configured")
        if self.started:
            return
        self.started = True
        self._stop.clear()
        with self._world.lock:
            self._world.start_order.append(self.num)
        self._thread = threading.Thread(target=self._run, name=f"fake-picamera2-{self.num}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        if not self.started:
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():
                self._world.errors.append(f"camera {self.num} thread did not stop")
        self.started = False

    def close(self) -> None:
        self.stop()
        self.closed = True

    # the camera thread ----------------------------------------------------------------------
    def _run(self) -> None:
        world, spec, cfg = self._world, self.spec, self.camera_config
        fd = self.controls.get("FrameDurationLimits", (33333, 33333))[0]
        period = int(fd) * 1000
        exposure_us = int(self.controls.get("ExposureTime", 8000))
        sync_role = self.controls.get("SyncMode")
        synced = sync_role in (_SyncModeEnum.Server, _SyncModeEnum.Client) and spec.has_sync
        w, h = cfg["main"]["size"]
        stride = cfg["main"]["stride"]
        now = time.monotonic_ns()
        with world.lock:
            if world.grid_t0 is None:
                world.grid_t0 = now + period
            t0 = world.grid_t0
        # synchronised cameras expose on one shared grid; free-running ones at a fixed phase offset
        base = t0 if synced else t0 + (world.free_run_phase_ns if self.num else 0)
        slot = max(0, -(-(now - base) // period))
        delivered = 0
        tid = threading.get_ident()
        while not self._stop.is_set():
            if world.max_frames is not None and slot >= world.max_frames:
                break
            t_frame = base + slot * period + spec.skew_ns
            delay = (t_frame - time.monotonic_ns()) / 1e9 + spec.callback_delay_s
            if delay > 0 and self._stop.wait(delay):
                break
            if spec.disappear_after is not None and delivered >= spec.disappear_after:
                break  # the camera is gone: no more callbacks
            this = slot
            slot += 1
            if this in spec.drop:
                continue
            with world.lock:
                if world.outstanding.get(self.num, 0) >= cfg["buffer_count"]:
                    world.skipped_no_buffer[self.num] = world.skipped_no_buffer.get(self.num, 0) + 1
                    continue
            md = {
                "SensorTimestamp": int(t_frame), "FrameWallClock": time.time_ns(),
                "ExposureTime": exposure_us, "FrameDuration": int(fd),
                "AnalogueGain": float(self.controls.get("AnalogueGain", 1.0)), "DigitalGain": 1.0,
                "SensorTemperature": 40.0,
            }
            if synced:
                md["SyncReady"] = this >= world.sync_ready_after
                md["SyncTimer"] = 0
            req = _FakeRequest(self, md, world.yuv_buffer(self.num, this, w, h, stride))
            with world.lock:
                world.callback_threads.setdefault(self.num, set()).add(tid)
            cb = self.post_callback
            try:
                if cb is not None:
                    cb(req)
            finally:
                req.release()
            delivered += 1
            with world.lock:
                world.delivered[self.num] = world.delivered.get(self.num, 0) + 1
