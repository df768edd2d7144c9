"""The IMU's start-up unknowns from a camera path (no still start): gyro bias, gravity, velocities."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.core.frames import ImuSamples
from stereopath.device.core.geometry import so3_exp
from stereopath.device.estimation.inertial_init import gravity_from_path, gyro_bias_from_path


def _omega(t: np.ndarray) -> np.ndarray:
    """A hand-held turn: up to ~70 deg/s about every axis (body frame, rad/s)."""
    return np.column_stack([0.8 * np.sin(1.3 * t), 0.5 * np.cos(0.7 * t), 1.2 * np.sin(0.4 * t + 1.0)])


def _turning(bias: np.ndarray, seconds: float = 6.0, rate_hz: float = 200.0, kf_s: float = 0.5):
    """Gyro samples (with ``bias``) of the turn, and the true body rotations at the keyframe times."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    imu = ImuSamples((t * 1e9).astype(np.int64), _omega(t) + bias, np.tile([0.0, 0.0, 9.81], (len(t), 1)))
    t_kf = np.arange(0.2, seconds - 0.2, kf_s)
    fine = np.arange(0.0, seconds, 1e-4)  # the truth: 10 kHz midpoint integration
    w = _omega(fine[:-1] + 5e-5)
    R, out, k = np.eye(3), [], 0
    for i, tt in enumerate(fine[:-1]):
        if k < len(t_kf) and tt >= t_kf[k] - 1e-9:
            out.append(R.copy())
            k += 1
        R = R @ so3_exp(w[i] * 1e-4)
    return imu, (t_kf * 1e9).astype(np.int64), np.array(out)


def test_gyro_bias_from_a_turning_path():
    bias = np.array([0.004, -0.021, 0.078])  # EuRoC V1_01's size
    imu, t_kf, R = _turning(bias)
    fit = gyro_bias_from_path(imu, t_kf, R)
    assert np.allclose(fit.bias_rad_s, bias, atol=1e-4)
    # one Gauss-Newton step from zero lands there with the model of A (2e-5 rad/s; with A = T I, 1.6e-3)
    assert np.allclose(gyro_bias_from_path(imu, t_kf, R, iterations=1).bias_rad_s, bias, atol=1e-4)
    assert fit.intervals == len(t_kf) - 1 and fit.rms_rad < 1e-3 and fit.sigma_rad_s < 1e-4
    # a bias error taken as the still camera's (log = T d) would be off by more on this turn
    A_still = np.vstack([np.eye(3) * 0.5] * fit.intervals)
    from stereopath.device.estimation.inertial_init import _stack

    _, e = _stack([(s, Rv) for s, Rv in _spans(imu, t_kf, R)], np.zeros(3))
    naive = np.linalg.lstsq(A_still, e, rcond=None)[0]
    assert np.linalg.norm(naive - bias) > 10 * np.linalg.norm(fit.bias_rad_s - bias)
    # one interval is not enough; neither are samples that do not cover the keyframes
    assert gyro_bias_from_path(imu, t_kf[:2], R[:2]) is None
    late = ImuSamples(imu.t_ns + 10**10, imu.gyro_rad_s, imu.accel_m_s2)
    assert gyro_bias_from_path(late, t_kf, R) is None


def _spans(imu, t_kf, R):
    from stereopath.device.estimation.inertial_init import _interval

    return [(_interval(imu, int(t_kf[i]), int(t_kf[i + 1])), R[i].T @ R[i + 1]) for i in range(len(t_kf) - 1)]


def _moving_path(R_world: np.ndarray, n: int = 12, dt: float = 0.4):
    """Keyframe poses of a swaying, turning walk in a world frame rotated by ``R_world`` (gravity is
    ``R_world @ (0, 0, -9.81)`` there), with the exact gravity-free increments of each interval."""
    t = np.arange(n) * dt
    p = np.column_stack([0.3 * np.sin(0.9 * t), 0.5 * t, 0.1 * np.cos(1.7 * t)]) @ R_world.T
    v = np.column_stack([0.27 * np.cos(0.9 * t), 0.5 + 0 * t, -0.17 * np.sin(1.7 * t)]) @ R_world.T
    T = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        T[k, :3, :3] = R_world @ so3_exp(np.array([0.1 * k, 0.3 * np.sin(k), 0.05 * k]))
        T[k, :3, 3] = p[k]
    g = R_world @ np.array([0.0, 0.0, -9.81])
    # the polynomial the increments must satisfy: dp, dv such that the model holds with true v and g
    inc = []
    for i in range(n - 1):
        Ri = T[i, :3, :3]
        inc.append((i, i + 1, Ri.T @ (p[i + 1] - p[i] - v[i] * dt - 0.5 * g * dt**2), Ri.T @ (v[i + 1] - v[i] - g * dt)))
    return (t * 1e9).astype(np.int64), T, inc, g, v


def test_gravity_and_velocities_from_a_path_in_any_world_frame():
    rng = np.random.default_rng(4)
    R_world = so3_exp(np.array([0.7, -0.4, 2.0]))  # e.g. the first camera's frame, not z up
    t_kf, T, inc, g, v = _moving_path(R_world)
    fit = gravity_from_path(t_kf, T, inc)
    assert np.allclose(fit.gravity_world, g, atol=1e-9) and np.allclose(fit.velocities, v, atol=1e-9)
    assert fit.intervals == len(inc) and fit.rms_m < 1e-9 and fit.rms_m_s < 1e-9
    # noisy increments (1 cm/s, 2 mm per interval): gravity within 0.3 deg
    noisy = [(i, j, dp + rng.normal(0, 0.002, 3), dv + rng.normal(0, 0.01, 3)) for i, j, dp, dv in inc]
    fit = gravity_from_path(t_kf, T, noisy)
    assert np.degrees(np.arccos(fit.gravity_world @ g / np.linalg.norm(fit.gravity_world) / 9.81)) < 0.3
    assert 0.003 < fit.rms_m_s < 0.03 and 0.0005 < fit.rms_m < 0.005
    # an interval missing (no IMU samples there): the chain on both sides still fixes gravity; a keyframe
    # no interval touches has no velocity
    gap = inc[:5] + inc[6:]
    fit = gravity_from_path(t_kf, T, gap)
    assert np.allclose(fit.gravity_world, g, atol=1e-6) and np.isfinite(fit.velocities).all()
    fit = gravity_from_path(t_kf, T, inc[:4])
    assert np.isnan(fit.velocities[6:]).all() and np.allclose(fit.gravity_world, g, atol=1e-6)
    assert gravity_from_path(t_kf, T, inc[:1]) is None


def test_gravity_of_a_still_rig_is_its_specific_force():
    R = so3_exp(np.array([0.2, -1.1, 0.4]))
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, :3, :3] = R
    f_body = R.T @ np.array([0.0, 0.0, 9.81])  # what the accelerometer reads at rest
    dt = 0.5
    inc = [(i, i + 1, 0.5 * f_body * dt**2, f_body * dt) for i in range(4)]
    fit = gravity_from_path((np.arange(5) * dt * 1e9).astype(np.int64), T, inc)
    assert fit.gravity_world == pytest.approx([0.0, 0.0, -9.81]) and np.allclose(fit.velocities, 0.0, atol=1e-12)
