"""The IMU's start-up unknowns from a metric camera path, for a recording with no still start.  Pure NumPy.

A rig that rests before its first frame gives the gyro bias and gravity by averaging; one switched on in
the hand (or EuRoC's, whose IMU starts with its cameras) never rests, so the stereo path stands in.
:func:`gyro_bias_from_path`: the gyro integrated between keyframes against the path's rotations, all
intervals in one least-squares problem, re-integrated and solved again.  :func:`gravity_from_path`: the
preintegrated increments against the path's positions, ``p_j = p_i + v_i dt + g dt^2 / 2 + R_i dp``,
``v_j = v_i + g dt + R_i dv``: one linear solve for the velocities and gravity (accelerometer bias left
at zero; the back end refines both).  It reports how well the increments fit, so the caller can refuse
readings that do not fit the path.  A time offset between IMU and cameras on a slow hand-held path is
not seen (gravity dominates).  See docs/architecture.md, "Reprocessing".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereopath.device.core.frames import ImuSamples
from stereopath.device.core.geometry import so3_exp, so3_log
from stereopath.device.estimation.inertial import GRAVITY_M_S2, carry_bias_jacobian, midpoint_rates


@dataclass(frozen=True)
class GyroBiasFit:
    bias_rad_s: np.ndarray
    sigma_rad_s: float  # formal standard deviation of each axis, scaled by the residuals
    intervals: int
    rms_rad: float  # rotation residual per interval at the solution


@dataclass(frozen=True)
class GravityFit:
    gravity_world: np.ndarray  # m/s^2, pointing down
    velocities: np.ndarray  # (K, 3) world velocities at the keyframes (nan where no interval touches one)
    intervals: int
    rms_m: float  # position residual per interval at the solution
    rms_m_s: float  # velocity residual per interval


def _interval(imu: ImuSamples, t0: int, t1: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Angular velocities at the knots of ``[t0, t1]`` (ends interpolated) and the knots' steps (s)."""
    blk = imu.between(t0 - 50_000_000, t1 + 50_000_000)
    if len(blk) < 2 or blk.t_ns[0] > t0 + 5_000_000 or blk.t_ns[-1] < t1 - 5_000_000:
        return None
    return midpoint_rates(blk.t_ns.astype(np.int64), blk.gyro_rad_s, t0, t1)


def _integrate(wm: np.ndarray, dt: np.ndarray, bias: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R_gyro`` over an interval at ``bias`` and ``A``, the derivative of its log by the bias error."""
    R, A = np.eye(3), np.zeros((3, 3))
    for w, d in zip(wm - bias, dt):
        step = so3_exp(w * d)
        A = carry_bias_jacobian(A, step, d)
        R = R @ step
    return R, A


def gyro_bias_from_path(imu: ImuSamples, t_kf: np.ndarray, R_world_body: np.ndarray,
                        bias_rad_s: np.ndarray | None = None, iterations: int = 3) -> GyroBiasFit | None:
    """The gyro bias that makes the gyro's rotations between consecutive keyframes (times ``t_kf``, ns)
    agree with the path's (``R_world_body``, (K, 3, 3)); None with fewer than two usable intervals."""
    spans = []
    for i in range(len(t_kf) - 1):
        s = _interval(imu, int(t_kf[i]), int(t_kf[i + 1]))
        if s is not None:
            spans.append((s, np.asarray(R_world_body[i], float).T @ np.asarray(R_world_body[i + 1], float)))
    if len(spans) < 2:
        return None
    b = np.zeros(3) if bias_rad_s is None else np.asarray(bias_rad_s, float).copy()
    for _ in range(max(1, iterations)):
        A, e = _stack(spans, b)
        d, *_ = np.linalg.lstsq(A, e, rcond=None)
        b = b + d
        if np.linalg.norm(d) < 1e-9:
            break
    A, e = _stack(spans, b)
    dof = max(len(e) - 3, 1)
    s2 = float(e @ e) / dof
    try:
        sigma = float(np.sqrt(max(s2, 1e-12) * np.max(np.diag(np.linalg.inv(A.T @ A)))))
    except np.linalg.LinAlgError:
        return None
    return GyroBiasFit(b, sigma, len(spans), float(np.sqrt(3 * s2)))


def _stack(spans: list, bias: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rows, res = [], []
    for (wm, dt), R_vis in spans:
        R_gyro, A = _integrate(wm, dt, bias)
        rows.append(A)
        res.append(so3_log(R_vis.T @ R_gyro))
    return np.vstack(rows), np.concatenate(res)


def gravity_from_path(t_kf: np.ndarray, T_world: np.ndarray, increments: list) -> GravityFit | None:
    """Gravity (world frame) and the keyframe velocities from the path ``T_world`` ((K, 4, 4), the frame the
    increments are expressed in: position and rotation to the world) and ``increments``: tuples
    ``(i, j, dp, dv)`` of keyframe intervals, ``dp``/``dv`` preintegrated in keyframe ``i``'s frame without
    gravity.  None with fewer than two intervals."""
    if len(increments) < 2:
        return None
    K = len(T_world)
    used = sorted({k for i, j, *_ in increments for k in (i, j)})
    col = {k: n for n, k in enumerate(used)}
    n_unk = 3 * len(used) + 3
    rows, rhs = [], []
    I3 = np.eye(3)
    scale_p = []
    for i, j, dp, dv in increments:
        dt = (int(t_kf[j]) - int(t_kf[i])) * 1e-9
        Ri, pi, pj = T_world[i][:3, :3], T_world[i][:3, 3], T_world[j][:3, 3]
        # p_j - p_i - R_i dp = v_i dt + g dt^2 / 2, rows weighted by 1 / dt (position over time: a velocity)
        a = np.zeros((3, n_unk))
        a[:, 3 * col[i]:3 * col[i] + 3] = I3
        a[:, -3:] = 0.5 * dt * I3
        rows.append(a)
        rhs.append((pj - pi - Ri @ np.asarray(dp, float)) / dt)
        scale_p.append(dt)
        # v_j - v_i - g dt = R_i dv
        a = np.zeros((3, n_unk))
        a[:, 3 * col[j]:3 * col[j] + 3] = I3
        a[:, 3 * col[i]:3 * col[i] + 3] -= I3
        a[:, -3:] = -dt * I3
        rows.append(a)
        rhs.append(Ri @ np.asarray(dv, float))
    A, y = np.vstack(rows), np.concatenate(rhs)
    x, *_ = np.linalg.lstsq(A, y, rcond=None)
    r = (A @ x - y).reshape(-1, 2, 3)
    dts = np.asarray(scale_p)
    v = np.full((K, 3), np.nan)
    for k, n in col.items():
        v[k] = x[3 * n:3 * n + 3]
    return GravityFit(x[-3:].copy(), v, len(increments),
                      float(np.sqrt(np.mean(np.sum((r[:, 0] * dts[:, None]) ** 2, axis=1)))),
                      float(np.sqrt(np.mean(np.sum(r[:, 1] ** 2, axis=1)))))


STILL_WINDOW_S = 1.0  # IMU averaged over this long where the rig rests during the frames
MAX_STILL_TURN_DEG = 0.5  # the path over such a stretch: it turns no more than this ...
MAX_STILL_SHIFT_M = 0.01  # ... and moves no more than this
MAX_STILL_ACCEL_DEV_M_S2 = 0.6  # the mean specific force there: 1 g within this


def gravity_from_still_frames(imu: ImuSamples, t_ns: np.ndarray, T_world_body: np.ndarray,
                              tracked: np.ndarray | None = None, window_s: float = STILL_WINDOW_S) -> np.ndarray | None:
    """Gravity (m/s^2, pointing down) in the world of the path ``T_world_body`` (body poses at the
    frame times ``t_ns``), from the first stretch of ``window_s`` during the frames where the path
    rests (it turns less than :data:`MAX_STILL_TURN_DEG` and moves less than :data:`MAX_STILL_SHIFT_M`):
    the IMU's mean specific force there, taken into the world by the body's rotation at the
    stretch's middle.  The path decides, not the IMU's own spread: a rig that rests may vibrate
    (EuRoC's drone sits on the ground with its rotors turning: gyro spread up to 0.08 rad/s and 2
    m/s^2 on the accelerometer, which averages out), and a box put down to start a scan rests too.
    The mean must be 1 g within 0.6 m/s^2 (at least 50 samples).  The accelerometer bias tilts it
    by ``|b_a| / 9.8`` rad.  ``tracked``: which frames' poses were measured (a predicted pose says
    nothing about rest); a stretch needs every frame in it tracked and finite.  None when the rig
    never rests for that long.  Stretches start every half window."""
    t_ns = np.asarray(t_ns, np.int64)
    T = np.asarray(T_world_body, float)
    good = np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)
    if tracked is not None:
        good &= np.asarray(tracked, bool)
    w = int(window_s * 1e9)
    for t0 in range(int(t_ns[0]), int(t_ns[-1]) - w + 1, max(w // 2, 1)):
        frames = np.flatnonzero((t_ns >= t0) & (t_ns <= t0 + w))
        if len(frames) < 2 or not good[frames].all():
            continue
        R0, p0 = T[frames[0], :3, :3], T[frames[0], :3, 3]
        turn = max(np.degrees(np.linalg.norm(so3_log(R0.T @ T[i, :3, :3]))) for i in frames)
        shift = float(np.max(np.linalg.norm(T[frames, :3, 3] - p0, axis=1)))
        if turn > MAX_STILL_TURN_DEG or shift > MAX_STILL_SHIFT_M:
            continue
        blk = imu.between(t0, t0 + w)
        f = blk.accel_m_s2.mean(axis=0) if len(blk) >= 50 else None
        if f is not None and abs(np.linalg.norm(f) - GRAVITY_M_S2) <= MAX_STILL_ACCEL_DEV_M_S2:
            return -(T[frames[len(frames) // 2], :3, :3] @ f)
    return None


def preintegrate(imu: ImuSamples, t0: int, t1: int, gyro_bias_rad_s: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The gravity-free increments ``(dp, dv)`` over ``[t0, t1]`` (ns) in the body frame at ``t0``: the
    accelerometer integrated twice through the gyro's rotation at ``gyro_bias_rad_s`` (accelerometer
    bias zero), piecewise-linear samples; None when the samples do not cover the interval."""
    blk = imu.between(t0 - 50_000_000, t1 + 50_000_000)
    if len(blk) < 2 or blk.t_ns[0] > t0 + 5_000_000 or blk.t_ns[-1] < t1 - 5_000_000:
        return None
    t = blk.t_ns.astype(np.int64)
    wm, dt = midpoint_rates(t, blk.gyro_rad_s - np.asarray(gyro_bias_rad_s, float), t0, t1)
    am, _ = midpoint_rates(t, blk.accel_m_s2, t0, t1)
    R, dp, dv = np.eye(3), np.zeros(3), np.zeros(3)
    for w, a, d in zip(wm, am, dt):
        step = so3_exp(w * d)
        Ra = R @ (so3_exp(0.5 * w * d) @ a)  # the specific force at the step's middle rotation
        dp = dp + dv * d + 0.5 * Ra * d * d
        dv = dv + Ra * d
        R = R @ step
    return dp, dv


START_MIN_SPAN_S = 1.0  # the path measured before the start is solved: at least this long ...
START_MIN_INTERVALS = 4  # ... in at least this many intervals
START_INTERVAL_S = 0.2  # poses closer than this to the previous one used are skipped
MAX_START_GRAVITY_DEV_M_S2 = 0.4  # the solved gravity: 1 g within this
MAX_START_RMS_M = 0.0015  # the increments' position residual per interval at the solution
MAX_START_BIAS_SIGMA_RAD_S = 0.005  # the gyro bias fit's formal standard deviation


@dataclass(frozen=True)
class StartFit:
    """A start in motion, solved from the path: the gyro bias and gravity (in the path's world)."""

    gyro: GyroBiasFit
    gravity: GravityFit

    @property
    def gravity_dev_m_s2(self) -> float:
        return abs(float(np.linalg.norm(self.gravity.gravity_world)) - GRAVITY_M_S2)


def start_from_path(imu: ImuSamples, t_ns: np.ndarray, T_world_body: np.ndarray) -> StartFit | None:
    """Gyro bias, then gravity (increments preintegrated with that bias), from body poses ``T_world_body``
    ((K, 4, 4), metric) at times ``t_ns``: poses at least :data:`START_INTERVAL_S` apart are chained.
    None when the path is too short (:data:`START_MIN_SPAN_S`, :data:`START_MIN_INTERVALS`) or a fit
    does not pass its checks (gravity's norm, the position residual, the bias's spread): the caller
    tries again with a longer path."""
    t_ns = np.asarray(t_ns, np.int64)
    keep = [0]
    for k in range(1, len(t_ns)):
        if (t_ns[k] - t_ns[keep[-1]]) * 1e-9 >= START_INTERVAL_S:
            keep.append(k)
    if len(keep) < START_MIN_INTERVALS + 1 or (t_ns[keep[-1]] - t_ns[keep[0]]) * 1e-9 < START_MIN_SPAN_S:
        return None
    t_kf, T = t_ns[keep], np.asarray(T_world_body, float)[keep]
    gyro = gyro_bias_from_path(imu, t_kf, T[:, :3, :3])
    if gyro is None or gyro.sigma_rad_s > MAX_START_BIAS_SIGMA_RAD_S:
        return None
    increments = []
    for i in range(len(t_kf) - 1):
        inc = preintegrate(imu, int(t_kf[i]), int(t_kf[i + 1]), gyro.bias_rad_s)
        if inc is not None:
            increments.append((i, i + 1, *inc))
    gravity = gravity_from_path(t_kf, T, increments)
    if gravity is None:
        return None
    fit = StartFit(gyro, gravity)
    if fit.gravity_dev_m_s2 > MAX_START_GRAVITY_DEV_M_S2 or gravity.rms_m > MAX_START_RMS_M:
        return None
    return fit
