"""OAK-D mono pair through depthai v3: CAM_B (left) and CAM_C (right), GRAY8, one Sync node.

The two mono sensors are hardware-synchronised (FSYNC); a ``Sync`` node groups their
frames within ``sync_threshold_ms`` and emits only synchronised groups.  Frame time is
``ImgFrame.getTimestamp(CameraExposureOffset.MIDDLE)``: the device's capture time carried
into the host-synchronised ``dai::Clock`` (std::chrono::steady_clock = CLOCK_MONOTONIC) at
mid-exposure, so it shares its clock with an IMU read on this machine (the MPU-6050 backend)
and with the OAK's own IMU reports.  A group whose two mid-exposure times differ by more
than ``source.pair_tolerance_us`` is dropped (``dropped_unpaired``); gaps in the left
sequence numbers count as ``dropped_sensor``.

That clock is not guaranteed monotonic: depthai documents ``getTimestampDevice()`` (the
device's own clock) as the one to use "when monotonicity is required", and the host time
offset is re-estimated by XLink's time sync while running, so ``getTimestamp()`` can step.
What a step does: both frames of an exposure are converted with the same offset, so pairing
is unaffected, except a pair straddling the update, whose skew then equals the step (dropped
by the tolerance if larger).  Relative to an IMU on the host clock the camera times shift by
the step.  Steps are detected against the sequence numbers and the frame period
(``clock_steps``, one warning each); a pair that would go back in time is dropped
(``dropped_clock``) so frame times stay increasing.

Outputs are requested with ``enableUndistortion=False``: the images stay as the sensor saw
them (cropped and scaled), since the rig carries the EEPROM's distortion coefficients and
undistortion would apply them twice.

Intrinsics: ``Camera.requestOutput(size)`` resizes with ``ImgResizeMode.CROP`` (its
default): the sensor image is cropped, centred, to the output's aspect ratio and then
scaled.  ``CalibrationHandler.getCameraIntrinsics(sock, w, h)`` does not describe that (it
scales by the width only: fx 400 instead of 480 at 640x480 from 1280x800), so K is taken
from the first frames' own ``ImgFrame.getTransformation().getIntrinsicMatrix()``, which
the device fills in for exactly the crop and scale it applied; where a frame carries no
valid transformation, the calibration's ``getDefaultIntrinsics`` is cropped and scaled the
same way (:func:`crop_scale_intrinsics`).  ``open()`` therefore waits for the first
synchronised pair (that pair is delivered as the first frame).

The rest of the factory calibration comes from the EEPROM: the 14 OpenCV distortion
coefficients (unchanged by a crop and a uniform scale) and the extrinsics with
``unit=LengthUnit.METER`` (depthai's default is centimetres).
``getCameraExtrinsics(src, dst)`` returns the transform that carries points from the
source camera's coordinates into the destination camera's (Luxonis stores OpenCV's
``stereoCalibrate`` R, T of left -> right), so ``(CAM_B, CAM_C)`` is exactly our
``T_cam1_cam0``, with ``T[0] < 0`` for a right camera on the right.  A positive ``T[0]``
means the other direction: it is inverted with a warning.

The OAK's own IMU (when enabled) is exposed as ``source.imu`` (:class:`DepthaiImu`).  It
streams ``ACCELEROMETER_CALIBRATED`` and ``GYROSCOPE_CALIBRATED``: reports in the DepthAI
IMU frame, the frame ``getCameraToImuExtrinsics`` refers to (the ``*_RAW`` reports are in
the chip's native axes).  Accelerometer and gyroscope reports carry their own timestamps;
the accelerometer is interpolated to the gyroscope's.
"""

from __future__ import annotations

import datetime as dt
import logging
import time
from types import ModuleType
from typing import TYPE_CHECKING, Any, Callable, Iterator

import numpy as np

from stereopath.device.errors import CalibrationError, CaptureError
from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.core.geometry import invert_pose
from stereopath.device.core.rig import Rig, make_camera, make_rig
from stereopath.device.settings import SourceSettings
from stereopath.device.capture.sources.base import SourceBase, load_rig_override

if TYPE_CHECKING:
    import depthai
    from numpy.typing import ArrayLike

log = logging.getLogger(__name__)

# an OAK pipeline needs a moment after start() before its first frames; open() waits this long
FIRST_PAIR_TIMEOUT_S = 5.0
# gyroscope samples kept while waiting for an accelerometer report to interpolate from
MAX_PENDING_IMU = 4096

DEPTHAI_NAMES = (
    "Pipeline", "Pipeline.create", "Pipeline.start", "Pipeline.stop", "Pipeline.isRunning",
    "Pipeline.getDefaultDevice", "node.Camera", "node.Camera.build", "node.Camera.requestOutput",
    "node.Sync", "node.Sync.setSyncThreshold", "node.IMU", "node.IMU.enableIMUSensor",
    "node.IMU.setBatchReportThreshold", "node.IMU.setMaxBatchReports",
    "CameraBoardSocket.CAM_B", "CameraBoardSocket.CAM_C", "ImgFrame.Type.GRAY8", "ImgFrame.getTimestamp",
    "ImgFrame.getFrame", "ImgFrame.getSequenceNum", "CameraExposureOffset.MIDDLE", "LengthUnit.METER",
    "IMUSensor.ACCELEROMETER_CALIBRATED", "IMUSensor.GYROSCOPE_CALIBRATED", "MessageGroup",
    "MessageGroup.getMessageNames", "MessageQueue",
    "CalibrationHandler.getDefaultIntrinsics", "CalibrationHandler.getDistortionCoefficients",
    "CalibrationHandler.getCameraExtrinsics", "CalibrationHandler.getCameraToImuExtrinsics",
    "ImgFrame.getTransformation", "ImgTransformation.getIntrinsicMatrix", "ImgTransformation.isValid",
    "ImgTransformation.getSize", "Pipeline.wait",
)


def import_depthai() -> ModuleType:
    try:
        import depthai
    except ImportError as exc:
        raise CaptureError(f"depthai backend: cannot import depthai ({exc}); pip install 'stereopath[oak]'") from None
    return depthai


def timedelta_to_ns(td: dt.timedelta) -> int:
    """Exact integer nanoseconds of a ``datetime.timedelta`` (microsecond resolution)."""
    return ((td.days * 86400 + td.seconds) * 1_000_000 + td.microseconds) * 1000


def crop_scale_intrinsics(K: ArrayLike, src_size: tuple[int, int], dst_size: tuple[int, int]) -> np.ndarray:
    """K of a ``dst_size`` image made with ``ImgResizeMode.CROP`` from a ``src_size`` one.

    CROP cuts the largest centred window of the output's aspect ratio out of the source and
    scales it to the output size, so focal lengths scale by that one factor and the
    principal point moves with the crop.
    """
    K = np.asarray(K, float)
    sw, sh = (float(v) for v in src_size)
    w, h = (float(v) for v in dst_size)
    if sw * h > sh * w:         # source wider than the output: columns are cut
        cw, ch = sh * w / h, sh
    else:                       # source taller (or the same shape): rows are cut
        cw, ch = sw, sw * h / w
    x0, y0 = (sw - cw) / 2.0, (sh - ch) / 2.0
    sx, sy = w / cw, h / ch
    out = K.copy()
    out[0, 0], out[0, 1], out[0, 2] = K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] - x0) * sx
    out[1, 1], out[1, 2] = K[1, 1] * sy, (K[1, 2] - y0) * sy
    return out


def frame_intrinsics(frame: depthai.ImgFrame, size: tuple[int, int]) -> np.ndarray | None:
    """K from an ``ImgFrame``'s own transformation, or None when it carries none for ``size``."""
    try:
        tr = frame.getTransformation()
        if not tr.isValid():
            return None
        w, h = tr.getSize()
        if (int(w), int(h)) != (int(size[0]), int(size[1])):
            return None
        return np.asarray(tr.getIntrinsicMatrix(), float)
    except (AttributeError, RuntimeError):
        return None


def rig_from_calibration(cal: depthai.CalibrationHandler, dai: ModuleType, size: tuple[int, int], name: str = "oak-d",
                         intrinsics: dict[str, Any] | None = None) -> Rig:
    """Our rig from a depthai ``CalibrationHandler`` (metres, ``T_cam1_cam0``).

    ``intrinsics`` maps ``"CAM_B"``/``"CAM_C"`` to K at ``size`` (from the frames'
    transformations); a camera missing there gets its calibrated K cropped and scaled as
    ``ImgResizeMode.CROP`` does.
    """
    w, h = (int(v) for v in size)
    socks = (dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C)
    cams = []
    for cname, sock in zip(("cam0", "cam1"), socks):
        model = getattr(cal, "getDistortionModel", None)
        if model is not None and hasattr(dai, "CameraModel"):
            m = model(sock)
            if m != dai.CameraModel.Perspective:
                raise CaptureError(f"depthai: {cname} uses the {m} lens model; only Perspective is supported")
        K = None if intrinsics is None else intrinsics.get(sock.name)
        if K is None:
            K_cal, cw, ch = cal.getDefaultIntrinsics(sock)
            K = crop_scale_intrinsics(K_cal, (int(cw), int(ch)), (w, h))
        d = np.asarray(cal.getDistortionCoefficients(sock), float).reshape(-1)
        cams.append(make_camera(cname, np.asarray(K, float), d, (w, h)))
    T = np.asarray(cal.getCameraExtrinsics(socks[0], socks[1], unit=dai.LengthUnit.METER), float)
    if T.shape != (4, 4):
        raise CaptureError(f"depthai: CAM_B -> CAM_C extrinsics have shape {T.shape}, expected 4x4")
    if T[0, 3] > 0:
        log.warning("depthai: CAM_B -> CAM_C extrinsics have T[0] = %+.4f m > 0; taking them as the "
                    "reverse direction and inverting", T[0, 3])
        T = invert_pose(T)
    baseline = float(np.linalg.norm(T[:3, 3]))
    if not 0.005 < baseline < 1.0:
        raise CaptureError(f"depthai: implausible stereo baseline {baseline:.4f} m from the factory "
                           "calibration (wrong unit?)")
    T_body_cam0 = None
    getter = getattr(cal, "getCameraToImuExtrinsics", None)
    if getter is not None:
        try:  # camera -> IMU: carries cam0 points into the (calibrated) IMU frame = T_body_cam0
            T_body_cam0 = np.asarray(getter(socks[0], unit=dai.LengthUnit.METER), float)
        except Exception as exc:  # older boards carry no IMU extrinsics
            log.info("depthai: no camera-IMU extrinsics in the calibration (%s)", exc)
    return make_rig(cams[0], cams[1], T[:3, :3], T[:3, 3], name=name, T_body_cam0=T_body_cam0)


class DepthaiImu:
    """The OAK's IMU as an :class:`stereopath.device.capture.imu.ImuSource` (host-synchronised timestamps).

    Samples are stamped with the gyroscope reports' times; the accelerometer, whose reports
    carry their own timestamps, is interpolated linearly to those times.  A gyroscope sample
    newer than the latest accelerometer report waits for the next :meth:`read`.
    """

    name = "depthai-imu"

    def __init__(self, queue: depthai.MessageQueue, rate_hz: float) -> None:
        self._q = queue
        self.rate_hz = float(rate_hz)
        self.gaps: list[tuple[int, int]] = []
        self.samples = 0
        self._last_t: int | None = None       # last gyroscope time handed out
        self._last_g: int | None = None       # last gyroscope report seen
        self._last_a: int | None = None       # last accelerometer report seen
        self._gyro: list[tuple[int, float, float, float]] = []   # waiting for accelerometer cover
        self._acc: list[tuple[int, float, float, float]] = []    # for interpolation

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def read(self) -> ImuSamples:
        """All samples received since the last call that the accelerometer already covers."""
        try:
            msgs = self._q.tryGetAll()
        except Exception as exc:
            raise CaptureError(f"depthai: IMU queue failed: {exc}") from None
        for msg in msgs:
            for pk in msg.packets:
                gy, ac = pk.gyroscope, pk.acceleroMeter
                tg = timedelta_to_ns(gy.getTimestamp())
                if tg > 0 and (self._last_g is None or tg > self._last_g):
                    self._last_g = tg
                    self._gyro.append((tg, gy.x, gy.y, gy.z))
                ta = timedelta_to_ns(ac.getTimestamp())
                if ta > 0 and (self._last_a is None or ta > self._last_a):
                    self._last_a = ta
                    self._acc.append((ta, ac.x, ac.y, ac.z))
        if len(self._gyro) > MAX_PENDING_IMU:  # the accelerometer stopped reporting: do not hoard
            self._gyro = self._gyro[-MAX_PENDING_IMU:]
        if not self._gyro or not self._acc:
            self._acc = self._acc[-1:]
            return ImuSamples.empty()
        g = np.array(self._gyro, float)
        a = np.array(self._acc, float)
        tg = np.array([x[0] for x in self._gyro], np.int64)
        ta = np.array([x[0] for x in self._acc], np.int64)
        ready = tg <= ta[-1]
        usable = ready & (tg >= ta[0])   # before the first accelerometer report: nothing to interpolate
        self._gyro = [x for x, r in zip(self._gyro, ready) if not r]
        keep_from = max(0, int(np.searchsorted(ta, tg[ready][-1], side="right")) - 1) if ready.any() else 0
        self._acc = self._acc[keep_from:]
        t = tg[usable]
        if t.size == 0:
            return ImuSamples.empty()
        rel = (t - ta[0]).astype(float)
        rel_a = (ta - ta[0]).astype(float)
        accel = np.stack([np.interp(rel, rel_a, a[:, k]) for k in (1, 2, 3)], axis=1)
        gyro = g[usable][:, 1:4]
        if self._last_t is not None and t[0] - self._last_t > 2.5e9 / self.rate_hz:
            self.gaps.append((self._last_t, int(t[0])))
        big = np.nonzero(np.diff(t) > 2.5e9 / self.rate_hz)[0]
        self.gaps.extend((int(t[i]), int(t[i + 1])) for i in big)
        self._last_t = int(t[-1])
        self.samples += int(t.size)
        return ImuSamples(t, gyro, accel)


class DepthaiSource(SourceBase):
    """Stereo pairs from an OAK-D's mono cameras (see module doc)."""

    name = "depthai"

    def __init__(self, settings: SourceSettings, dai: Any | Callable[[], Any] | None = None,
                 rig: Rig | None = None) -> None:
        super().__init__()
        self.settings = settings
        self._dai_arg = dai
        self._rig_arg = rig
        self._pipeline: depthai.Pipeline | None = None
        self._queue: depthai.MessageQueue | None = None
        self._dai: ModuleType | None = None
        self._first: depthai.MessageGroup | None = None

    def _module(self) -> ModuleType:
        if self._dai_arg is None:
            return import_depthai()
        if callable(self._dai_arg) and not hasattr(self._dai_arg, "Pipeline"):
            return self._dai_arg()
        return self._dai_arg

    def _open(self) -> None:
        s, ds = self.settings, self.settings.depthai
        dai = self._dai = self._module()
        try:
            p = dai.Pipeline()  # connects to the first available device
        except Exception as exc:
            raise CaptureError(f"depthai: no OAK device ({exc})") from None
        self._pipeline = p
        try:
            size = (int(s.size[0]), int(s.size[1]))
            cams, outs = [], []
            for sock in (dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C):
                cam = p.create(dai.node.Camera).build(sock)
                outs.append(cam.requestOutput(size, type=dai.ImgFrame.Type.GRAY8, fps=float(s.fps),
                                              enableUndistortion=False))
                cam.initialControl.setManualExposure(int(s.exposure_us), int(ds.iso))
                cams.append(cam)
            sync = p.create(dai.node.Sync)
            sync.setSyncThreshold(dt.timedelta(milliseconds=ds.sync_threshold_ms))
            outs[0].link(sync.inputs["left"])
            outs[1].link(sync.inputs["right"])
            self._queue = sync.out.createOutputQueue(maxSize=ds.queue_size, blocking=False)
            if ds.imu:
                imu = p.create(dai.node.IMU)
                # the calibrated reports are in the IMU frame getCameraToImuExtrinsics refers to
                imu.enableIMUSensor([dai.IMUSensor.ACCELEROMETER_CALIBRATED, dai.IMUSensor.GYROSCOPE_CALIBRATED],
                                    ds.imu_rate_hz)
                imu.setBatchReportThreshold(5)
                imu.setMaxBatchReports(20)
                self._imu = DepthaiImu(imu.out.createOutputQueue(maxSize=50, blocking=False), ds.imu_rate_hz)
            cal = None
            if self._rig_arg is not None:
                self._rig = self._rig_arg
            else:
                calib = load_rig_override(s.rig_file)
                if calib is not None:
                    self._use_rig_file(calib, size)
                else:
                    cal = p.getDefaultDevice().readCalibration()
                    rig_from_calibration(cal, dai, size)  # fail early on a calibration we cannot use
            p.start()
            self._first = self._first_group(max(float(s.timeout_s), FIRST_PAIR_TIMEOUT_S))
            if cal is not None:
                K = {}
                for key, sock in (("left", dai.CameraBoardSocket.CAM_B), ("right", dai.CameraBoardSocket.CAM_C)):
                    K_frame = frame_intrinsics(self._first[key], size)
                    if K_frame is None:
                        log.warning("depthai: %s frames carry no image transformation; K is the calibration "
                                    "cropped and scaled as ImgResizeMode.CROP does", key)
                    else:
                        K[sock.name] = K_frame
                self._rig = rig_from_calibration(cal, dai, size, intrinsics=K)
        except (CaptureError, CalibrationError):  # a calibration we cannot use stays a calibration error
            self._stop_pipeline()
            raise
        except Exception as exc:
            self._stop_pipeline()
            raise CaptureError(f"depthai: building/starting the pipeline failed: {exc}") from None
        log.info("depthai: CAM_B/CAM_C %dx%d GRAY8 at %.2f fps, exposure %d us ISO %d, baseline %.4f m",
                 s.size[0], s.size[1], s.fps, s.exposure_us, ds.iso, self._rig.baseline_m)

    def _frames(self) -> Iterator[StereoFrame]:
        s, dai = self.settings, self._dai
        mid = dai.CameraExposureOffset.MIDDLE
        tol_ns = s.pair_tolerance_us * 1000
        seq = 0
        last_seq: int | None = None
        last_t: int | None = None      # mid time of the last delivered pair
        ref_t: int | None = None       # mid time and left sequence number of the last pair seen:
        ref_seq: int | None = None     # where the next one is expected, to see clock steps
        period_ns = int(round(1e9 / float(s.fps)))
        last_progress = time.monotonic()
        while self._opened:
            group, self._first = self._first, None
            if group is None:
                try:
                    running = self._pipeline.isRunning()
                    group = self._queue.get(timeout=dt.timedelta(seconds=min(0.1, s.timeout_s))) if running else None
                except Exception as exc:  # QueueException when the device went away, XLink errors
                    raise CaptureError(f"depthai: lost the device: {exc}") from None
                if not running:
                    raise CaptureError("depthai: the pipeline stopped (device disconnected?)")
            if group is None:
                if time.monotonic() - last_progress > s.timeout_s:
                    raise CaptureError(f"depthai: no synchronised frame pair for {s.timeout_s:.1f} s")
                continue
            last_progress = time.monotonic()
            try:
                lf, rf = group["left"], group["right"]
            except (IndexError, KeyError):  # MessageGroup raises IndexError("map::at") for a missing name
                self._count(dropped_unpaired=int(group.getNumMessages()))
                continue
            tl = timedelta_to_ns(lf.getTimestamp(mid))
            tr = timedelta_to_ns(rf.getTimestamp(mid))
            sn = int(lf.getSequenceNum())
            self._count(frames_left=1, frames_right=1)
            if last_seq is not None and sn - last_seq > 1:
                self._count(dropped_sensor=sn - last_seq - 1)
            last_seq = sn
            skew = abs(tl - tr)
            if skew > tol_ns:
                self._count(dropped_unpaired=2)
                with self._stats_lock:
                    self._stats.last_skew_ns = skew
                continue
            t_mid = (tl + tr) // 2
            if ref_t is not None and ref_seq is not None:
                step = t_mid - (ref_t + (sn - ref_seq) * period_ns)
                back = last_t is not None and t_mid <= last_t
                if abs(step) > period_ns // 2:
                    self._count(clock_steps=1)
                    log.warning("depthai: the host-synchronised frame clock stepped by %+.2f ms (XLink time sync "
                                "re-estimated the device offset)%s", step / 1e6,
                                "; pairs dropped until frame times pass the last one" if back else "")
            ref_t, ref_seq = t_mid, sn
            if last_t is not None and t_mid <= last_t:
                self._count(dropped_clock=2)
                continue
            left, right = np.asarray(lf.getFrame()), np.asarray(rf.getFrame())
            if left.ndim == 3:
                left, right = left[..., 0], right[..., 0]
            with self._stats_lock:
                self._stats.paired += 1
                self._stats.delivered += 1
                self._stats.max_skew_ns = max(self._stats.max_skew_ns, skew)
                self._stats.last_skew_ns = skew
            meta = {"source": self.name, "t_left_ns": tl, "t_right_ns": tr, "skew_ns": skew,
                    "sequence_num": sn, "exposure_us": s.exposure_us}
            last_t = t_mid
            yield StereoFrame(seq=seq, t_ns=t_mid, left=left, right=right, meta=meta)
            seq += 1

    def _first_group(self, timeout_s: float) -> depthai.MessageGroup | None:
        """The first complete synchronised group (its frames carry the transformation K is read from)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                if not self._pipeline.isRunning():
                    raise CaptureError("depthai: the pipeline stopped before the first frame pair "
                                       "(device disconnected?)")
                group = self._queue.get(timeout=dt.timedelta(seconds=0.1))
            except CaptureError:
                raise
            except Exception as exc:
                raise CaptureError(f"depthai: lost the device before the first frame pair: {exc}") from None
            if group is not None and {"left", "right"} <= set(group.getMessageNames()):
                return group
            if time.monotonic() > deadline:
                raise CaptureError(f"depthai: no synchronised frame pair within {timeout_s:.1f} s of starting")

    def _stop_pipeline(self) -> None:
        p, self._pipeline = self._pipeline, None
        self._first = None
        if p is None:
            return
        try:  # what Pipeline.__exit__ does: stop, then wait for the pipeline's threads
            p.stop()
            p.wait()
        except Exception as exc:
            log.warning("depthai: stopping the pipeline failed: %s", exc)

    def _close(self) -> None:
        self._stop_pipeline()
