"""Gyro integration, start-up bias and gravity from a still period, the bias refined from vision.  Pure NumPy."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereopath.device.core.frames import ImuSamples
from stereopath.device.core.geometry import so3_exp, so3_log

GRAVITY_M_S2 = 9.80665


@dataclass
class StillEstimate:
    gyro_bias_rad_s: np.ndarray
    accel_mean_m_s2: np.ndarray
    samples: int
    gyro_std_rad_s: float

    @property
    def gravity_norm_m_s2(self) -> float:
        return float(np.linalg.norm(self.accel_mean_m_s2))


def estimate_still(block: ImuSamples, max_gyro_std_rad_s: float = 0.01, max_accel_dev_m_s2: float = 0.6,
                   min_samples: int = 50) -> StillEstimate | None:
    """Gyro bias and mean specific force of a still block, or None when the block is not still."""
    if len(block) < min_samples:
        return None
    g_std = float(np.max(np.std(block.gyro_rad_s, axis=0)))
    a_norm = np.linalg.norm(block.accel_m_s2, axis=1)
    if g_std > max_gyro_std_rad_s or np.max(np.abs(a_norm - np.median(a_norm))) > 4 * max_accel_dev_m_s2:
        return None
    a_mean = block.accel_m_s2.mean(axis=0)
    if abs(np.linalg.norm(a_mean) - GRAVITY_M_S2) > max_accel_dev_m_s2:
        return None
    return StillEstimate(block.gyro_rad_s.mean(axis=0), a_mean, len(block), g_std)


def gravity_aligned_rotation(accel_mean_body: np.ndarray) -> np.ndarray:
    """``R_world_body`` that maps the measured specific force (pointing up at rest) onto +z.

    The yaw about gravity is unobservable; the body x axis is kept as close to
    the world x-z plane as possible (minimal rotation).
    """
    up_b = np.asarray(accel_mean_body, dtype=float)
    up_b = up_b / np.linalg.norm(up_b)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(up_b, z)
    s = np.linalg.norm(v)
    c = float(np.dot(up_b, z))
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return so3_exp(v / s * np.arctan2(s, c))


def leveling_rotation(R_world_cam: np.ndarray, R_body_cam: np.ndarray, gravity_world: np.ndarray) -> np.ndarray:
    """``R_new_world``: the rotation that takes a world in which gravity is ``gravity_world`` onto the
    gravity-aligned world a still start would have given (z up, the yaw of
    :func:`gravity_aligned_rotation` for the body at ``R_world_cam``, the camera's pose then)."""
    R_world_body = np.asarray(R_world_cam, float) @ np.asarray(R_body_cam, float).T
    up_body = R_world_body.T @ -np.asarray(gravity_world, float)  # what the accelerometer would read at rest
    return gravity_aligned_rotation(up_body) @ R_world_body.T


class GyroIntegrator:
    """Integrates bias-corrected gyro samples into body rotations between frame times.

    Samples are treated as piecewise-linear angular velocity; integration runs
    over exactly ``[t_prev, t_cur]`` using the last sample before ``t_prev`` kept
    from the previous block.
    """

    def __init__(self, bias_rad_s: np.ndarray | None = None) -> None:
        self.bias = np.zeros(3) if bias_rad_s is None else np.asarray(bias_rad_s, dtype=float)
        self._last_t: int | None = None
        self._last_w: np.ndarray | None = None

    def feed_and_integrate(self, block: ImuSamples | None, t_prev: int, t_cur: int) -> np.ndarray | None:
        """``R_bprev_bcur`` over ``[t_prev, t_cur]``; None when the samples do not cover the interval."""
        ts: list[int] = []
        ws: list[np.ndarray] = []
        if self._last_t is not None:
            ts.append(self._last_t)
            ws.append(self._last_w)
        if block is not None and len(block):
            ts.extend(int(t) for t in block.t_ns)
            ws.extend(block.gyro_rad_s)
        if ts:
            self._last_t, self._last_w = ts[-1], ws[-1]  # as measured: the bias may change before it is used
        if len(ts) < 2 or ts[0] > t_prev + 5_000_000 or ts[-1] < t_cur - 5_000_000:
            return None
        wm, dt = midpoint_rates(np.array(ts, dtype=np.int64), np.array(ws) - self.bias, t_prev, t_cur)
        R = np.eye(3)
        for d, wi in zip(dt, wm):
            R = R @ so3_exp(wi * d)
        return R


def midpoint_rates(t_ns: np.ndarray, w: np.ndarray, t0: int, t1: int) -> tuple[np.ndarray, np.ndarray]:
    """Piecewise-linear angular velocity over ``[t0, t1]``: the mean rate of each step between the
    sample times inside it (the ends resampled) and the steps' lengths in seconds."""
    knots = np.concatenate([[t0], t_ns[(t_ns > t0) & (t_ns < t1)], [t1]])
    wk = np.stack([np.interp(knots, t_ns, w[:, k]) for k in range(3)], axis=1)
    return 0.5 * (wk[1:] + wk[:-1]), np.diff(knots) * 1e-9


def carry_bias_jacobian(A: np.ndarray, R_step: np.ndarray, dt_s: float) -> np.ndarray:
    """``A`` (the derivative of an integrated rotation's log by the gyro bias error, up to the end of the
    previous step) after one more step ``R_step`` of ``dt_s`` seconds: ``R_step^T A + dt I``."""
    return R_step.T @ A + dt_s * np.eye(3)


class VisionGyroBias:
    """The gyro bias refined from the camera's own rotation, one window of tracked frames at a time.

    Over a window of ``window_s`` seconds of tracked frames, the gyro integrated with the current
    bias ``b`` gives ``R_gyro`` and the tracked poses give ``R_vis`` (body frame, window start to
    end).  With the true bias ``b + d`` the two differ by ``log(R_vis^T R_gyro) = A d``, where
    ``A = sum_k R_(k->end)^T dt_k`` carries each step's bias error to the window's end (``A = T I``
    without rotation).  Each window's ``d`` is fused by a Kalman update whose measurement noise is
    the tracked rotation's error at both ends (``vision_sigma_rad``) through ``A``, with the bias as
    a random walk; a window whose ``d`` is farther than ``gate_sigma`` standard deviations from the
    prediction is rejected (a bad pose, a moving scene).  Pure compute: the caller keeps the
    window's start pose, feeds the gyro step of every tracked frame and restarts the window when a
    frame is not tracked."""

    def __init__(self, bias_rad_s: np.ndarray | None, sigma_rad_s: float, window_s: float = 1.0,
                 vision_sigma_rad: float = 1e-3, walk_rad_s2_rthz: float = 1e-4, gate_sigma: float = 4.0) -> None:
        self.bias = np.zeros(3) if bias_rad_s is None else np.asarray(bias_rad_s, float).copy()
        self.var = float(sigma_rad_s) ** 2
        self.window_s = float(window_s)
        self.vision_sigma_rad = float(vision_sigma_rad)
        self.walk = float(walk_rad_s2_rthz)
        self.gate_sigma = float(gate_sigma)
        self.updates = 0
        self.rejected = 0
        self.restart()

    @property
    def sigma_rad_s(self) -> float:
        return float(np.sqrt(self.var))

    @property
    def window_full(self) -> bool:
        return self._T >= self.window_s

    def restart(self) -> None:
        """Forget the window's gyro steps (the caller starts it at a new tracked pose)."""
        self._R_gyro, self._A, self._T = np.eye(3), np.zeros((3, 3)), 0.0

    def reset(self, bias_rad_s: np.ndarray, sigma_rad_s: float) -> None:
        """A bias measured otherwise, with its spread: the estimate and the window restart there (the
        counts are kept)."""
        self.bias = np.asarray(bias_rad_s, float).copy()
        self.var = float(sigma_rad_s) ** 2
        self.restart()

    def add(self, R_step_body: np.ndarray, dt_s: float) -> None:
        """The gyro's body rotation from the previous tracked frame to this one (current bias)."""
        R_step_body = np.asarray(R_step_body, float)
        self._A = carry_bias_jacobian(self._A, R_step_body, dt_s)
        self._R_gyro = self._R_gyro @ R_step_body
        self._T += dt_s

    def update(self, R_vis_body: np.ndarray) -> bool:
        """Close the window with the tracked body rotation over it (start to end); True when the bias
        was updated.  The window restarts either way."""
        A, R_gyro, T = self._A, self._R_gyro, self._T
        self.restart()
        if T <= 0.0:
            return False
        e = so3_log(np.asarray(R_vis_body, float).T @ R_gyro)
        try:
            A_inv = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            return False
        d = A_inv @ e
        meas_var = 2.0 * self.vision_sigma_rad**2 * float(np.max(np.linalg.eigvalsh(A_inv @ A_inv.T)))
        prior_var = self.var + self.walk**2 * T
        self.var = prior_var
        if float(np.max(np.abs(d))) > self.gate_sigma * np.sqrt(prior_var + meas_var):
            self.rejected += 1
            return False
        k = prior_var / (prior_var + meas_var)
        self.bias = self.bias + k * d
        self.var = (1.0 - k) * prior_var
        self.updates += 1
        return True
