"""A fake of picamera2 + libcamera.controls that behaves like picamera2 0.3.38.

picamera2 cannot be imported here (Debian packages no libcamera Python bindings), so this
fake copies the real library's behaviour, read from its source (the 0.3.38 wheel on PyPI,
``picamera2/picamera2.py`` and ``picamera2/request.py``).  Each behaviour names the real
function it copies:

* ``Picamera2.global_camera_info()``: one dict per libcamera camera (``Model``,
  ``Location``, ``Rotation``, ``Id``, ``Num`` = the libcamera index), **sorted by Id in
  reverse, USB cameras last** (``Picamera2.global_camera_info``).
* ``Picamera2(camera_num)`` takes a **position in that sorted list** and looks ``Num`` up
  itself; a position past the end raises ``RuntimeError("No camera number N found ...")``
  (``Picamera2.__init__``); a camera that cannot be acquired raises
  ``RuntimeError("Camera __init__ sequence did not complete.")`` with the libcamera error
  in ``__cause__`` (``Picamera2.__init__`` around ``_open_camera``).
* ``create_video_configuration`` rounds the main size down to even
  (``align_stream(main, optimal=False)``), rejects unknown stream keys
  (``_make_initial_stream_config``) and merges ``NoiseReductionMode`` /
  ``FrameDurationLimits`` defaults under the caller's controls.
* ``configure`` checks the configuration (``check_camera_config``: sensor keys, even
  sizes), then lets "libcamera" adjust it and writes the adjusted size and stride back into
  the stream dict (``configure_`` -> ``validate()`` -> ``_update_stream_config``); the
  dict is a shallow copy, so the caller's ``main`` dict changes too, as in the real one.
* each started camera has its own event-loop thread; completed requests whose buffer
  status is not Success are released **before** any callback, and ``post_callback`` runs
  **under the per-camera ``picam2.lock``**, followed by ``release()``
  (``Picamera2.process_requests``).  Requests are reference counted like
  ``CompletedRequest.acquire/release``.
* ``MappedArray(request, "main")`` maps the YUV420 buffer as ``(h*3//2, stride)``
  (``MappedArray.__enter__`` -> ``helpers._make_array_shared``).
* ``set_controls`` rejects controls that are not advertised (``Controls.__setattr__``).

Software sync, copied from libcamera (raspberrypi/libcamera,
``src/ipa/rpi/controller/rpi/sync.cpp`` and ``src/ipa/rpi/common/ipa_base.cpp``; see
:class:`_SyncAlgorithm`):

* the server reports ``SyncReady`` once ``SyncFrames`` sensor frames have passed since it
  started (``Sync::process``, server branch: ``framesRemaining = readyFrame_ - frameCount_``;
  without the control the tuning file's ``"rpi.sync": {}`` keeps ``kDefaultReadyFrame`` = 100,
  ``Sync::read``), and says so on every later frame (the ``syncReady_`` latch);
* the server multicasts its "ready time" every ``sync_period`` (30, ``kDefaultSyncPeriod``)
  frames; the client reports ``SyncReady`` False and no ``SyncTimer`` until it has a packet
  (``timerKnown = clientSeenPacket_``), then becomes ready at the server's ready time;
* with no IPv4 route to the group 239.255.255.250 the client's ``IP_ADD_MEMBERSHIP`` fails
  (ENODEV), ``Sync::initialiseSocket`` closes the socket and ``Sync::process`` returns before
  writing ``sync.status``: its frames carry neither ``SyncReady`` nor ``SyncTimer``, on every
  frame; the server's ``sendto`` fails (ENETUNREACH, logged only), so it still becomes ready;
* frames closer than 0.9 x ``controller_min_frame_duration`` (1/30 s,
  ``defaultControllerMinimumFrameDurationUs`` in ``pipeline_base.cpp``) to the last frame the
  controller ran on skip the controller (``IpaBase::prepareIsp``), and ``IpaBase::processStats``
  then sets no ``SyncReady``/``SyncTimer`` (``libcameraMetadata_`` is cleared per frame in
  ``IpaBase::applyControls``): above ~33 fps some frames carry no sync keys at all.  Which
  frames are skipped depends on when each camera's IPA started (``skip_phase``).

Emulated faults (per camera spec): a timestamp skew, frames that never arrive (``drop``),
frames whose buffer failed (``failed``: dropped inside picamera2 before callbacks), the
controller-skip phase (``skip_phase``) and a camera that disappears after
``disappear_after`` frames; per world: no multicast route (``multicast_route``).  Each frame's luma encodes its
grid slot and the camera's libcamera ``Num`` in the first row (``decode_slot``), so a test
can tell which physical camera a frame came from.
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


class _NoiseReductionModeEnum(enum.Enum):
    Off = 0
    Fast = 1
    HighQuality = 2


controls = SimpleNamespace(rpi=SimpleNamespace(SyncModeEnum=_SyncModeEnum),
                           draft=SimpleNamespace(NoiseReductionModeEnum=_NoiseReductionModeEnum))


def encode_slot(img: np.ndarray, slot: int, num: int) -> None:
    row = np.frombuffer(int(slot).to_bytes(4, "little") + bytes([num]), np.uint8)
    img[0, :5] = row


def decode_slot(img: np.ndarray) -> tuple[int, int]:
    """(grid slot, libcamera Num of the camera) written into a frame by the fake."""
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
    failed: frozenset[int] = frozenset()   # grid slots whose buffer status is not Success
    disappear_after: int | None = None     # stop calling back after this many delivered frames
    present: bool = True                   # False: the camera cannot be acquired (in use / broken)
    callback_delay_s: float = 0.0          # time the fake's thread spends before the callback
    skip_phase: int = 0                    # >0: the IPA ran its controller this many frames before the
    #                                        first delivered one (which then may be skipped above 33 fps)


def _no_adjust(size: tuple[int, int]) -> tuple[int, int]:
    return size


@dataclass
class FakeCameraWorld:
    # libcamera's own camera order (Num = index in this list); global_camera_info() sorts it
    cameras: list[FakeCameraSpec] = field(default_factory=lambda: [
        FakeCameraSpec("/base/axi/pcie@120000/rp1/i2c@88000/imx296@1a", location=2),
        FakeCameraSpec("/base/axi/pcie@120000/rp1/i2c@80000/imx296@1a", location=2),
    ])
    tuning_ready_frame: int = 100          # "rpi.sync" ready_frame (kDefaultReadyFrame) when SyncFrames is unset
    sync_period: int = 30                  # "rpi.sync" sync_period (kDefaultSyncPeriod): frames between packets
    multicast_route: bool = True           # an IPv4 route to 239.255.255.250 exists (client can join the group)
    controller_min_frame_duration_us: float = 1e6 / 30.0  # pipeline_base.cpp defaultControllerMinimumFrameDurationUs
    images: list[tuple[np.ndarray, np.ndarray]] | None = None  # pre-rendered (Num 0, Num 1) luma
    free_run_phase_ns: int = 7_000_000     # phase of the second camera when not synchronised
    max_frames: int | None = None          # stop every camera after this many slots
    # what libcamera's validate() does to a requested main size (Status.Adjusted when it changes)
    adjust_size: Callable[[tuple[int, int]], tuple[int, int]] = _no_adjust

    def __post_init__(self) -> None:
        self.lock = threading.Lock()
        self.grid_t0: int | None = None
        self.start_order: list[int] = []
        self.callback_threads: dict[int, set[int]] = {}
        self.callback_lock_held: dict[int, bool] = {}
        self.delivered: dict[int, int] = {}
        self.failed_released: dict[int, int] = {}
        self.outstanding: dict[int, int] = {}
        self.skipped_no_buffer: dict[int, int] = {}
        self.errors: list[str] = []
        self.instances: list["_FakePicamera2"] = []
        self.applied_controls: dict[int, dict[str, Any]] = {}
        self._yuv_cache: dict[tuple[int, int, int, int], np.ndarray] = {}
        self.sync_packet_ready_ns: int | None = None  # the server's latest multicast "ready time"
        self.sync_ready_slot: dict[int, int] = {}      # first grid slot each camera reported SyncReady

    def api(self) -> SimpleNamespace:
        world = self

        class Picamera2(_FakePicamera2):
            _world = world

        return SimpleNamespace(Picamera2=Picamera2, MappedArray=MappedArray, controls=controls)

    def position_of(self, camera_id: str) -> int:
        """Where the camera with this Id sits in global_camera_info() (what Picamera2() takes)."""
        return [c["Id"] for c in _sorted_info(self.cameras)].index(camera_id)

    # frame content ----------------------------------------------------------------------
    def yuv_buffer(self, num: int, slot: int, w: int, h: int, stride: int) -> np.ndarray:
        if self.images is not None:  # pre-rendered: build each YUV buffer once
            idx = slot % len(self.images)
            key = (num, idx, w, h)
            buf = self._yuv_cache.get(key)
            if buf is None:
                buf = np.full((h * 3 // 2, stride), 128, np.uint8)
                buf[:h, :w] = self.images[idx][min(num, 1)][:h, :w]
                buf.setflags(write=False)
                self._yuv_cache[key] = buf
            return buf
        buf = np.full((h * 3 // 2, stride), 128, np.uint8)   # chroma planes stay 128
        ramp = ((np.arange(w) + slot * 3) % 256).astype(np.uint8)
        buf[:h, :w] = ramp[None, :]
        encode_slot(buf, slot, num)
        return buf


def _sorted_info(cameras: list[FakeCameraSpec]) -> list[dict[str, Any]]:
    # Picamera2.global_camera_info: sorted(cameras, key=lambda cam: ("/usb" not in cam['Id'], cam['Id']),
    # reverse=True), "Num" being the libcamera index
    info = [{"Model": c.model, "Location": c.location, "Rotation": 0, "Id": c.id, "Num": i}
            for i, c in enumerate(cameras)]
    return sorted(info, key=lambda cam: ("/usb" not in cam["Id"], cam["Id"]), reverse=True)



class _SyncAlgorithm:
    """One camera's ``RPiController::Sync`` plus the IPA's controller skip, per frame.

    ``status(slot, t_ns)`` returns the sync keys ``IpaBase::processStats`` would put in that
    frame's metadata (an empty dict when it puts none).  Copied from raspberrypi/libcamera
    ``src/ipa/rpi/controller/rpi/sync.cpp`` (``Sync::process``, ``Sync::initialiseSocket``,
    ``Sync::reset``) and ``src/ipa/rpi/common/ipa_base.cpp`` (``IpaBase::prepareIsp``,
    ``IpaBase::processStats``, ``IpaBase::applyControls`` for ``SYNC_FRAMES``).  The fake's
    cameras already share one exposure grid, so the client's frame-length corrections are not
    modelled: only when each side says it is ready, and which frames carry the keys.
    """

    def __init__(self, world: "FakeCameraWorld", role: "_SyncModeEnum", period_ns: int,
                 sync_frames: int | None, skip_phase: int) -> None:
        self.world = world
        self.server = role == _SyncModeEnum.Server
        self.period_ns = period_ns
        # IpaBase::applyControls SYNC_FRAMES: "if (frames > 0) sync->setReadyFrame(frames)"
        self.ready_frame = sync_frames if sync_frames and sync_frames > 0 else world.tuning_ready_frame
        self.skip_phase = skip_phase
        self.first_slot: int | None = None
        self.last_run_ns: int | None = None
        self.last_sent = 0
        self.ready = False          # Sync::syncReady_: once true, stays true (Sync::reset clears it)
        self.seen_packet = False    # Sync::clientSeenPacket_
        self.server_ready_ns = 0

    def controller_runs(self, t_ns: int) -> bool:
        """IpaBase::prepareIsp: skip the controller when the frame is closer than 0.9 x the
        controller's minimum frame duration to the last frame it ran on."""
        if self.last_run_ns is None:
            self.last_run_ns = t_ns - self.skip_phase * self.period_ns if self.skip_phase else None
            if self.last_run_ns is None:
                self.last_run_ns = t_ns
                return True
        if t_ns - self.last_run_ns < 0.9 * self.world.controller_min_frame_duration_us * 1000:
            return False
        self.last_run_ns = t_ns
        return True

    def status(self, slot: int, t_ns: int) -> dict[str, Any]:
        world = self.world
        if self.first_slot is None:
            self.first_slot = slot
            if self.server:  # a fresh sync session: no packet from an earlier run is valid
                with world.lock:
                    world.sync_packet_ready_ns = None
        if not self.controller_runs(t_ns):
            return {}
        if not self.server and not world.multicast_route:
            return {}  # Sync::initialiseSocket: IP_ADD_MEMBERSHIP fails, socket closed, no sync.status
        frame_count = slot - self.first_slot  # frameCount_ plus the dropped frames it counts from the clock
        if self.server:
            # wallClockReadyTime = wallClockFrameTimestamp + framesRemaining * frameDurationEstimated_
            ready_ns = t_ns + (self.ready_frame - frame_count) * self.period_ns
            if frame_count - self.last_sent >= world.sync_period:
                self.last_sent = frame_count
                if world.multicast_route:  # otherwise sendto fails with ENETUNREACH: "Send error!" only
                    with world.lock:
                        world.sync_packet_ready_ns = ready_ns
            if not self.ready and t_ns + self.period_ns // 2 > ready_ns:
                self.ready = True
            return {"SyncReady": self.ready, "SyncTimer": (ready_ns - t_ns) // 1000}
        with world.lock:
            packet = world.sync_packet_ready_ns
        if packet is not None:
            self.seen_packet = True
            self.server_ready_ns = packet
        md: dict[str, Any] = {}
        if self.seen_packet:
            md["SyncTimer"] = (self.server_ready_ns - t_ns) // 1000  # only once timerKnown
            if not self.ready and t_ns + self.period_ns // 2 > self.server_ready_ns:
                self.ready = True
        md["SyncReady"] = self.ready
        return md


class _FakeRequest:
    """CompletedRequest: reference counted; a release below zero raises like the real one."""

    def __init__(self, cam: "_FakePicamera2", metadata: dict[str, Any], buffer: np.ndarray, ok: bool = True) -> None:
        self.picam2 = cam
        self.request: Any = SimpleNamespace(status_ok=ok)
        self.ref_count = 1
        self.config = dict(cam.camera_config)
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
        return _sorted_info(cls._world.cameras)

    def __init__(self, camera_num: int = 0) -> None:
        world = self._world
        info = self.global_camera_info()
        # Picamera2.__init__ (0.3.38): a position past the end of global_camera_info()
        if camera_num >= len(info):
            raise RuntimeError(f'No camera number {camera_num} found - use "rpicam-hello --list-cameras" '
                               "to check connected cameras")
        num = info[camera_num]["Num"]  # "Get the real libcamera internal number."
        self.num = num
        self.spec = world.cameras[num]
        self.is_open = False
        self.camera_config: dict[str, Any] | None = None
        self.configured: dict[str, Any] = {}
        self.post_callback: Callable[[Any], None] | None = None
        self.pre_callback = None
        self.lock = threading.Lock()  # Picamera2.lock: held around pre/post callbacks
        self.started = False
        self.closed = False
        self.controls: dict[str, Any] = {}
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.sync_algorithm: _SyncAlgorithm | None = None
        try:
            if not self.spec.present:
                # libcamera src/py/libcamera/py_main.cpp, Camera.acquire: std::system_error(-ret,
                # "Failed to acquire camera"), which pybind11 raises as RuntimeError (EBUSY here)
                raise RuntimeError("Failed to acquire camera: Device or resource busy")
        except Exception as e:
            # Picamera2.__init__: the real error is chained, the message is generic
            raise RuntimeError("Camera __init__ sequence did not complete.") from e
        self.is_open = True
        world.instances.append(self)
        cc: dict[str, Any] = {
            "ExposureTime": (14, 15534385, None), "AnalogueGain": (1.0, 251.1886444091797, None),
            "FrameDurationLimits": (16562, 15534444, None), "AeEnable": (False, True, None),
            "NoiseReductionMode": (0, 4, 0),
        }
        if self.spec.has_sync:
            # ipa_base.cpp ipaControls: SyncMode ControlInfo({Off, Client}, Off), SyncFrames ControlInfo(100, 100000, 1000)
            cc["SyncMode"] = (0, 2, 0)
            cc["SyncFrames"] = (100, 100000, 1000)
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
        if not self.is_open:
            raise RuntimeError("Camera not opened")
        # _make_initial_stream_config: defaults, then the caller's keys (unknown keys rejected)
        stream: dict[str, Any] = {"format": "XBGR8888", "size": (1280, 720), "preserve_ar": True}
        for key, value in (main or {}).items():
            if key not in ("format", "size", "stride", "preserve_ar"):
                raise ValueError(f"Bad key {key!r}: valid stream configuration keys are "
                                 "('format', 'size', 'stride', 'preserve_ar')")
            stream[key] = value
        size = stream["size"]  # align_stream(main, optimal=False): round down to even
        stream["size"] = (size[0] - size[0] % 2, size[1] - size[1] % 2)
        ctrl = dict(controls or {})
        if "NoiseReductionMode" in self.camera_controls and "FrameDurationLimits" in self.camera_controls:
            ctrl = {"NoiseReductionMode": _NoiseReductionModeEnum.Fast, "FrameDurationLimits": (33333, 33333)} | ctrl
        return {"use_case": use_case, "transform": transform, "colour_space": colour_space,
                "buffer_count": buffer_count, "queue": queue, "main": stream, "lores": lores, "raw": raw, "controls": ctrl, "sensor": sensor,
                "display": display, "encode": encode}

    def configure(self, config: dict[str, Any]) -> None:
        if self.started:
            raise RuntimeError("Camera must be stopped before configuring")
        config = config.copy()  # configure_: a shallow copy, so the stream dicts are shared with the caller
        self.camera_config = {}
        sensor = config.get("sensor")
        if sensor is not None:  # check_camera_config
            bad = set(sensor) - {"bit_depth", "output_size"}
            if bad:
                raise RuntimeError(f"Unexpected keys {bad} in sensor configuration")
        main = config["main"]  # check_stream_config
        size = main["size"]
        if type(size) is not tuple or len(size) != 2:
            raise RuntimeError("size in main stream should be (width, height)")
        if size[0] % 2 or size[1] % 2:
            raise RuntimeError("width and height should be even")
        self._check_controls(config.get("controls", {}))
        # libcamera validate() may adjust; _update_stream_config writes size and stride back
        w, h = self._world.adjust_size(tuple(size))
        main["size"] = (int(w), int(h))
        fmt = main.get("format")
        main["stride"] = (w + 63) // 64 * 64 if fmt in ("YUV420", "YVU420") else w * 4
        main["framesize"] = main["stride"] * h * 3 // 2 if fmt in ("YUV420", "YVU420") else main["stride"] * h
        self.camera_config = config
        self.configured = config  # kept for tests: close() empties camera_config like the real one
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
        if not self.camera_config:
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
        if not self.is_open:
            return
        self.stop()
        self.is_open = False
        self.closed = True
        self.camera_config = {}

    # the camera's event loop ------------------------------------------------------------------
    def _process_request(self, req: _FakeRequest, tid: int) -> bool:
        """Picamera2.process_requests for one completed request; True if callbacks saw it."""
        world = self._world
        if not req.request.status_ok:  # "Discard startup frames, or frames with errors"
            req.release()
            with world.lock:
                world.failed_released[self.num] = world.failed_released.get(self.num, 0) + 1
            return False
        with self.lock:
            with world.lock:
                world.callback_threads.setdefault(self.num, set()).add(tid)
            cb = self.post_callback
            try:
                if cb is not None:
                    world.callback_lock_held[self.num] = self.lock.locked()
                    cb(req)
            finally:
                req.release()
        return True

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
        sync = None
        if synced:
            sync = _SyncAlgorithm(world, sync_role, period, self.controls.get("SyncFrames"), spec.skip_phase)
        self.sync_algorithm = sync
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
            if sync is not None:
                keys = sync.status(this, int(t_frame) - spec.skew_ns)
                md.update(keys)
                if keys.get("SyncReady"):
                    with world.lock:
                        world.sync_ready_slot.setdefault(self.num, this)
            req = _FakeRequest(self, md, world.yuv_buffer(self.num, this, w, h, stride), ok=this not in spec.failed)
            if self._process_request(req, tid):
                delivered += 1
                with world.lock:
                    world.delivered[self.num] = world.delivered.get(self.num, 0) + 1
