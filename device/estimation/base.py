"""What every estimator returns, and the loop that runs one over a sequence."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Callable, Iterable, Literal, Protocol

import numpy as np

from stereopath.device.errors import EstimationError
from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.formats.tum import Trajectory

log = logging.getLogger(__name__)

WorldFrame = Literal["first_camera", "gravity_aligned"]


class TrackStatus(StrEnum):
    """How a frame's pose was obtained.  It equals its name as a string (``"ok"``, as in reports and the
    wire's pose message); :attr:`code` is the integer recorded in ``estimate.npz`` and sent on the wire."""

    OK = "ok"  # tracked (or relocalised) by vision
    IMU_ONLY = "imu_only"  # vision failed: the gyro's rotation (constant velocity for the translation)
    LOST = "lost"  # vision failed and no gyro: the constant-velocity prediction

    @property
    def code(self) -> int:
        return list(TrackStatus).index(self)

    @classmethod
    def from_code(cls, code: int) -> TrackStatus:
        return list(cls)[code]


@dataclass
class PoseEstimate:
    """The pose of camera 1 (left) at one stereo frame."""

    seq: int
    t_ns: int
    T_world_cam: np.ndarray
    status: TrackStatus
    inliers: int = 0
    keyframe: bool = False
    note: str = ""  # why a frame is not "ok" (e.g. "too_few_matches")

    def __post_init__(self) -> None:
        self.status = TrackStatus(self.status)  # the name ("ok") is accepted too


class Estimator(Protocol):
    name: str
    world_frame: WorldFrame

    def process(self, frame: StereoFrame, imu: ImuSamples | None) -> PoseEstimate | None:
        """Estimate the pose at ``frame``; ``imu`` holds the samples since the previous frame.

        ``None`` means the method gives no pose for this frame (the paper's method and the
        SFM baseline work on positions every ``frame_step`` frames, not on every video frame).
        """


@dataclass
class EstimateRun:
    estimates: list[PoseEstimate]  # one per frame that got a pose
    frame_ms: list[float]  # one per frame processed
    world_frame: WorldFrame
    estimator: str
    extra: dict[str, int | float | str] = field(default_factory=dict)

    @property
    def trajectory(self) -> Trajectory:
        return Trajectory(np.array([e.t_ns for e in self.estimates], dtype=np.int64),
                          np.array([e.T_world_cam for e in self.estimates]))

    @property
    def frames_tracked(self) -> int:
        return sum(1 for e in self.estimates if e.status is TrackStatus.OK)


@dataclass
class EstimateProgress:
    """A run's results so far and where it stands: the next frame's ``seq`` (a recorded sequence's
    index) and the last frame's time (the IMU samples after it go to the next frame)."""

    estimates: list[PoseEstimate] = field(default_factory=list)
    frame_ms: list[float] = field(default_factory=list)
    next_seq: int = 0
    prev_t: int | None = None
    skipped_frames: list[int] = field(default_factory=list)  # the source's unreadable frames so far (its record)


@dataclass(frozen=True)
class Chunks:
    """``save(progress)`` called after every ``frames`` frames processed (a stage's stored progress)."""

    frames: int
    save: Callable[[EstimateProgress], None]


def run_estimator(estimator: Estimator, frames: Iterable[StereoFrame], imu: ImuSamples | None,
                  progress: Callable[[int], None] | None = None, resume: EstimateProgress | None = None,
                  chunks: Chunks | None = None) -> EstimateRun:
    """Run ``estimator`` over ``frames``, handing it the IMU samples since the previous frame.

    Frame times count only the estimator's own work (``process``), not the
    source (rendering or decoding happens inside the iterator, outside the timer).  ``resume``: the
    progress of an earlier run of this estimator that ``frames`` continue; ``chunks``: where the
    progress goes every so many frames.
    """
    done = resume if resume is not None else EstimateProgress()
    estimates, frame_ms = done.estimates, done.frame_ms
    for frame in frames:
        block = None
        if imu is not None and len(imu):
            t0 = int(imu.t_ns[0]) - 1 if done.prev_t is None else done.prev_t
            block = imu.between(t0, frame.t_ns)
        start = time.perf_counter()
        est = estimator.process(frame, block)
        frame_ms.append((time.perf_counter() - start) * 1e3)
        if est is not None:
            estimates.append(est)
        done.prev_t, done.next_seq = frame.t_ns, frame.seq + 1
        if progress is not None:
            progress(1)
        if chunks is not None and len(frame_ms) % chunks.frames == 0:
            try:
                chunks.save(done)
            except Exception:  # noqa: BLE001 - the stored progress is a convenience: the run goes on without it
                log.exception("the estimate's progress could not be stored; going on without storing it")
                chunks = None
    if not estimates:
        raise EstimationError("no frames to estimate")
    close = getattr(estimator, "close", None)
    if close is not None:
        close()
    rebase = getattr(estimator, "world_rebase", None)
    if rebase is not None:  # the world was redefined during the run: the poses given before, in the new one
        seq, G = rebase
        for e in estimates:
            if e.seq < seq:
                e.T_world_cam = G @ e.T_world_cam
    extra = getattr(estimator, "stats", lambda: {})()
    extra["frames_in"] = len(frame_ms)
    return EstimateRun(estimates, frame_ms, estimator.world_frame, estimator.name, extra=extra)
