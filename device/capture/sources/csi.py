"""Two CSI cameras through picamera2 (Raspberry Pi 5), paired by sensor timestamp.

Both cameras get identical fixed-frame-rate video configurations: ``FrameDurationLimits``
pinned to one value, a fixed ``ExposureTime`` and ``AnalogueGain`` (picamera2 turns a
non-zero value into manual exposure/gain) and, on colour sensors, fixed ``ColourGains``
with AWB off.  Where the platform offers libcamera's software sync (``SyncMode`` in
``camera_controls``) the left camera is the server and the right one the client; the
client is started first.  Software sync, as libcamera's ``src/ipa/rpi/controller/rpi/sync.cpp``
and ``src/ipa/rpi/common/ipa_base.cpp`` implement it:

* the server gets ``SyncFrames`` (``source.picamera2.sync_frames``) and reports ``SyncReady``
  after that many frames; the client after the server's "ready time", which it learns from a
  UDP multicast packet the server sends every 30 frames (``Sync::process``).  The first pair
  is therefore waited for ``max(sync_frames, 30) / fps + timeout_s``
  (:meth:`Picamera2Source.first_pair_timeout_s`), later pairs ``timeout_s``;
* each camera is taken as synchronised from its first frame with ``SyncReady`` True on: the
  key is only the start signal (picamera2's ``capture_sync_request`` uses it to find the first
  synced request, and libcamera's ``syncReady_`` never falls back).  Frames before it are
  dropped (``dropped_presync``).  Above ~33 fps the IPA skips its controller on alternate
  frames (``IpaBase::prepareIsp``) and those frames carry no ``SyncReady`` at all, so a
  missing key never means "not ready" once a camera was ready;
* the multicast needs an IPv4 route to 239.255.255.250 (:mod:`..multicast_route`); without
  one the client never reports ``SyncReady``, so opening refuses with a :class:`ConfigError`
  naming the route (the service exits 78) instead of timing out later.

Without ``SyncMode`` (or with ``sync = "off"``) the cameras run free and pairing relies on
the timestamp tolerance alone.

Cameras are chosen by libcamera ``Id``: ``Picamera2(n)`` takes the camera's position in
``Picamera2.global_camera_info()`` (sorted by ``Id`` in reverse, USB cameras last) and looks
libcamera's ``Num`` up itself, so we pass that position, never ``Num``.  Without
``left_id``/``right_id`` the left camera is position 0: on a Raspberry Pi 5 the sensor on the
CAM/DISP 0 connector (its Id holds ``rp1/i2c@88000``, which sorts after CAM/DISP 1's
``rp1/i2c@80000``; see :data:`PI5_CONNECTORS`).  Other boards (CM4) are not mapped: name the
Ids there, and check with ``device selftest --cover-left``.  After
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

import dataclasses
import logging
import time
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any, Callable, Iterator

from stereopath.device.errors import CalibrationError, CaptureError, ConfigError
from stereopath.device.core.frames import StereoFrame
from stereopath.device.core.rig import Rig
from stereopath.device.settings import SourceSettings
from stereopath.device.capture.sources.base import SourceBase, load_rig_override
from stereopath.device.capture.pairing import LEFT, RIGHT, SIDE_NAMES, FramePairer
from stereopath.device.capture.multicast_route import ROUTE_COMMAND, SYNC_GROUP, multicast_route, read_proc_net_route

START_BUDGET_S = 45.0  # the first pair must come within this (systemd/stereopath-capture.service: TimeoutStartSec=60)

if TYPE_CHECKING:
    from picamera2 import MappedArray, Picamera2
    from picamera2.request import CompletedRequest

log = logging.getLogger(__name__)

# names this backend uses, checked against the real libraries when they are installed
PICAMERA2_NAMES = (
    "Picamera2", "Picamera2.global_camera_info", "Picamera2.create_video_configuration",
    "Picamera2.configure", "Picamera2.set_controls", "Picamera2.start", "Picamera2.stop",
    "Picamera2.close", "MappedArray",
)
LIBCAMERA_NAMES = ("controls.rpi.SyncModeEnum.Server", "controls.rpi.SyncModeEnum.Client")
SYNC_PERIOD_FRAMES = 30  # sync.cpp kDefaultSyncPeriod: the server multicasts every 30 frames


@dataclass
class SyncState:
    """What the software sync did: for ``device selftest`` and the logs."""

    mode: str = "off"                          # "software" | "off"
    route: str | None = None                   # interface of the route to the sync group (None: none)
    sync_frames: int = 0                       # SyncFrames given to the server
    frames_to_ready: list[int | None] = dataclasses.field(default_factory=lambda: [None, None])  # per camera


@dataclass
class Picamera2Api:
    """The three names the backend needs (real modules, or a fake in tests)."""

    Picamera2: type[Picamera2]
    MappedArray: type[MappedArray]
    controls: ModuleType  # libcamera.controls


def import_picamera2() -> Picamera2Api:
    try:
        from libcamera import controls
        from picamera2 import MappedArray, Picamera2
    except ImportError as exc:
        raise CaptureError(
            f"picamera2 backend: cannot import picamera2/libcamera ({exc}); install "
            "python3-picamera2 with apt and create the venv with --system-site-packages") from None
    return Picamera2Api(Picamera2=Picamera2, MappedArray=MappedArray, controls=controls)


# Raspberry Pi 5: the camera connectors' I2C buses in the sensor's libcamera Id (its device-tree
# path, CameraSensorLegacy::generateId).  bcm2712-rpi-5-b.dts: i2c_csi_dsi0 = &i2c6 ("MIPI0
# connector"), i2c_csi_dsi1 = &i2c4 ("MIPI1"); rp1.dtsi: i2c6 is i2c@88000, i2c4 is i2c@80000.
PI5_CONNECTORS = {"/rp1/i2c@88000/": "CAM/DISP 0", "/rp1/i2c@80000/": "CAM/DISP 1"}


def connector_of(camera_id: str) -> str | None:
    """The Pi 5 connector a camera Id names, or None when the Id is not a Pi 5 CSI camera's."""
    return next((name for key, name in PI5_CONNECTORS.items() if key in camera_id), None)


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
                 rig: Rig | None = None, route_reader: Callable[[], str] | None = None) -> None:
        super().__init__()
        self._route_reader = route_reader
        self._ready = [False, False]       # per camera: reported SyncReady once (libcamera's syncReady_)
        self._seen = [0, 0]                # frames each camera delivered before it was ready
        self._last_cb_ns: list[int | None] = [None, None]  # monotonic time of each camera's latest callback
        self._settled = False              # start-up drops moved from unpaired to presync (first pair made)
        self.sync_state = SyncState()
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

    def _lock_controls(self, cam: Picamera2) -> dict[str, Any]:
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
        self._ready, self._seen, self._last_cb_ns = [False, False], [0, 0], [None, None]
        self._settled = False
        self.sync_state = SyncState(mode="software" if self._sync else "off")
        roles = (None, None)
        if self._sync:
            self._check_route()
            enum = api.controls.rpi.SyncModeEnum
            roles = (enum.Server, enum.Client)
            self._check_sync_frames(self._cams[0])
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
                    if cam is self._cams[0] and "SyncFrames" in (getattr(cam, "camera_controls", {}) or {}):
                        controls["SyncFrames"] = int(s.picamera2.sync_frames)  # only the server's counts
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

    def _check_route(self) -> None:
        """Refuse software sync without a route to the multicast group (see module doc)."""
        try:
            iface = multicast_route(SYNC_GROUP, self._route_reader or read_proc_net_route)
        except OSError as exc:
            log.warning("picamera2: cannot read the IPv4 routing table (%s); assuming a route to %s exists",
                        exc, SYNC_GROUP)
            self.sync_state.route = "?"
            return
        self.sync_state.route = iface
        if iface is None:
            self._close_cameras()
            raise ConfigError(
                f"picamera2: software sync needs an IPv4 route to the multicast group {SYNC_GROUP} and there is "
                f"none (no network interface up?): add one with `{ROUTE_COMMAND}` (the capture service's "
                "ExecStartPre= does) or set source.picamera2.sync = \"off\"")
        log.info("picamera2: software sync multicast to %s goes through %s", SYNC_GROUP, iface)

    def _check_sync_frames(self, server: Picamera2) -> None:
        frames = int(self.settings.picamera2.sync_frames)
        self.sync_state.sync_frames = frames
        if self.first_pair_timeout_s > START_BUDGET_S:
            raise ConfigError(
                f"source.picamera2.sync_frames = {frames} at {self.settings.fps:g} fps: the first synchronised pair "
                f"may take {self.first_pair_timeout_s:.0f} s, and the capture unit's TimeoutStartSec gives the "
                f"start {START_BUDGET_S:.0f} s at most (lower sync_frames, or raise the frame rate)")
        info = (getattr(server, "camera_controls", {}) or {}).get("SyncFrames")
        if info is None:
            log.warning("picamera2: the sync server has no SyncFrames control; libcamera's tuning file decides "
                        "when it is ready (100 frames by default) and the first pair is waited for %.1f s",
                        self.first_pair_timeout_s)
            return
        lo, hi = info[0], info[1]
        if (lo is not None and frames < lo) or (hi is not None and frames > hi):
            log.warning("picamera2: source.picamera2.sync_frames = %d is outside the %s..%s libcamera advertises; "
                        "it is applied anyway (the IPA takes any positive value)", frames, lo, hi)

    @property
    def camera_ids(self) -> tuple[str, str]:
        """libcamera Ids of the cameras taken as left and right (after open)."""
        return self._ids[0], self._ids[1]

    @property
    def first_pair_timeout_s(self) -> float:
        """How long the first pair may take: the sync start-up plus the usual timeout."""
        s = self.settings
        if not self._sync:
            return float(s.timeout_s)
        frames = max(int(s.picamera2.sync_frames), SYNC_PERIOD_FRAMES) + 2  # +2: a skipped controller frame
        return frames / float(s.fps) + float(s.timeout_s)

    def _make_callback(self, side: int, mapped_array: type[MappedArray]) -> Callable[[CompletedRequest], None]:
        w, h = self._size  # the size libcamera chose, not necessarily the one asked for
        frame_ns = self.settings.frame_duration_us * 1000
        counter = "frames_left" if side == LEFT else "frames_right"
        pairer = self._pairer

        def on_request(request: CompletedRequest) -> None:  # runs on this camera's picamera2 thread
            try:
                self._last_cb_ns[side] = time.monotonic_ns()
                md = request.get_metadata()
                if self._sync and not self._ready[side]:
                    # picamera2's capture_sync_request: the first request with SyncReady True is the
                    # first synchronised one; libcamera's Sync::syncReady_ stays set from then on, and
                    # frames whose controller run was skipped carry no key at all (ipa_base.cpp)
                    if not md.get("SyncReady", False):
                        self._seen[side] += 1
                        self._count(dropped_presync=1)
                        return
                    self._ready[side] = True
                    self.sync_state.frames_to_ready[side] = self._seen[side]
                    log.info("picamera2: %s camera reported SyncReady after %d frames (SyncTimer %s us)",
                             SIDE_NAMES[side], self._seen[side], md.get("SyncTimer", "absent"))
                with mapped_array(request, "main", write=False) as m:
                    luma = m.array[:h, :w].copy()
                ts = int(md["SensorTimestamp"])
                last = self._last_ts[side]
                if last is not None and ts - last > 1.5 * frame_ns:
                    self._count(dropped_sensor=int(round((ts - last) / frame_ns)) - 1)
                self._last_ts[side] = ts
                self._count(**{counter: 1})
                pairer.push(side, ts, (ts, md, luma))
                if self._sync and not self._settled:
                    self._settle_startup()
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
        timeout_s = self.first_pair_timeout_s  # until the first pair; then source.timeout_s
        while self._opened:
            if self._error is not None:
                raise self._error
            got = pairer.get(min(0.05, s.timeout_s))
            if got is None:
                if time.monotonic() - last_progress > timeout_s:
                    raise CaptureError(self._diagnose(timeout_s))
                continue
            last_progress = time.monotonic()
            timeout_s = s.timeout_s
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

    def _settle_startup(self) -> None:
        """Once the first pair is made: frames one camera sent before the other was ready are start-up frames.

        The cameras rarely report SyncReady on the same frame (above ~33 fps each skips the
        controller on its own alternate frames), so the one ready first sends a frame or two the
        pairer cannot match; they count as ``dropped_presync``, not as lost partners."""
        with self._stats_lock:
            if self._settled or not self._stats.paired:
                return
            self._settled = True
            self._stats.dropped_presync += self._stats.dropped_unpaired
            self._stats.dropped_unpaired = 0

    def _diagnose(self, timeout_s: float) -> str:
        s, p = self.settings, self._pairer
        now = time.monotonic_ns()
        # any frame counts here, before SyncReady too: a camera that stops calling back is gone
        ages = [None if a is None else (now - a) / 1e9 for a in self._last_cb_ns]
        st = self.stats
        for side in (LEFT, RIGHT):
            if ages[side] is None or ages[side] > s.timeout_s:
                other = ages[1 - side]
                if other is not None and other <= s.timeout_s:
                    since = "never delivered a frame" if ages[side] is None else f"delivered no frame for {ages[side]:.1f} s"
                    return (f"picamera2: {SIDE_NAMES[side]} camera ({self._ids[side]}) {since} while the "
                            f"{SIDE_NAMES[1 - side]} one keeps running: disconnected or stalled?")
        if self._sync and not all(self._ready) and st.dropped_presync:
            waiting = [SIDE_NAMES[k] for k in (LEFT, RIGHT) if not self._ready[k]]
            msg = (f"picamera2: the {' and '.join(waiting)} camera{'s' if len(waiting) > 1 else ''} never reported "
                   f"SyncReady ({st.dropped_presync} frames dropped in {timeout_s:.1f} s, SyncFrames "
                   f"{s.picamera2.sync_frames})")
            if not self._ready[RIGHT]:
                msg += (f": the sync client (right) never heard the server's multicast on {SYNC_GROUP}; check the "
                        f"IPv4 route to it (`ip route get {SYNC_GROUP}`; `{ROUTE_COMMAND}` adds one) and that "
                        "AF_INET is allowed")
            return msg
        if all(a is None or a > s.timeout_s for a in ages):
            return f"picamera2: no frames from either camera for {timeout_s:.1f} s (cameras stopped or disconnected?)"
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
