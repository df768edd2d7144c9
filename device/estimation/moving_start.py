"""A start in motion on board: the gyro bias and gravity solved from the first keyframes' path.

A rig that rests before its first frame gives both by averaging (:func:`~stereopath.device.estimation.inertial.estimate_still`).
One switched on in the hand does not rest: :class:`MovingStart` keeps the IMU samples and the tracked
poses (every :data:`~stereopath.device.estimation.inertial_init.START_INTERVAL_S`) from the first frame on, and once they span :data:`~stereopath.device.estimation.inertial_init.START_MIN_SPAN_S`
hands :func:`~stereopath.device.estimation.inertial_init.start_from_path` to the keyframe worker (copies:
the frame loop goes on).  A solve that does not pass its checks is tried again with the next pose on
the longer path, over the last :data:`MAX_SPAN_S` at most, up to :data:`MAX_ATTEMPTS` times.  The estimator takes the solved start once:
the gyro bias, and the rotation that levels its world (:meth:`SolvedStart.leveling`).  The poses it gave
before are in the first camera's world; the estimator's ``world_rebase`` (the first frame seq in the
new world, the rotation) lets :func:`~stereopath.device.estimation.base.run_estimator` map them into
the new one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from stereopath.device.core.frames import ImuSamples
from stereopath.device.core.geometry import invert_pose, make_pose
from stereopath.device.estimation.base import PoseEstimate, TrackStatus
from stereopath.device.estimation.inertial import leveling_rotation
from stereopath.device.estimation.inertial_init import START_INTERVAL_S, START_MIN_SPAN_S, StartFit, start_from_path

log = logging.getLogger(__name__)

MAX_SPAN_S = 4.0  # the path and IMU kept for the solve: the last this many seconds
MAX_ATTEMPTS = 25  # solves refused in a row before the start is given up (the world stays the first camera's)


class Pending(Protocol):
    """Work handed to the worker: a Future, or the result of work done in line."""

    def done(self) -> bool: ...

    def result(self) -> StartFit | None: ...


class Runner(Protocol):
    """Where the solve runs: :meth:`~stereopath.device.estimation.keyframe_jobs.KeyframeWorker.run_aside`."""

    def run_aside(self, fn: Callable[[], StartFit | None]) -> Pending: ...


@dataclass(frozen=True)
class SolvedStart:
    """A solved start: the fit, gravity (m/s^2, in the world of the path) and the frame seq of the path's end."""

    fit: StartFit
    gravity_world: np.ndarray
    seq: int

    def leveling(self, R_world_cam0: np.ndarray, R_body_cam: np.ndarray) -> np.ndarray:
        """The rigid motion (a rotation about the world's origin) that takes the live world onto the
        gravity-aligned one a still start would have given, its yaw that of the first camera
        (whose orientation in the live world is ``R_world_cam0``)."""
        return make_pose(leveling_rotation(R_world_cam0, R_body_cam, self.gravity_world), np.zeros(3))


class MovingStart:
    """The path and IMU since the first frame until the start is solved (see the module doc)."""

    def __init__(self, T_body_cam: np.ndarray) -> None:
        self._T_cam_body = invert_pose(np.asarray(T_body_cam, float))
        self._imu: list[ImuSamples] = []
        self._kf: list[tuple[int, np.ndarray]] = []  # (t_ns, T_world_cam as tracked)
        self._job: tuple[Pending, int] | None = None  # (future, frame seq at submission)
        self._kept = 0  # poses kept so far ...
        self._tried_at = 0  # ... and at the last submission
        self.solved = False
        self.attempts = 0

    @property
    def open(self) -> bool:
        """Still collecting: neither solved nor given up."""
        return not self.solved and self.attempts < MAX_ATTEMPTS

    def add_imu(self, block: ImuSamples | None) -> None:
        if block is not None and len(block) and self.open:
            self._imu.append(block)

    def add_pose(self, t_ns: int, T_world_cam: np.ndarray) -> bool:
        """A tracked frame's pose as the frame loop gave it, kept when it is :data:`START_INTERVAL_S` after
        the last one kept (True then).  The path is kept as given: a keyframe correction moves the live
        state to agree with the older poses, which stay where they were."""
        if not self.open or self._kf and (int(t_ns) - self._kf[-1][0]) * 1e-9 < START_INTERVAL_S:
            return False
        self._kf.append((int(t_ns), np.array(T_world_cam, float)))
        self._kept += 1
        t_new = self._kf[-1][0]
        while self._kf and (t_new - self._kf[0][0]) * 1e-9 > MAX_SPAN_S:
            self._kf.pop(0)
        return True

    def feed(self, est: PoseEstimate, imu: ImuSamples | None, worker: Runner) -> bool:
        """One frame of the frame loop: its IMU samples, its pose if tracked, a solve handed to ``worker``
        when due (True then)."""
        self.add_imu(imu)
        return est.status is TrackStatus.OK and self.add_pose(est.t_ns, est.T_world_cam) and self.submit(worker, est.seq)

    def submit(self, worker: Runner, seq: int) -> bool:
        """Hand a solve to the worker when none is in flight, the path is long enough and has grown
        since the last one; True when one was submitted."""
        if not self.open or self._job is not None or self._kept <= self._tried_at or len(self._kf) < 2:
            return False
        if (self._kf[-1][0] - self._kf[0][0]) * 1e-9 < START_MIN_SPAN_S:
            return False
        t0 = self._kf[0][0] - 100_000_000
        imu = ImuSamples.concat(self._imu).between(t0, self._kf[-1][0] + 100_000_000)
        self._imu = [imu]  # what is older than the path kept is not needed again
        t = np.array([k[0] for k in self._kf], np.int64)
        T_body = np.array([T @ self._T_cam_body for _, T in self._kf])
        self._job = (worker.run_aside(lambda: start_from_path(imu, t, T_body)), int(seq))
        self._tried_at = self._kept
        self.attempts += 1
        return True

    def settle(self, freeze: Callable[[Pending], Pending]) -> None:
        """The solve in flight, if any, replaced by ``freeze(it)`` (its result held as plain data)."""
        if self._job is not None:
            self._job = (freeze(self._job[0]), self._job[1])

    def poll(self) -> SolvedStart | None:
        """The solved start once its solve is done and passed; None otherwise (never waits)."""
        if self._job is None or not self._job[0].done():
            return None
        fut, seq = self._job
        self._job = None
        try:
            fit = fut.result()
        except Exception:  # a failed solve is tried again on a longer path
            log.exception("start solve failed")
            return None
        if fit is None:
            if not self.open:
                log.warning("start in motion: %d solves of gyro bias and gravity refused; the world stays the "
                            "first camera's", self.attempts)
                self._imu, self._kf = [], []
            return None
        self.solved = True
        self._imu, self._kf = [], []
        log.info("start in motion solved on the path up to frame %d (%d tries): gyro bias %s rad/s (+- %.5f), "
                 "|g| = %.3f m/s^2, residual %.2f mm per interval; the world becomes gravity aligned", seq,
                 self.attempts, np.round(fit.gyro.bias_rad_s, 5), fit.gyro.sigma_rad_s,
                 float(np.linalg.norm(fit.gravity.gravity_world)), 1e3 * fit.gravity.rms_m)
        return SolvedStart(fit, fit.gravity.gravity_world, seq)
