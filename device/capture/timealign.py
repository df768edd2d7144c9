"""Time alignment: IMU samples attached to stereo frames, and a rate/drop monitor.

Clock convention (Kalibr's ``timeshift_cam_imu``): ``t_imu = t_cam + offset``, so an IMU
timestamp is brought onto the camera clock as ``t_cam = t_imu - offset``.  The offset is
a calibrated parameter (``timealign.time_offset_us``).

:class:`TimeAligner` buffers IMU samples and gives every frame ``k`` the block
``frame.imu``: an interpolated sample at the previous frame's time, every raw
sample strictly between the two frames, and an interpolated sample at this frame's time
(the first frame gets the pre-roll instead: up to 2 s of samples before it, so that an
estimator can take the gyro bias and gravity from the start-up rest).  Integrating the block therefore
covers exactly ``[t_{k-1}, t_k]``.  A frame is released once a sample at or after its
time has arrived; if none arrives within ``max_wait`` (measured in frame time, so
independent of the host clock) it is released with the last sample held
(``meta["imu_complete"] = False``).  ``meta["imu_gap"]`` is set when the block spans a
step longer than ``gap_factor`` IMU periods.

:class:`RateMonitor` reports the observed camera frame rate, IMU rate, dropped frames
(timestamp steps of more than 1.5 frame periods) and IMU gaps.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Iterable, Iterator

import numpy as np

from stereopath.device.core.frames import ImuSamples, StereoFrame

PREROLL_NS = 2_000_000_000  # IMU samples before the first frame handed to it

if TYPE_CHECKING:
    from stereopath.device.settings import TimeAlignSettings

log = logging.getLogger(__name__)


@dataclass
class MonitorReport:
    frames: int
    camera_fps: float          # observed, from frame timestamps (0 when < 2 frames)
    dropped_frames: int        # estimated from timestamp steps longer than 1.5 frame periods
    imu_samples: int
    imu_hz: float              # observed, from sample timestamps
    imu_gaps: int              # steps longer than gap_factor IMU periods (plus gaps the driver reported)
    imu_gap_s: float           # total time inside those gaps

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


class RateMonitor:
    """Counts frames and IMU samples as they pass (see module doc)."""

    def __init__(self, nominal_fps: float | None = None, nominal_imu_hz: float | None = None,
                 gap_factor: float = 2.5) -> None:
        self.frame_period_ns = None if not nominal_fps else 1e9 / nominal_fps
        self.imu_period_ns = None if not nominal_imu_hz else 1e9 / nominal_imu_hz
        self.gap_factor = float(gap_factor)
        self.frames = 0
        self.dropped_frames = 0
        self._t_first: int | None = None
        self._t_last: int | None = None
        self._frame_dts: deque[int] = deque(maxlen=64)
        self.imu_samples = 0
        self._imu_first: int | None = None
        self._imu_last: int | None = None
        self._imu_dts: deque[float] = deque(maxlen=8)
        self.imu_gaps = 0
        self.imu_gap_ns = 0
        self.reported_gaps: list[tuple[int, int]] = []

    def frame(self, t_ns: int) -> None:
        t = int(t_ns)
        if self._t_last is not None:
            dt = t - self._t_last
            if dt > 0:
                self._frame_dts.append(dt)
            period = self.frame_period_ns or (float(np.median(self._frame_dts)) if len(self._frame_dts) >= 3 else None)
            if period and dt > 1.5 * period:
                self.dropped_frames += int(round(dt / period)) - 1
        else:
            self._t_first = t
        self._t_last = t
        self.frames += 1

    def imu(self, samples: ImuSamples) -> None:
        if not len(samples):
            return
        t = samples.t_ns
        if self._imu_last is not None:
            t = np.concatenate([[self._imu_last], t])
        else:
            self._imu_first = int(t[0])
        dts = np.diff(t)
        if len(dts):
            self._imu_dts.append(float(np.median(dts)))
            period = self.imu_period_ns or float(np.median(self._imu_dts))
            big = dts > self.gap_factor * period
            self.imu_gaps += int(np.count_nonzero(big))
            self.imu_gap_ns += int(np.sum(dts[big]))
        self._imu_last = int(samples.t_ns[-1])
        self.imu_samples += len(samples)

    def report(self) -> MonitorReport:
        fps = 0.0
        if self.frames >= 2 and self._t_last > self._t_first:
            fps = (self.frames - 1) * 1e9 / (self._t_last - self._t_first)
        hz = 0.0
        if self.imu_samples >= 2 and self._imu_last > self._imu_first:
            hz = (self.imu_samples - 1) * 1e9 / (self._imu_last - self._imu_first)
        return MonitorReport(self.frames, fps, self.dropped_frames, self.imu_samples, hz,
                             self.imu_gaps, self.imu_gap_ns / 1e9)


def interpolate(samples: ImuSamples, t_ns: int) -> ImuSamples:
    """One sample at ``t_ns``, linearly interpolated (held constant outside the samples' span)."""
    ts = samples.t_ns.astype(np.float64)
    tq = float(t_ns)
    g = [np.interp(tq, ts, samples.gyro_rad_s[:, j]) for j in range(3)]
    a = [np.interp(tq, ts, samples.accel_m_s2[:, j]) for j in range(3)]
    temp = None if samples.temp_c is None else np.array([np.interp(tq, ts, samples.temp_c)])
    return ImuSamples(np.array([t_ns], np.int64), np.array([g]), np.array([a]), temp)


class TimeAligner:
    """Attaches IMU blocks to frames (see module doc); feed with :meth:`add_imu` / :meth:`add_frame`."""

    def __init__(self, time_offset_ns: int = 0, max_wait_ns: int = 100_000_000, gap_factor: float = 2.5,
                 nominal_imu_hz: float | None = None, monitor: RateMonitor | None = None) -> None:
        self.time_offset_ns = int(time_offset_ns)
        self.max_wait_ns = int(max_wait_ns)
        self.gap_factor = float(gap_factor)
        self.imu_period_ns = None if not nominal_imu_hz else 1e9 / nominal_imu_hz
        self.monitor = monitor
        self._imu = ImuSamples.empty()
        self._pending: deque[StereoFrame] = deque()
        self._t_prev: int | None = None

    @classmethod
    def from_settings(cls, settings: "TimeAlignSettings", nominal_imu_hz: float | None = None,
                      monitor: RateMonitor | None = None) -> "TimeAligner":
        """From the ``[timealign]`` section (offset in µs, wait in ms)."""
        return cls(int(round(settings.time_offset_us * 1000)), int(round(settings.max_wait_ms * 1e6)),
                   settings.gap_factor, nominal_imu_hz, monitor)

    def add_imu(self, samples: ImuSamples) -> None:
        if not len(samples):
            return
        if self.time_offset_ns:
            samples = ImuSamples(samples.t_ns - self.time_offset_ns, samples.gyro_rad_s, samples.accel_m_s2,
                                 samples.temp_c)
        if len(self._imu):
            keep = samples.t_ns > self._imu.t_ns[-1]
            if not np.all(keep):
                samples = samples.slice(int(np.argmax(keep)) if np.any(keep) else len(samples), len(samples))
        if self.monitor is not None:
            self.monitor.imu(samples)
        self._imu = ImuSamples.concat([self._imu, samples])

    def add_frame(self, frame: StereoFrame) -> list[StereoFrame]:
        """Queue a frame; return the frames that are now complete, oldest first."""
        if self.monitor is not None:
            self.monitor.frame(frame.t_ns)
        self._pending.append(frame)
        return self._release(latest_t=frame.t_ns)

    def flush(self) -> list[StereoFrame]:
        """Release every waiting frame with whatever IMU samples there are (end of stream)."""
        out = []
        while self._pending:
            out.append(self._attach(self._pending.popleft()))
        return out

    def _release(self, latest_t: int) -> list[StereoFrame]:
        out = []
        while self._pending:
            f = self._pending[0]
            covered = len(self._imu) and self._imu.t_ns[-1] >= f.t_ns
            if not covered and latest_t - f.t_ns < self.max_wait_ns:
                break
            out.append(self._attach(self._pending.popleft()))
        return out

    def _period(self) -> float | None:
        if self.imu_period_ns:
            return self.imu_period_ns
        if len(self._imu) >= 3:
            return float(np.median(np.diff(self._imu.t_ns[-50:])))
        return None

    def _attach(self, frame: StereoFrame) -> StereoFrame:
        t_k = int(frame.t_ns)
        imu = self._imu
        meta = frame.meta
        if not len(imu):
            frame.imu = ImuSamples.empty()
            meta["imu_complete"] = False
            meta["imu_gap"] = True
            self._t_prev = t_k
            return frame
        parts = []
        t_prev = self._t_prev
        if t_prev is not None and t_prev < t_k:
            parts.append(interpolate(imu, t_prev))
            inner = imu.between(t_prev, t_k - 1)  # t_prev < t < t_k
        elif t_prev is None:
            # first frame: the pre-roll (up to PREROLL_NS of samples before it), from which an
            # estimator takes the gyro bias and gravity when the device starts at rest
            inner = imu.between(t_k - PREROLL_NS - 1, t_k - 1)
        else:
            inner = ImuSamples.empty()
        parts.append(inner)
        parts.append(interpolate(imu, t_k))
        block = ImuSamples.concat(parts)
        frame.imu = block
        meta["imu_complete"] = bool(imu.t_ns[-1] >= t_k and (t_prev is None or imu.t_ns[0] <= t_prev))
        period = self._period()
        gap = False
        if period and len(block) >= 2:
            # steps between real samples (the interpolated ends are not evidence of data)
            lo = int(np.searchsorted(imu.t_ns, t_prev if t_prev is not None else t_k, side="right")) - 1
            hi = int(np.searchsorted(imu.t_ns, t_k, side="left")) + 1
            real = imu.t_ns[max(lo, 0):min(hi, len(imu))]
            gap = bool(len(real) >= 2 and np.max(np.diff(real)) > self.gap_factor * period)
        meta["imu_gap"] = gap or not meta["imu_complete"]
        self._t_prev = t_k
        # keep only what the next frame can still need
        cut = int(np.searchsorted(imu.t_ns, t_k, side="left")) - 1
        if cut > 0:
            self._imu = imu.slice(cut, len(imu))
        return frame


def align_stream(frames: Iterable[StereoFrame], imu: object | None, time_offset_ns: int = 0,
                 max_wait_ns: int = 100_000_000, gap_factor: float = 2.5, nominal_imu_hz: float | None = None,
                 monitor: RateMonitor | None = None) -> Iterator[StereoFrame]:
    """Frames with ``imu`` attached, reading ``imu.read()`` before each frame."""
    aligner = TimeAligner(time_offset_ns, max_wait_ns, gap_factor, nominal_imu_hz, monitor)
    for frame in frames:
        if imu is not None:
            aligner.add_imu(imu.read())
        yield from aligner.add_frame(frame)
    if imu is not None:
        aligner.add_imu(imu.read())
    yield from aligner.flush()
