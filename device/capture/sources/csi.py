"""Two CSI cameras through picamera2 (Raspberry Pi 5), paired by sensor timestamp.

Both cameras get identical fixed-frame-rate video configurations: ``FrameDurationLimits``
pinned to one value, a fixed ``ExposureTime`` and ``AnalogueGain`` (picamera2 turns a
non-zero value into manual exposure/gain) and, on colour sensors, fixed ``ColourGains``
with AWB off.  Where the platform offers libcamera's software sync (``SyncMode`` in
``camera_controls``) the left camera is the server and the right one the client; the
client is started first, and frames before ``SyncReady`` are dropped (counted in
``dropped_presync``; a frame without the key counts as not ready, as in picamera2's own
``capture_sync_request``).  Without it the cameras run free and pairing relies on the
timestamp tolerance alone.

Cameras are chosen by libcamera ``Id``: ``Picamera2(n)`` takes the camera's position in
``Picamera2.global_camera_info()`` (sorted by ``Id`` in reverse, USB cameras last) and looks
libcamera's ``Num`` up itself, so we pass that position, never ``Num``.  After
``configure`` the main-stream size is read back from ``camera_config`` (libcamera may adjust
it) and the luma is cut at that size.

Every frame arrives through ``post_callback`` on that camera's own picamera2 thread.
The callback copies the luma plane out of the request through ``MappedArray`` and
returns: it never ``acquire()``\\ s the request, so picamera2 releases it (returns the
buffer to the camera) right after the callback.  Nothing escapes the callback: an
error is stored and re-raised to the consumer as :class:`CaptureError`.

Timestamps: libcamera documents ``SensorTimestamp`` (CLOCK_BOOTTIME, equal to
CLOCK_MONOTONIC on a unit that never suspends) as the start of exposure of the first
row, while picamera2's own example treats it as the start of readout with exposure
beginning ``ExposureTime`` earlier.  We follow the latter by default
(``timestamp_is = "readout_start"``: mid-exposure = SensorTimestamp - ExposureTime/2)
and make it a setting; any remaining constant error is absorbed by the calibrated
camera-IMU time offset.  Pairing uses the raw SensorTimestamp, which both cameras
define the same way.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterator

from stereopath.device.errors import CalibrationError, CaptureError
from stereopath.device.core.frames import StereoFrame
from stereopath.device.core.rig import Rig
from stereopath.device.service.settings import SourceSettings
from stereopath.device.capture.sources.base import SourceBase, load_rig_override
from stereopath.device.capture.pairing import LEFT, RIGHT, SIDE_NAMES, FramePairer

log = logging.getLogger(__name__)

# names this backend uses, checked against the real libraries when they are installed
PICAMERA2_NAMES = (
    "Picamera2", "Picamera2.global_camera_info", "Picamera2.create_video_configuration",
    "Picamera2.configure", "Picamera2.set_controls", "Picamera2.start", "Picamera2.stop",
    "Picamera2.close", "MappedArray",
)
LIBCAMERA_NAMES = ("controls.rpi.SyncModeEnum.Server", "controls.rpi.SyncModeEnum.Client")


@dataclass
class Picamera2Api:
    """The three names the backend needs (real modules, or a fake in tests)."""

    Picamera2: Any
    MappedArray: Any
    controls: Any  # libcamera.controls


def import_picamera2() -> Picamera2Api:
    try:
        from libcamera import controls
        from picamera2 import MappedArray, Picamera2
    except ImportError as exc:
        raise CaptureError(
            f"picamera2 backend: cannot import picamera2/libcamera ({exc}); install "
            "python3-picamera2 with apt and create the venv with --system-site-packages") from None
    return Picamera2Api(Picamera2=Picamera2, MappedArray=MappedArray, controls=controls)


def _error_chain(exc: BaseException) -> str:
    """An error with its causes: picamera2 raises a generic "Camera __init__ sequence did not
    complete." and chains the real reason (camera busy, not found) as ``__cause__``."""
    parts, seen = [], set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        parts.append((str(cur) or type(cur).__name__).rstrip("."))
        cur = cur.__cause__ or cur.__context__
    return ": ".join(parts)


class Picamera2Source(SourceBase):
    """Stereo pairs from two picamera2 cameras (see module doc)."""

    name = "picamera2"

    def __init__(self, settings: SourceSettings, api: Picamera2Api | Callable[[], Picamera2Api] | None = None,
                 rig: Rig | None = None) -> None:
        super().__init__()
        self.settings = settings
        self._api_arg = api
        self._rig_arg = rig
        self._cams: list[Any] = []
        self._ids = ["?", "?"]
        self._pairer: FramePairer | None = None
        self._error: BaseException | None = None
        self._sync = False
        self._last_ts: list[int | None] = [None, None]
        self._size: tuple[int, int] = (int(settings.size[0]), int(settings.size[1]))

    # ---------------------------------------------------------------------------------
    def _api(self) -> Picamera2Api:
        if self._api_arg is None:
            return import_picamera2()
        if callable(self._api_arg) and not isinstance(self._api_arg, Picamera2Api):
            return self._api_arg()
        return self._api_arg

    def _choose(self, infos: list[dict[str, Any]]) -> tuple[int, int]:
        """Positions in ``global_camera_info()`` of the left and right cameras.

        ``Picamera2(n)`` takes the position in that list (sorted by ``Id`` in reverse, USB
        cameras last) and looks libcamera's ``Num`` up itself, so the position is what we
        pass, never ``Num``: the two differ whenever libcamera enumerates in another order.
        """
        ps = self.settings.picamera2
        if len(infos) < 2:
            found = [i.get("Id") for i in infos]
            raise CaptureError(f"picamera2: need two cameras, found {len(infos)}: {found}")
        ids = [str(i.get("Id", "")) for i in infos]
        chosen: list[int | None] = []
        for wanted in (ps.left_id, ps.right_id):
            if not wanted:
                chosen.append(None)
                continue
            if wanted not in ids:
                raise CaptureError(f"picamera2: camera Id {wanted!r} not found; cameras present: {ids}")
            chosen.append(ids.index(wanted))
        for k in (0, 1):  # unspecified sides take the first cameras not chosen explicitly
            if chosen[k] is None:
                chosen[k] = next(i for i in range(len(ids)) if i not in chosen)
        if chosen[0] == chosen[1]:
            raise CaptureError(f"picamera2: left and right are the same camera ({ids[chosen[0]]!r})")
        self._ids = [ids[chosen[0]], ids[chosen[1]]]
        return chosen[0], chosen[1]

    def _configured_size(self) -> tuple[int, int]:
        """The main-stream size libcamera settled on (``configure`` may adjust what was asked)."""
        asked = (int(self.settings.size[0]), int(self.settings.size[1]))
        sizes = []
        for cam in self._cams:
            cfg = getattr(cam, "camera_config", None) or {}
            size = (cfg.get("main") or {}).get("size") or asked
            sizes.append((int(size[0]), int(size[1])))
        if sizes[0] != sizes[1]:
            raise CaptureError(f"picamera2: libcamera configured the left camera at {sizes[0][0]}x{sizes[0][1]} "
                               f"and the right one at {sizes[1][0]}x{sizes[1][1]} (asked for {asked[0]}x{asked[1]}); "
                               "choose a source.size both cameras support")
        if sizes[0] != asked:
            log.warning("picamera2: libcamera adjusted the main stream from %dx%d to %dx%d; frames are %dx%d "
                        "(set source.size to match the calibration)", *asked, *sizes[0], *sizes[0])
        return sizes[0]

    def _lock_controls(self, cam: Any) -> dict[str, Any]:
        s, ps = self.settings, self.settings.picamera2
        fd = s.frame_duration_us
        ctrl: dict[str, Any] = {
            "FrameDurationLimits": (fd, fd),
            "ExposureTime": int(s.exposure_us),
            "AnalogueGain": float(ps.analogue_gain),
        }
        avail = getattr(cam, "camera_controls", {}) or {}
        if "AeEnable" in avail:
            ctrl["AeEnable"] = False
        if "ColourGains" in avail and all(g > 0 for g in ps.colour_gains):
            ctrl["AwbEnable"] = False
            ctrl["ColourGains"] = tuple(float(g) for g in ps.colour_gains)
        return ctrl

    def _open(self) -> None:
        s = self.settings
        # the rig file first: a calibration that cannot be used stops before any camera runs
        calib = load_rig_override(s.rig_file) if self._rig_arg is None else None
        api = self._api()
        self._error = None
        self._last_ts = [None, None]
        self._pairer = FramePairer(s.pair_tolerance_us * 1000, self._count, maxlen=8,
                                   out_maxlen=s.queue_size)
        try:
            infos = list(api.Picamera2.global_camera_info())
        except Exception as exc:  # libcamera not running, no permission, ...
            raise CaptureError(f"picamera2: cannot list cameras: {exc}") from None
        positions = self._choose(infos)
        for side, pos in zip((LEFT, RIGHT), positions):
            try:
                self._cams.append(api.Picamera2(pos))
            except Exception as exc:
                self._close_cameras()
                raise CaptureError(f"picamera2: cannot open the {SIDE_NAMES[side]} camera {self._ids[side]} "
                                   f"({_error_chain(exc)})") from None

        has_sync = all("SyncMode" in (getattr(c, "camera_controls", {}) or {}) for c in self._cams)
        self._sync = s.picamera2.sync == "software" and has_sync
        if s.picamera2.sync == "software" and not has_sync:
            log.warning("picamera2: this platform has no SyncMode control; the cameras run free "
                        "and frames are paired by timestamp within %d us only", s.pair_tolerance_us)
        roles = (None, None)
        if self._sync:
            enum = api.controls.rpi.SyncModeEnum
            roles = (enum.Server, enum.Client)
        try:
            for cam, role in zip(self._cams, roles):
                sensor = None
                if s.picamera2.sensor_mode >= 0:
                    modes = cam.sensor_modes
                    if s.picamera2.sensor_mode >= len(modes):
                        raise CaptureError(f"picamera2: sensor_mode {s.picamera2.sensor_mode} does not exist "
                                           f"({len(modes)} modes)")
                    mode = modes[s.picamera2.sensor_mode]
                    sensor = {"output_size": tuple(mode["size"]), "bit_depth": int(mode["bit_depth"])}
                    if self._sync and "fps" in mode and s.fps >= float(mode["fps"]):
                        log.warning("picamera2: software sync needs a frame rate below the mode's "
                                    "maximum (%.2f fps); configured %.2f", float(mode["fps"]), s.fps)
                lock = self._lock_controls(cam)
                controls = dict(lock)
                if role is not None:
                    controls["SyncMode"] = role
                kwargs: dict[str, Any] = dict(main={"size": tuple(s.size), "format": "YUV420"},
                                              buffer_count=s.picamera2.buffer_count, queue=False,
                                              controls=controls)
                if sensor is not None:
                    kwargs["sensor"] = sensor
                cam.configure(cam.create_video_configuration(**kwargs))
                cam.set_controls(lock)  # identical values on both, applied with the next request
            self._size = self._configured_size()
            for side, cam in ((LEFT, self._cams[0]), (RIGHT, self._cams[1])):
                cam.post_callback = self._make_callback(side, api.MappedArray)
            # the sync client (right) starts first, then the server (left)
            self._cams[1].start()
            self._cams[0].start()
        except CaptureError:
            self._close_cameras()
            raise
        except Exception as exc:
            self._close_cameras()
            raise CaptureError(f"picamera2: configuring/starting the cameras failed: {exc}") from None
        log.info("picamera2: left %s, right %s, %dx%d at %.2f fps, exposure %d us, sync %s",
                 self._ids[0], self._ids[1], self._size[0], self._size[1], s.fps, s.exposure_us,
                 "software" if self._sync else "off")
        if self._rig_arg is not None:
            self._rig = self._rig_arg
        elif calib is None:
            log.warning("picamera2: no rig calibration configured (source.rig_file)")
        else:
            try:
                self._use_rig_file(calib, self._size)
            except CalibrationError:
                self._close_cameras()
                raise

    def _make_callback(self, side: int, mapped_array: Any) -> Callable[[Any], None]:
        w, h = self._size  # the size libcamera chose, not necessarily the one asked for
        frame_ns = self.settings.frame_duration_us * 1000
        counter = "frames_left" if side == LEFT else "frames_right"
        pairer = self._pairer

        def on_request(request: Any) -> None:  # runs on this camera's picamera2 thread
            try:
                md = request.get_metadata()
                # as picamera2's own capture_sync_request: no SyncReady means not (yet) synchronised
                if self._sync and not md.get("SyncReady", False):
                    self._count(dropped_presync=1)
                    return
                with mapped_array(request, "main", write=False) as m:
                    luma = m.array[:h, :w].copy()
                ts = int(md["SensorTimestamp"])
                last = self._last_ts[side]
                if last is not None and ts - last > 1.5 * frame_ns:
                    self._count(dropped_sensor=int(round((ts - last) / frame_ns)) - 1)
                self._last_ts[side] = ts
                self._count(**{counter: 1})
                pairer.push(side, ts, (ts, md, luma))
            except Exception as exc:  # never let anything escape into picamera2's event loop
                if self._error is None:
                    self._error = CaptureError(f"picamera2: {SIDE_NAMES[side]} camera callback failed: {exc!r}")
                pairer.wake()

        return on_request

    def _mid_exposure_ns(self, ts: int, md: dict[str, Any]) -> int:
        exp_ns = int(md.get("ExposureTime", self.settings.exposure_us)) * 1000
        if self.settings.picamera2.timestamp_is == "readout_start":
            return ts - exp_ns // 2
        return ts + exp_ns // 2

    def _frames(self) -> Iterator[StereoFrame]:
        s = self.settings
        pairer = self._pairer
        seq = 0
        last_progress = time.monotonic()
        while self._opened:
            if self._error is not None:
                raise self._error
            got = pairer.get(min(0.05, s.timeout_s))
            if got is None:
                if time.monotonic() - last_progress > s.timeout_s:
                    raise CaptureError(self._diagnose())
                continue
            last_progress = time.monotonic()
            (tl, mdl, left), (tr, mdr, right), skew = got
            ml, mr = self._mid_exposure_ns(tl, mdl), self._mid_exposure_ns(tr, mdr)
            with self._stats_lock:
                self._stats.delivered += 1
                self._stats.max_skew_ns = max(self._stats.max_skew_ns, skew)
                self._stats.last_skew_ns = skew
            meta = {
                "source": self.name, "t_left_ns": ml, "t_right_ns": mr, "skew_ns": skew,
                "sensor_timestamp_left": tl, "sensor_timestamp_right": tr,
                "exposure_us": int(mdl.get("ExposureTime", s.exposure_us)),
                "analogue_gain": float(mdl.get("AnalogueGain", s.picamera2.analogue_gain)),
                "frame_duration_us": int(mdl.get("FrameDuration", s.frame_duration_us)),
            }
            yield StereoFrame(seq=seq, t_ns=(ml + mr) // 2, left=left, right=right, meta=meta)
            seq += 1

    def _diagnose(self) -> str:
        s, p = self.settings, self._pairer
        now = time.monotonic_ns()
        ages = [None if a is None else (now - a) / 1e9 for a in p.last_arrival_ns]
        st = self.stats
        for side in (LEFT, RIGHT):
            if ages[side] is None or ages[side] > s.timeout_s:
                other = ages[1 - side]
                if other is not None and other <= s.timeout_s:
                    since = "never delivered a frame" if ages[side] is None else f"delivered no frame for {ages[side]:.1f} s"
                    return (f"picamera2: {SIDE_NAMES[side]} camera ({self._ids[side]}) {since} while the "
                            f"{SIDE_NAMES[1 - side]} one keeps running: disconnected or stalled?")
        if all(a is None or a > s.timeout_s for a in ages):
            if st.dropped_presync and not (st.frames_left or st.frames_right):
                return (f"picamera2: the cameras never reported SyncReady ({st.dropped_presync} frames dropped "
                        f"in {s.timeout_s:.1f} s): is the sync server running and AF_INET allowed?")
            return f"picamera2: no frames from either camera for {s.timeout_s:.1f} s (cameras stopped or disconnected?)"
        return (f"picamera2: both cameras deliver frames but none pair within +-{s.pair_tolerance_us} us "
                f"(last skew {p.last_skew_ns / 1000:.0f} us): are they synchronised (source.picamera2.sync) "
                f"and at the same frame rate?")

    def _close_cameras(self) -> None:
        for cam in self._cams:
            try:
                cam.stop()
            except Exception as exc:
                log.warning("picamera2: stopping a camera failed: %s", exc)
            try:
                cam.post_callback = None
                cam.close()
            except Exception as exc:
                log.warning("picamera2: closing a camera failed: %s", exc)
        self._cams = []

    def _close(self) -> None:
        self._close_cameras()
        if self._pairer is not None:
            self._pairer.close()
