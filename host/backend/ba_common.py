"""What every bundle-adjustment back end shares: the observation rows, the result, rotation
priors, the reprojection residuals (NumPy, for statistics and outlier removal) and the
propagation of keyframe corrections to the other frames.

Observations are rows ``(pose index, point id, cam, u, v[, weight])`` in undistorted pixels
(cam 0 left, 1 right); the optional weight scales the residual (``sigma_nominal / sigma``).  They come
as a float (N, 5) or (N, 6) array, or held compact (:mod:`~stereopath.host.backend.observations`) and
widened a window at a time by :func:`as_observations`.

Pure computation: no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from stereopath.device.core.config import check_ranges, ranged
from stereopath.device.core.geometry import invert_pose, so3_exp, so3_log
from stereopath.device.core.rig import Rig
from stereopath.device.errors import ConfigError, EstimationError
from stereopath.host.backend.observations import widened

if TYPE_CHECKING:
    from stereopath.host.backend.imu_factors import ImuTerms
    from stereopath.host.backend.loops import Loop

LOSSES = ("huber", "cauchy", "linear")
MIN_POSES_PER_POINT = 2  # a point seen from fewer poses constrains nothing and is left out
# Levenberg-Marquardt stops when an iteration lowers the cost by less than this fraction (the last such
# steps move the keyframes by micrometres)
RELATIVE_TOL = 1e-4


@dataclass(frozen=True)
class BAConfig:
    """Settings of the keyframe bundle adjustment (:func:`stereopath.host.backend.gtsam_ba.bundle_adjust`)."""

    loss: str = "huber"  # robust loss of the reprojection error: huber, cauchy or linear
    robust_px: float = ranged(1.0, 0.01, 100.0)  # where the robust loss turns (pixels)
    max_iterations: int = ranged(30, 1, 10_000)  # Levenberg-Marquardt iterations per solve
    outlier_px: float = ranged(3.0, 0.1, 1000.0)  # residuals above this are dropped between solves ...
    outlier_rounds: int = ranged(1, 0, 100)  # ... this many times
    disparity_offset: bool = True  # estimate a constant disparity error (the right principal point)
    disparity_offset_min_px: float = ranged(0.02, 0.0, 100.0)  # smaller estimates are noise: not applied
    # IMU preintegration between keyframes (the reprocessing's ba stage, when the session's IMU fits the path)
    imu: bool = True
    relative_tol: float = ranged(RELATIVE_TOL, 0.0, 1.0)  # the last solve's stopping rule

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ConfigError(f"ba.loss = {self.loss!r}; known: {', '.join(LOSSES)}")
        check_ranges(self, "ba.")


@dataclass
class BAProblem:
    """What a bundle adjustment refines: poses ``T_world_cam`` (K, 4, 4), ``points`` {id: XYZ world} and the
    observation rows linking them, plus verified ``loops`` and preintegrated ``imu`` terms between
    consecutive poses; the first ``n_fixed`` poses are held (the gauge; with IMU terms free to tilt,
    which gravity then fixes, unless ``held_may_tilt`` is False), and ``disparity_offset_px`` is the
    right principal point's offset to start from."""

    T_world_cam: np.ndarray
    points: dict[int, np.ndarray]
    observations: np.ndarray
    loops: list[Loop] = field(default_factory=list)
    imu: ImuTerms | None = None
    n_fixed: int = 1
    disparity_offset_px: float = 0.0
    held_may_tilt: bool = True


@dataclass
class BAResult:
    T_world_cam: np.ndarray  # (K, 4, 4) refined poses
    points: dict[int, np.ndarray]
    rms_before_px: float
    rms_after_px: float
    n_obs: int
    n_points: int
    iterations: int
    cost_before: float = float("nan")
    cost_after: float = float("nan")
    inlier_fraction: float = float("nan")  # observations with a residual below ``outlier_px``
    history: list[float] = field(default_factory=list)  # robust cost after each iteration
    disparity_offset_px: float = 0.0  # estimated right principal-point offset (0 unless estimated)
    imu_biases: np.ndarray | None = None  # (K, 6) accelerometer then gyro bias per pose (with IMU factors)
    gravity_world: np.ndarray | None = None  # gravity (m/s^2) in the world of ``T_world_cam`` (with IMU factors)
    pixel_sigma_px: float | None = None  # the observations' measured noise (set where other factors weigh against them)


@dataclass(frozen=True)
class RotationPrior:
    """A measured relative rotation ``R_ci_cj`` (camera j to camera i) between poses ``i`` and ``j``."""

    i: int
    j: int
    R_ci_cj: np.ndarray
    sigma_rad: float


def as_observations(observations: np.ndarray) -> np.ndarray:
    """``observations`` (either form) as a float (N, 5) or (N, 6) array; EstimationError on any other shape."""
    raw = np.asarray(observations)
    if raw.dtype.names is not None:
        return widened(raw)
    obs = np.asarray(raw, dtype=float)
    if obs.size == 0:
        return np.zeros((0, 5))
    if obs.ndim != 2 or obs.shape[1] not in (5, 6):
        raise EstimationError(f"observations must be (N, 5) or (N, 6) rows, got shape {obs.shape}")
    return obs


def select_observations(observations: np.ndarray, points: dict[int, np.ndarray],
                        min_poses_per_point: int = 2) -> np.ndarray:
    """The observation rows of known points seen from at least ``min_poses_per_point`` poses."""
    obs = as_observations(observations)
    if len(obs) == 0:
        return obs
    pid = obs[:, 1].astype(np.int64)
    known = np.isin(pid, np.fromiter(points.keys(), dtype=np.int64, count=len(points)))
    obs, pid = obs[known], pid[known]
    if len(obs) == 0:
        return obs
    pairs = np.unique(np.column_stack([pid, obs[:, 0].astype(np.int64)]), axis=0)
    ids, counts = np.unique(pairs[:, 0], return_counts=True)
    good = ids[counts >= min_poses_per_point]
    return obs[np.isin(pid, good)]


def check_problem(T_world_cam: np.ndarray, observations: np.ndarray, points: dict[int, np.ndarray],
                  min_poses_per_point: int) -> tuple[np.ndarray, np.ndarray]:
    """Validated ``(poses (K, 4, 4), usable observation rows)``; EstimationError when too little."""
    T_world_cam = np.asarray(T_world_cam, dtype=float).reshape(-1, 4, 4)
    obs = as_observations(observations)
    if len(T_world_cam) < 2 or len(obs) == 0:
        raise EstimationError("bundle adjustment needs at least two poses with observations")
    if np.any(obs[:, 0] < 0) or np.any(obs[:, 0] >= len(T_world_cam)):
        raise EstimationError(f"bundle adjustment: observation pose index outside 0..{len(T_world_cam) - 1}")
    obs = select_observations(obs, points, min_poses_per_point)
    n_pts = len(np.unique(obs[:, 1])) if len(obs) else 0
    if n_pts < 10:
        raise EstimationError(f"bundle adjustment: only {n_pts} points seen from two poses")
    return T_world_cam, obs


def reprojection_residuals(rig: Rig, T_world_cam: np.ndarray, points: dict[int, np.ndarray], obs: np.ndarray,
                           disparity_offset_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) weighted pixel residuals of ``obs`` and the mask of observations in front of their camera."""
    obs = as_observations(obs)
    kf = obs[:, 0].astype(np.int64)
    right = obs[:, 2].astype(int) == 1
    X = np.array([points[int(p)] for p in obs[:, 1].astype(np.int64)], float).reshape(-1, 3)
    T_cw = np.array([invert_pose(T) for T in np.asarray(T_world_cam, float).reshape(-1, 4, 4)])
    Xc = np.einsum("nij,nj->ni", T_cw[kf, :3, :3], X) + T_cw[kf, :3, 3]
    Xc[right] = Xc[right] @ np.asarray(rig.R, float).T + np.asarray(rig.T, float)
    K0, K1 = rig.cam0.K, rig.cam1.K
    f = np.where(right[:, None], [K1[0, 0], K1[1, 1]], [K0[0, 0], K0[1, 1]])
    c = np.where(right[:, None], [K1[0, 2] + disparity_offset_px, K1[1, 2]], [K0[0, 2], K0[1, 2]])
    z = Xc[:, 2]
    front = z > 1e-6
    p = f * Xc[:, :2] / np.where(front, z, 1.0)[:, None] + c
    w = obs[:, 5] if obs.shape[1] > 5 else np.ones(len(obs))
    r = (p - obs[:, 3:5]) * w[:, None]
    r[~front] = 0.0
    return r, front


def rms_px(r: np.ndarray, front: np.ndarray) -> float:
    """Root mean square per image coordinate of the residuals in front of their camera."""
    rn2 = np.sum(r[front] ** 2, axis=1)
    return float(np.sqrt(np.mean(rn2 / 2))) if len(rn2) else float("nan")


def propagate_to_frames(T_frames: np.ndarray, frame_kf: np.ndarray, T_kf_old: np.ndarray,
                        T_kf_new: np.ndarray) -> np.ndarray:
    """Move every frame with the correction of its keyframe: ``T_new = T_kf_new inv(T_kf_old) T_old``."""
    out = np.empty_like(T_frames)
    for i, (T, k) in enumerate(zip(T_frames, frame_kf)):
        out[i] = T_kf_new[k] @ invert_pose(T_kf_old[k]) @ T
    return out


def interpolate_corrections(t_frames: np.ndarray, T_frames: np.ndarray, t_kf: np.ndarray, T_kf_old: np.ndarray,
                            T_kf_new: np.ndarray) -> np.ndarray:
    """Move every frame by the correction ``C = T_new inv(T_old)`` interpolated in time between the two
    keyframes around it (rotation by SLERP on the log, translation linearly); constant outside."""
    t_frames = np.asarray(t_frames, dtype=float)
    t_kf = np.asarray(t_kf, dtype=float)
    C = np.array([Tn @ invert_pose(To) for Tn, To in zip(T_kf_new, T_kf_old)])
    out = np.empty_like(T_frames)
    for i, (t, T) in enumerate(zip(t_frames, T_frames)):
        j = int(np.searchsorted(t_kf, t, side="right")) - 1
        if j < 0:
            Ci = C[0]
        elif j >= len(t_kf) - 1:
            Ci = C[-1]
        else:
            a = (t - t_kf[j]) / max(t_kf[j + 1] - t_kf[j], 1e-12)
            dR = so3_log(C[j][:3, :3].T @ C[j + 1][:3, :3])
            Ci = np.eye(4)
            Ci[:3, :3] = C[j][:3, :3] @ so3_exp(a * dR)
            Ci[:3, 3] = (1 - a) * C[j][:3, 3] + a * C[j + 1][:3, 3]
        out[i] = Ci @ T
    return out
