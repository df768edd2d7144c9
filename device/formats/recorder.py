"""Session recorder: the one writer of our recording layout (EuRoC/ASL plus a manifest).

The layout is described in :mod:`stereopath.device.formats.layout`; :func:`stereopath.device.formats.open_session`
reads it back.  Both ``stereopath sim`` and the device at capture time write through
:class:`SessionRecorder`.

Durability.  Rows are buffered in memory and written in chunks (every ``chunk_s`` seconds of
the recorder's clock, or sooner when many images are pending), each chunk as whole lines
followed by ``fsync``, so a power cut loses at most about one chunk and leaves every file
parseable (at worst a final partial line, which the readers drop with a warning).  An image is
written to a temporary name and renamed before its CSV row is queued, and the images of a chunk
(and their folders) are fsynced before the chunk's rows are written, so a durable row always
points at a durable image.  ``manifest.json`` is written at start (status ``recording``) and
rewritten atomically when the recording ends.

Disk space.  The recorder refuses to start (:class:`CaptureError`) when the free space of the
target file system is below ``reserve_bytes``, and stops cleanly (state ``stopped_low_disk``:
pending data flushed, files closed, manifest written, further data refused) when it falls below
while recording.  The free-space probe and the clock are injectable (:class:`RecorderHooks`) for tests.

States: ``recording`` -> ``closed`` (after :meth:`close`), ``stopped_low_disk`` (final, also
after :meth:`close`), or ``error`` (an I/O error other than a full disk; raised as
:class:`CaptureError`).  Methods are thread-safe (one lock).
"""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import threading
import time
from datetime import datetime, timezone
from pathlib import Path
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Mapping, Protocol

import numpy as np

from stereopath.device.formats import layout
from stereopath.device.errors import CaptureError, ConfigError
from stereopath.device.formats.fileio import fsync_dir, write_renamed_open, write_text_atomic
from stereopath.device.wire.protocol import new_session_id
from stereopath.device.core.frames import ImuSamples, StereoFrame, median_rate_hz
from stereopath.device.core.rig import Rig
from stereopath.device.formats.rig_files import MPU6050_NOISE, camera_sensor_yaml, imu_sensor_yaml, save_rig_yaml
from stereopath.device.formats.tum import Trajectory, format_tum_line, write_tum

if TYPE_CHECKING:
    from stereopath.device.formats.sequence import StereoSequence

log = logging.getLogger(__name__)

DEFAULT_RESERVE_BYTES = 256 * 1024 * 1024
MAX_PENDING_IMAGES = 64  # flush sooner than chunk_s when this many image files wait for fsync

FLUSH_ORDER = ("imu", "temp", "cam0", "cam1", "traj")

RECORDING, CLOSED, STOPPED_LOW_DISK, ERROR = "recording", "closed", "stopped_low_disk", "error"


def _utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _append_whole(fd: int, data: bytes) -> None:
    """Append ``data`` (whole rows) durably or nothing: a write cut short or whose fsync fails (disk
    full) is cut back off the file, so no half row is left for a later row to be glued onto, and no
    row is counted that may not be on disk."""
    start = os.lseek(fd, 0, os.SEEK_END)
    try:
        _write_all(fd, data)
        os.fsync(fd)
    except OSError:
        try:
            os.ftruncate(fd, start)
        except OSError:
            pass
        raise


class DiskUsage(Protocol):
    """What the recorder reads of ``shutil.disk_usage``."""

    @property
    def free(self) -> int: ...


@dataclass(frozen=True)
class SensorInfo:
    """What the session's sensor files (``cam*/sensor.yaml``, ``imu0/sensor.yaml``) say."""

    cam_rate_hz: float = 20.0
    imu_rate_hz: float = 200.0
    imu_noise: Mapping[str, float] | None = None  # the IMU's noise figures (None: the MPU-6050's)


@dataclass(frozen=True)
class RecorderHooks:
    """Injectable free-space probe and monotonic clock (None: ``shutil.disk_usage``, ``time.monotonic``)."""

    disk_usage: Callable[[Path], DiskUsage] | None = None
    clock: Callable[[], float] | None = None


# PNG compression of the recorded images (zlib level: 1 is fast and already near the best size of grey frames)
PNG_LEVEL = 1


class SessionRecorder:
    """Records frames, IMU samples and estimated poses into ``out_dir`` (see module doc)."""

    def __init__(
        self,
        out_dir: str | Path,
        rig: Rig,
        config_dict: Mapping[str, object] | None = None,
        session_id: str | None = None,
        reserve_bytes: int = DEFAULT_RESERVE_BYTES,
        chunk_s: float = 1.0,
        *,
        sensors: SensorInfo = SensorInfo(),
        hooks: RecorderHooks = RecorderHooks(),
    ) -> None:
        if chunk_s < 0 or reserve_bytes < 0:
            raise ConfigError(f"recorder: chunk_s ({chunk_s}) and reserve_bytes ({reserve_bytes}) must be >= 0")
        self.dir = Path(out_dir)
        self.rig = rig
        self.session_id = session_id or new_session_id()
        self.reserve_bytes = int(reserve_bytes)
        self.chunk_s = float(chunk_s)
        self._disk_usage = hooks.disk_usage or shutil.disk_usage
        self._clock = hooks.clock or time.monotonic
        self._config = dict(config_dict or {})
        self._lock = threading.RLock()
        self._created = _utc_now()
        self.counts = {"frames": 0, "imu_samples": 0, "poses": 0, "dropped_frames": 0, "dropped_imu_samples": 0}
        self._first_t: int | None = None
        self._last_frame_t: int | None = None
        self._last_imu_t: int | None = None
        self._fds: dict[str, int] = {}
        self._pending: dict[str, list[str]] = {}
        self._pending_images: list[int] = []
        self._images_failed = False  # an image's fsync failed: the queued frames' rows are not written
        self._low_disk_logged = False
        self._closed = False
        self.state = RECORDING

        if self.dir.exists() and (not self.dir.is_dir() or any(self.dir.iterdir())):
            raise CaptureError(f"recording folder {self.dir} exists and is not empty; refusing to overwrite it")
        probe = self.dir
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        free = self._free_bytes(probe)
        if free < self.reserve_bytes:
            raise CaptureError(
                f"not starting the recording in {self.dir}: {free / 2**20:.0f} MiB free, below the reserve of "
                f"{self.reserve_bytes / 2**20:.0f} MiB"
            )
        try:
            self._create_layout(sensors.cam_rate_hz, sensors.imu_rate_hz, dict(sensors.imu_noise or MPU6050_NOISE))
        except OSError as exc:
            self._close_fds()
            self.state = ERROR
            raise CaptureError(f"cannot create the recording in {self.dir}: {exc}") from exc
        self._last_flush = self._clock()
        log.info("recording session %s into %s (reserve %.0f MiB, chunks of %.2f s)",
                 self.session_id, self.dir, self.reserve_bytes / 2**20, self.chunk_s)

    # -- set-up ----------------------------------------------------------------------------

    def _create_layout(self, cam_rate_hz: float, imu_rate_hz: float, imu_noise: dict[str, float]) -> None:
        m = self.dir / layout.MAV0
        for cam in layout.CAMERAS:
            (m / cam / "data").mkdir(parents=True, exist_ok=True)
        (m / layout.IMU).mkdir(parents=True, exist_ok=True)
        T_body_cam0 = self.rig.T_body_cam0 if self.rig.T_body_cam0 is not None else np.eye(4)
        T_body_cam1 = T_body_cam0 @ self.rig.T_cam0_cam1
        write_text_atomic(m / "cam0" / "sensor.yaml", camera_sensor_yaml(self.rig.cam0, "cam0", T_body_cam0, cam_rate_hz))
        write_text_atomic(m / "cam1" / "sensor.yaml", camera_sensor_yaml(self.rig.cam1, "cam1", T_body_cam1, cam_rate_hz))
        write_text_atomic(m / layout.IMU / "sensor.yaml", imu_sensor_yaml(imu_rate_hz, imu_noise))
        write_text_atomic(m / "body.yaml", "%YAML:1.0\ncomment: stereopath handheld rig (body frame = IMU frame)\n")
        save_rig_yaml(self.rig, m / layout.RIG_YAML,
                      comment=f"stereopath rig calibration of session {self.session_id}")
        self._open_csv("cam0", m / "cam0" / "data.csv", layout.CAM_CSV_HEADER)
        self._open_csv("cam1", m / "cam1" / "data.csv", layout.CAM_CSV_HEADER)
        self._open_csv("imu", m / layout.IMU / "data.csv", layout.IMU_CSV_HEADER)
        self._open_csv("traj", self.dir / layout.TRAJECTORY, layout.TRAJECTORY_HEADER)
        self._write_manifest()
        fsync_dir(m)
        fsync_dir(self.dir)

    def _open_csv(self, key: str, path: Path, header: str) -> None:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        self._fds[key] = fd
        self._pending[key] = []
        _write_all(fd, header.encode())
        os.fsync(fd)

    def _free_bytes(self, path: Path | None = None) -> int:
        return int(self._disk_usage(path or self.dir).free)

    # -- public API -------------------------------------------------------------------------

    def __enter__(self) -> "SessionRecorder":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def recording(self) -> bool:
        return self.state == RECORDING

    def add_frame(self, frame: StereoFrame) -> bool:
        """Write one stereo pair (PNG) and queue its CSV rows.  False when not recorded."""
        with self._lock:
            if not self._accepting():
                self.counts["dropped_frames"] += 1
                return False
            t = int(frame.t_ns)
            if self._last_frame_t is not None and t <= self._last_frame_t:
                log.warning("frame %d at t=%d ns does not follow the previous one (%d ns); not recorded",
                            frame.seq, t, self._last_frame_t)
                self.counts["dropped_frames"] += 1
                return False
            if not self._check_disk():
                self.counts["dropped_frames"] += 1
                return False
            name = f"{t}.png"
            blobs = [self._encode_png(img, cam) for img, cam in ((frame.left, "cam0"), (frame.right, "cam1"))]
            try:
                for cam, blob in zip(layout.CAMERAS, blobs):
                    self._pending_images.append(self._write_image(self.dir / layout.MAV0 / cam / "data" / name, blob))
            except OSError as exc:
                self._io_failed(exc)
                self.counts["dropped_frames"] += 1
                return False
            for cam in layout.CAMERAS:
                self._pending[cam].append(f"{t},{name}\n")
            self._last_frame_t = t
            self._first_t = t if self._first_t is None else min(self._first_t, t)
            self.counts["frames"] += 1
            self._maybe_flush()
            return self.state == RECORDING

    def add_imu(self, imu: ImuSamples) -> bool:
        """Queue IMU rows (samples not after the previous ones, or non-finite, are dropped)."""
        with self._lock:
            if not self._accepting():
                self.counts["dropped_imu_samples"] += len(imu)
                return False
            if not len(imu):
                return True
            rows, trows, dropped = [], [], 0
            last = self._last_imu_t
            temps = imu.temp_c.tolist() if imu.temp_c is not None else None
            for k, (t, g, a) in enumerate(zip(imu.t_ns.tolist(), imu.gyro_rad_s.tolist(), imu.accel_m_s2.tolist())):
                if (last is not None and t <= last) or not all(np.isfinite(g + a)):
                    dropped += 1
                    continue
                rows.append(f"{t},{g[0]!r},{g[1]!r},{g[2]!r},{a[0]!r},{a[1]!r},{a[2]!r}\n")
                if temps is not None and np.isfinite(temps[k]):
                    trows.append(f"{t},{float(temps[k])!r}\n")
                last = t
            if dropped:
                first = self.counts["dropped_imu_samples"] == 0
                log.log(logging.WARNING if first else logging.DEBUG,
                        "%d IMU samples not after the previous ones or non-finite; not recorded%s", dropped,
                        " (further drops are counted in the manifest)" if first else "")
                self.counts["dropped_imu_samples"] += dropped
            if trows and "temp" not in self._fds:
                try:
                    self._open_csv("temp", self.dir / layout.MAV0 / layout.IMU / layout.IMU_TEMPERATURE,
                                   layout.TEMP_CSV_HEADER)
                except OSError as exc:
                    self._io_failed(exc)
                    return False
            self._pending["imu"].extend(rows)
            if trows:
                self._pending["temp"].extend(trows)
            self._last_imu_t = last
            self.counts["imu_samples"] += len(rows)
            if rows and self._first_t is None:
                self._first_t = int(imu.t_ns[0])
            self._maybe_flush()
            return True

    def add_pose(self, t_ns: int, T_world_cam: np.ndarray) -> bool:
        """Append one estimated pose to ``trajectory.tum``."""
        with self._lock:
            if not self._accepting():
                return False
            T = np.asarray(T_world_cam, dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                log.warning("pose at t=%d ns is not a finite 4x4 matrix; not recorded", t_ns)
                return False
            self._pending["traj"].append(format_tum_line(int(t_ns), T))
            self.counts["poses"] += 1
            self._maybe_flush()
            return True

    def write_groundtruth(self, traj: Trajectory) -> None:
        """Write ``groundtruth.tum`` (``T_world_cam0``) atomically."""
        with self._lock:
            if self.state in (CLOSED, ERROR):
                raise CaptureError(f"session {self.session_id}: cannot write ground truth, recorder is {self.state}")
            try:
                write_tum(self.dir / layout.GROUNDTRUTH, traj)
            except OSError as exc:
                self._io_failed(exc)

    def flush(self) -> None:
        """Make everything queued durable now (images first, then their rows)."""
        with self._lock:
            if self._fds:
                self._flush_or_fail()

    def close(self) -> None:
        """Flush, close the files and rewrite the manifest.  Safe to call more than once."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self.state != RECORDING:  # stopped earlier: files are closed, record the final counts
                self._finish_manifest()
                return
            try:
                if self._fds:
                    self._flush()
            except OSError as exc:
                self._io_failed(exc)
                return
            finally:
                self._close_fds()
            if self.state == RECORDING:
                self.state = CLOSED
            self._finish_manifest()
            log.info("session %s %s: %d frames, %d IMU samples, %d poses", self.session_id, self.state,
                     self.counts["frames"], self.counts["imu_samples"], self.counts["poses"])

    # -- internals --------------------------------------------------------------------------

    def _accepting(self) -> bool:
        if self.state == RECORDING:
            return True
        if self.state == STOPPED_LOW_DISK and not self._low_disk_logged:
            log.warning("session %s stopped (low disk); data not recorded", self.session_id)
            self._low_disk_logged = True
        return False

    def _check_disk(self) -> bool:
        free = self._free_bytes()
        if free >= self.reserve_bytes:
            return True
        log.error("free disk %.0f MiB fell below the reserve of %.0f MiB: stopping session %s",
                  free / 2**20, self.reserve_bytes / 2**20, self.session_id)
        self._stop(STOPPED_LOW_DISK)
        return False

    def _stop(self, state: str) -> None:
        try:
            self._salvage_rows()
        finally:
            self._close_fds()
        self.state = state
        self._finish_manifest()

    def _io_failed(self, exc: OSError) -> None:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            log.error("session %s: disk full (%s); stopping", self.session_id, exc)
            self._salvage_rows()
            self._close_fds()
            self.state = STOPPED_LOW_DISK
            self._finish_manifest()
            return
        self._close_fds()
        self.state = ERROR
        self._finish_manifest()
        raise CaptureError(f"recording to {self.dir} failed: {exc}") from exc

    def _encode_png(self, img: np.ndarray, cam: str) -> bytes:
        import cv2

        a = np.asarray(img)
        if a.ndim not in (2, 3) or a.dtype not in (np.uint8, np.uint16) or a.size == 0:
            raise CaptureError(f"{cam}: cannot record an image of shape {a.shape} and type {a.dtype}")
        ok, buf = cv2.imencode(".png", a, [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL])
        if not ok:
            raise CaptureError(f"{cam}: PNG encoding failed")
        return buf.tobytes()

    @staticmethod
    def _write_image(path: Path, blob: bytes) -> int:
        """Write ``blob`` under a temporary name and rename it; the open fd is fsynced at flush."""
        return write_renamed_open(path, blob)

    def _maybe_flush(self) -> None:
        if (self._clock() - self._last_flush >= self.chunk_s) or len(self._pending_images) >= 2 * MAX_PENDING_IMAGES:
            self._flush_or_fail()

    def _flush_or_fail(self) -> None:
        try:
            self._flush()
        except OSError as exc:
            self._io_failed(exc)

    def _flush(self) -> None:
        if self._pending_images:
            images, self._pending_images = self._pending_images, []
            try:
                for fd in images:
                    os.fsync(fd)
            except OSError:
                # those images may not be on disk: their frames' rows must not be written (a durable row
                # always points at a durable image); _salvage_rows drops them
                self._images_failed = True
                raise
            finally:
                for fd in images:
                    os.close(fd)
            for cam in layout.CAMERAS:
                fsync_dir(self.dir / layout.MAV0 / cam / "data")
        for key in FLUSH_ORDER:  # IMU first: a durable frame row has its IMU samples before it
            lines = self._pending.get(key)
            if lines:
                fd = self._fds[key]
                _append_whole(fd, "".join(lines).encode())
                self._pending[key] = []  # only once durable: a failed write is tried again at the stop
        self._last_flush = self._clock()

    def _salvage_rows(self) -> None:
        """Disk full: the queued rows of frames whose images are already on disk are tried once more
        (rows are small: the last page of a file often still takes them).  What cannot be written is
        taken off the counts, so that the manifest says what the files hold."""
        dropped = 0
        if self._images_failed:  # the queued frames' images may not be on disk: their rows go
            dropped = self._unwritten_frames()
            for cam in layout.CAMERAS:
                self._pending[cam] = []
        try:
            if self._fds:
                self._flush()
        except OSError as exc:
            log.error("session %s: the rows of the last %d frame(s) could not be written (%s)",
                      self.session_id, self._unwritten_frames(), exc)
        lost = {"frames": dropped + self._unwritten_frames(), "imu_samples": len(self._pending.get("imu", ())),
                "poses": len(self._pending.get("traj", ()))}
        for key, n in lost.items():
            if n:
                self.counts[key] -= n
                self.counts[f"{key}_lost_disk_full"] = n
        for key in self._pending:
            self._pending[key] = []

    def _unwritten_frames(self) -> int:
        """Frames whose row is still queued in either camera's file (a reader needs both)."""
        return max(len(self._pending.get(cam, ())) for cam in layout.CAMERAS)

    def _close_fds(self) -> None:
        for fd in self._pending_images:
            try:
                os.close(fd)
            except OSError:
                pass
        self._pending_images = []
        for fd in self._fds.values():
            try:
                os.close(fd)
            except OSError:
                pass
        self._fds = {}

    def manifest(self) -> dict[str, Any]:
        from stereopath.device import __version__

        return {
            "format": layout.FORMAT_NAME,
            "format_version": layout.FORMAT_VERSION,
            "session_id": self.session_id,
            "software": "stereopath",
            "software_version": __version__,
            "created_utc": self._created,
            "status": self.state,
            "rig": self.rig.name,
            "configuration": self._config,
            "counts": dict(self.counts),
            "first_t_ns": self._first_t,
            "last_frame_t_ns": self._last_frame_t,
            "reserve_bytes": self.reserve_bytes,
        }

    def _write_manifest(self, extra: dict[str, Any] | None = None) -> None:
        data = self.manifest()
        if extra:
            data.update(extra)
        write_text_atomic(self.dir / layout.MANIFEST, json.dumps(data, indent=2, default=str) + "\n")

    def _finish_manifest(self) -> None:
        try:
            self._write_manifest({"status": self.state, "ended_utc": _utc_now()})
        except OSError as exc:
            log.error("session %s: cannot write %s: %s", self.session_id, layout.MANIFEST, exc)


def record_sequence(seq: StereoSequence, out_dir: str | Path, config_dict: dict[str, Any] | None = None,
                    max_frames: int | None = None, **recorder_kwargs: object) -> dict[str, Any]:
    """Write any sequence (``rig``, ``t_ns``, ``frames()``, ``imu``, ``groundtruth``) as a session.

    IMU samples are interleaved with the frames as a live recording would write them (the
    samples up to each frame's time before that frame).  Returns the final manifest.
    """
    imu = seq.imu
    t_frames = np.asarray(seq.t_ns, dtype=np.int64)
    if "sensors" not in recorder_kwargs:
        sensors = SensorInfo(cam_rate_hz=median_rate_hz(t_frames) or 20.0)
        if imu is not None and len(imu):
            # a sequence that knows its IMU's noise (the simulator) records it
            sensors = SensorInfo(sensors.cam_rate_hz, median_rate_hz(imu.t_ns) or 200.0,
                                 getattr(seq, "imu_noise_figures", None) or None)
        recorder_kwargs["sensors"] = sensors
    with SessionRecorder(out_dir, seq.rig, config_dict, **recorder_kwargs) as rec:
        prev = None
        for k, frame in enumerate(seq.frames()):
            if max_frames is not None and k >= max_frames:
                break
            if imu is not None:
                rec.add_imu(imu.between(np.iinfo(np.int64).min if prev is None else prev, frame.t_ns))
            rec.add_frame(frame)
            prev = frame.t_ns
            if not rec.recording:
                break
        if imu is not None and rec.recording:
            rec.add_imu(imu.between(np.iinfo(np.int64).min if prev is None else prev, np.iinfo(np.int64).max))
        gt = seq.groundtruth
        if gt is not None and rec.state in (RECORDING, STOPPED_LOW_DISK):
            rec.write_groundtruth(gt)
    return rec.manifest()
