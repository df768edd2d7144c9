"""The frame pipeline: ``source -> time align -> estimate -> sinks`` on its own thread.

It pulls stereo pairs from the source, drains the IMU, attaches the IMU samples to each frame
(:class:`~stereopath.device.capture.timealign.TimeAligner`), hands each frame to its sinks (the
recorder first, so a frame is on disk before it is estimated), runs the estimator and hands the
estimate to the sinks (pose to the recorder, pose and keyframes to the streamer).  Counters are
plain attributes with a single writer (this thread), read by the supervisor.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Iterable, Protocol, Sequence

from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.errors import EstimationError, StereopathError
from stereopath.device.estimation.base import Estimator, PoseEstimate, TrackStatus
from stereopath.device.service.sinks import FrameSink

if TYPE_CHECKING:
    from stereopath.device.capture.timealign import TimeAligner
    from stereopath.device.settings import TimeAlignSettings

log = logging.getLogger(__name__)


@dataclass
class PipelineCounters:
    """What the pipeline has done so far (read by the supervisor and the status report)."""

    frames_in: int = 0
    frames_done: int = 0
    imu_samples_in: int = 0
    keyframes: int = 0
    estimation_errors: int = 0
    tracked_frames: int = 0
    last_frame_at: float | None = None
    last_imu_at: float | None = None
    last_estimate: PoseEstimate | None = None
    stage_ms: dict[str, float] = field(default_factory=dict)  # average time per frame of each stage (ms)
    # the estimator's own time per frame (ms), kept for the session's estimator.json
    estimate_ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=200_000))
    # the estimator redefined its world (a start in motion, levelled once): poses given before this frame
    # time are in the earlier world, ``T_new_old`` maps them (kept for the session's estimator.json)
    world_rebase: dict[str, object] | None = None

    def average(self, stage: str, seconds: float) -> None:
        """Exponential average of a stage's time per frame (ms)."""
        ms = seconds * 1e3
        old = self.stage_ms.get(stage)
        self.stage_ms[stage] = ms if old is None else 0.9 * old + 0.1 * ms


class ImuReader(Protocol):
    def read(self) -> ImuSamples:
        """The samples that arrived since the last read."""


@dataclass
class FrameInputs:
    """What a run's frame loop reads and runs: the stereo frames, the IMU (or None), the time alignment
    that attaches the IMU samples to each frame, and the estimator."""

    source: Iterable[StereoFrame]
    imu: ImuReader | None
    aligner: TimeAligner
    estimator: Estimator


class FramePipeline:
    """One capture run's frame loop; :meth:`run` is the pipeline thread's body."""

    def __init__(self, inputs: FrameInputs, sinks: Sequence[FrameSink], *, stop: threading.Event,
                 request_stop: Callable[[str], None], frame_limit: int | None = None,
                 clock: Callable[[], float] = time.monotonic, counters: PipelineCounters | None = None) -> None:
        self.source = inputs.source
        self.imu = inputs.imu
        self.aligner = inputs.aligner
        self.estimator = inputs.estimator
        self.sinks = list(sinks)
        self.counters = counters if counters is not None else PipelineCounters()
        self.failure: BaseException | None = None
        self.done = threading.Event()
        self._stop = stop
        self._request_stop = request_stop
        self._frame_limit = frame_limit
        self._clock = clock
        self._pending_timealign: TimeAlignSettings | None = None

    def set_timealign(self, settings: TimeAlignSettings) -> None:
        """New ``[timealign]`` settings, applied by the pipeline thread before its next frame."""
        self._pending_timealign = settings

    def run(self, on_end: Callable[[], None] = lambda: None) -> None:
        try:
            self._loop()
        except StereopathError as exc:
            if self._stop.is_set() and self.counters.frames_in:
                log.info("pipeline ended while stopping: %s", exc)
            else:
                self.failure = exc
        except Exception as exc:  # a bug: keep the traceback
            log.exception("pipeline thread failed")
            self.failure = exc
        finally:
            self.done.set()
            on_end()

    def _loop(self) -> None:
        c = self.counters
        frames = iter(self.source)
        while not self._stop.is_set():
            frame = next(frames, None)
            if frame is None:
                self._request_stop("the source has no more frames")
                break
            now = self._clock()
            c.last_frame_at = now
            c.frames_in += 1
            self._take_imu(now)
            if self._pending_timealign is not None:
                self._apply_timealign()
            for done in self.aligner.add_frame(frame):
                self._handle(done)
            if self._frame_limit is not None and c.frames_in >= self._frame_limit:
                self._request_stop(f"{self._frame_limit} frames captured")
                break
        if self.failure is None:
            self._take_imu(self._clock())
        for done in self.aligner.flush():
            self._handle(done)

    def _take_imu(self, now: float) -> None:
        if self.imu is None:
            return
        block = self.imu.read()
        if len(block):
            self.counters.last_imu_at = now
            self.counters.imu_samples_in += len(block)
            for sink in self.sinks:
                sink.add_imu(block)
            self.aligner.add_imu(block)

    def _handle(self, frame: StereoFrame) -> None:
        c = self.counters
        spent = dict.fromkeys((s.name for s in self.sinks), 0.0)
        for sink in self.sinks:
            t0 = time.perf_counter()
            sink.add_frame(frame)
            spent[sink.name] += time.perf_counter() - t0
        t0 = time.perf_counter()
        try:
            est = self.estimator.process(frame, frame.imu)
        except EstimationError as exc:
            c.estimation_errors += 1
            log.log(logging.WARNING if c.estimation_errors == 1 else logging.DEBUG,
                    "frame %d not estimated: %s%s", frame.seq, exc,
                    " (further failures are counted in the status)" if c.estimation_errors == 1 else "")
            self._note_times(spent)
            return
        dt = time.perf_counter() - t0
        c.average("estimate", dt)
        c.estimate_ms.append(dt * 1e3)
        if est is None:  # no pose for this frame (not an on-board estimator's answer)
            self._note_times(spent)
            return
        c.last_estimate = est
        c.frames_done += 1
        if c.world_rebase is None:
            self._note_world_rebase(frame)
        c.tracked_frames += est.status is TrackStatus.OK
        c.keyframes += bool(est.keyframe)
        for sink in self.sinks:
            t0 = time.perf_counter()
            sink.add_estimate(frame, est)
            spent[sink.name] += time.perf_counter() - t0
        self._note_times(spent)

    def _note_world_rebase(self, frame: StereoFrame) -> None:
        """The estimator levelled its world at this frame: the poses recorded and streamed before it are
        in the earlier world; the session's estimator.json says how to map them."""
        rebase = getattr(self.estimator, "world_rebase", None)
        if rebase is None:
            return
        _, G = rebase
        self.counters.world_rebase = {"from_t_ns": int(frame.t_ns), "T_new_old": [[float(v) for v in row] for row in G]}
        for sink in self.sinks:  # the hosts hold poses of the earlier world: they are told how to map them
            sink.world_rebased(int(frame.t_ns), G)
        log.info("world frame levelled at frame %d: poses before it are in the first camera's world "
                 "(estimator.json world_rebase maps them)", frame.seq)

    def _note_times(self, spent: dict[str, float]) -> None:
        for name, seconds in spent.items():
            self.counters.average(name, seconds)

    def _apply_timealign(self) -> None:
        s, self._pending_timealign = self._pending_timealign, None
        a = self.aligner
        a.time_offset_ns = int(round(s.time_offset_us * 1000))
        a.max_wait_ns = int(round(s.max_wait_ms * 1e6))
        a.gap_factor = float(s.gap_factor)

    def estimator_summary(self) -> dict[str, object] | None:
        """``estimator.json``: the estimator's time per frame and tracking counts (None before any estimate)."""
        c = self.counters
        if not c.estimate_ms:
            return None
        import numpy as np

        ms = np.array(c.estimate_ms)
        stats = getattr(self.estimator, "stats", lambda: {})()
        return {
            "estimator": getattr(self.estimator, "name", "?"),
            "world_frame": getattr(self.estimator, "world_frame", "first_camera"),
            "frames": int(c.frames_done), "frames_tracked": int(c.tracked_frames),
            **({"world_rebase": c.world_rebase} if c.world_rebase is not None else {}),
            "median_frame_ms": float(np.median(ms)), "p95_frame_ms": float(np.percentile(ms, 95)),
            "stats": {k: v for k, v in stats.items() if isinstance(v, (int, float, bool, str))},
            "frame_ms": [round(float(v), 3) for v in ms],
        }
