"""The ``stereo`` estimator's live state and its counters (pure data).

:class:`LiveState` is everything a keyframe correction moves: the poses the frame loop keeps, the
tracked map, the newest keyframe library's pose and the product of the corrections applied so far.
One call, :meth:`LiveState.apply`, moves them together as one rigid motion.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stereopath.device.core.features import Features
from stereopath.device.core.geometry import project_to_se3
from stereopath.device.estimation.tracked_map import TrackedMap


def compose(G: np.ndarray, C: np.ndarray) -> np.ndarray:
    """The cumulative correction ``C`` followed by ``G`` (kept a rigid motion)."""
    return project_to_se3(G @ C)


@dataclass
class Library:
    """A keyframe's features of all views, each with a stereo 3D point in that keyframe's camera frame."""

    seq: int
    feats: Features
    X_cam: np.ndarray


@dataclass
class LiveState:
    """The live world of the frame loop: every pose in it (camera 1 to world) and the map."""

    T_world_cam: np.ndarray | None = None  # the last frame's pose
    T_prev_prev: np.ndarray | None = None  # the one before (constant velocity)
    T_prev_left: np.ndarray | None = None  # the pose of the camera that took the last tracked image
    T_kf: np.ndarray | None = None  # the last keyframe's pose
    T_asift: np.ndarray | None = None  # the last keyframe whose ASIFT work was submitted
    T_bias_start: np.ndarray | None = None  # the start of the gyro bias window
    library: Library | None = None  # the newest keyframe library joined
    T_library: np.ndarray | None = None  # its keyframe's pose
    map: TrackedMap = field(default_factory=TrackedMap)
    C: np.ndarray = field(default_factory=lambda: np.eye(4))  # the product of the corrections applied so far

    def apply(self, G: np.ndarray) -> None:
        """One rigid motion of the whole live state keeps the map and the poses consistent."""
        self.map.move(G)
        self.T_world_cam, self.T_prev_prev = _moved(G, self.T_world_cam), _moved(G, self.T_prev_prev)
        self.T_prev_left, self.T_kf = _moved(G, self.T_prev_left), _moved(G, self.T_kf)
        self.T_library, self.T_asift = _moved(G, self.T_library), _moved(G, self.T_asift)
        self.T_bias_start = _moved(G, self.T_bias_start)
        self.C = compose(G, self.C)


def _moved(G: np.ndarray, T: np.ndarray | None) -> np.ndarray | None:
    return None if T is None else G @ T


@dataclass
class StereoStats:
    """What the estimator has done so far (``stats()``: the session's estimator.json and the reports)."""

    keyframes: int = 0
    imu_only: int = 0
    lost: int = 0
    asift_matches: int = 0
    kf_jobs: int = 0
    kf_jobs_skipped: int = 0
    kf_jobs_deferred: int = 0
    asift_views: int = 0
    kf_corrections: int = 0
    retracked: int = 0
    relocalised: int = 0
    disparity_offset_pairs: int = 0
    disparity_offset_unidentified: int = 0
    disparity_offset_path_corrections: int = 0
    disparity_offset_windows: int = 0
    exposure_fits: int = 0
    exposure_corrected_frames: int = 0
    gyro_bias_updates: int = 0
    gyro_bias_rejected: int = 0
    start_solves: int = 0  # a start in motion: solves of gyro bias and gravity handed to the worker ...
    start_solved_frame: int = -1  # ... and the frame whose live state the solved one moved (-1: none)
    right_gain_milli: int = 1000  # the right camera's grey levels in the left's: gain (x 1000) ...
    right_offset_centi: int = 0  # ... and offset (x 100)
    disparity_offset_mpx: int = 0  # the disparity offset in use (millipixels)
    window_solves: int = 0  # local window solves submitted ...
    window_corrections: int = 0  # ... whose newest keyframe's correction was applied
    window_cpu_us: int = 0  # the solves' CPU time (the worker thread's)
