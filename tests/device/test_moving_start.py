"""A start in motion on board: gyro bias and gravity from the first tracked poses, the world levelled once."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.core.frames import ImuSamples
from stereopath.device.core.geometry import make_pose, so3_exp, so3_log
from stereopath.device.errors import ConfigError
from stereopath.device.estimation import inertial_init
from stereopath.device.estimation.inertial_init import preintegrate, start_from_path

G_NORM = 9.80665


def _motion(t: float) -> tuple[np.ndarray, np.ndarray]:
    """A hand-held sway: position (m) and rotation of the body in a level world at time ``t`` (s)."""
    p = np.array([0.3 * np.sin(0.9 * t), 0.4 * t + 0.05 * np.sin(3 * t), 0.1 * np.cos(1.7 * t)])
    return p, so3_exp(np.array([0.5 * np.sin(0.8 * t), 0.3 * t, 0.4 * np.cos(1.1 * t)]))


def _moving_start(R_world: np.ndarray, bias: np.ndarray, seconds: float = 3.0, rate_hz: float = 200.0):
    """IMU samples (gyro with ``bias``) of the sway from its first instant, and a function giving the true
    body pose in a world rotated by ``R_world`` (gravity ``R_world @ (0, 0, -g)`` there)."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    h = 1e-4
    gyro, acc = [], []
    for tt in t:
        (p0, R0), (p1, R1), (p2, R2) = _motion(tt - h), _motion(tt), _motion(tt + h)
        gyro.append(so3_log(R0.T @ R2) / (2 * h))
        acc.append(R1.T @ ((p2 - 2 * p1 + p0) / h**2 + np.array([0.0, 0.0, G_NORM])))
    imu = ImuSamples((t * 1e9).astype(np.int64), np.array(gyro) + bias, np.array(acc))

    def pose(tt: float) -> np.ndarray:
        p, R = _motion(tt)
        return make_pose(R_world @ R, R_world @ p)

    return imu, pose


def test_start_from_a_moving_path_gives_bias_and_gravity_in_the_path_world():
    R_world = so3_exp(np.array([0.7, -0.4, 2.0]))  # the first camera's world: not z up
    bias = np.array([0.004, -0.02, 0.01])
    imu, pose = _moving_start(R_world, bias)
    t_kf = np.arange(0.1, 1.6, 0.05)  # every frame at 20 Hz: thinned to 0.2 s intervals
    fit = start_from_path(imu, (t_kf * 1e9).astype(np.int64), np.array([pose(t) for t in t_kf]))
    g = R_world @ np.array([0.0, 0.0, -G_NORM])
    assert np.allclose(fit.gyro.bias_rad_s, bias, atol=2e-5)
    assert np.degrees(np.arccos(fit.gravity.gravity_world @ g / np.linalg.norm(fit.gravity.gravity_world) / G_NORM)) < 0.05
    assert fit.gravity_dev_m_s2 < 0.02 and fit.gravity.rms_m < 1e-4
    assert fit.gravity.intervals == 7  # 0.1 .. 1.5 s every 0.2 s
    # too short a path: tried again later
    short = np.arange(0.1, 0.8, 0.05)
    assert start_from_path(imu, (short * 1e9).astype(np.int64), np.array([pose(t) for t in short])) is None
    # a path that the IMU does not fit (its scale 50 % off, as with a wrong baseline) is refused
    wrong = np.array([pose(t) for t in t_kf])
    wrong[:, :3, 3] *= 1.5
    assert start_from_path(imu, (t_kf * 1e9).astype(np.int64), wrong) is None


def test_preintegrated_increments_match_the_motion():
    bias = np.array([0.01, 0.0, -0.02])
    imu, pose = _moving_start(np.eye(3), bias)
    t0, t1 = 0.5, 0.9
    dp, dv = preintegrate(imu, int(t0 * 1e9), int(t1 * 1e9), bias)
    T0, T1, h = pose(t0), pose(t1), 1e-4
    v = [(pose(t + h)[:3, 3] - pose(t - h)[:3, 3]) / (2 * h) for t in (t0, t1)]
    g = np.array([0.0, 0.0, -G_NORM])
    dt = t1 - t0
    R0 = T0[:3, :3]
    assert np.allclose(R0 @ dp, T1[:3, 3] - T0[:3, 3] - v[0] * dt - 0.5 * g * dt**2, atol=2e-4)
    assert np.allclose(R0 @ dv, v[1] - v[0] - g * dt, atol=2e-3)
    assert preintegrate(imu, int(5e9), int(6e9), bias) is None  # no samples there


def _handheld(frames: int):
    from stereopath.device.formats.source import open_source
    from stereopath.device.sim.handheld import motion_file

    try:
        motion_file()
    except ConfigError:
        pytest.skip("the recorded flight (shared data trajectories/V101_gt.txt) is not available")
    return open_source("sim:0", frames=frames, trajectory="handheld")


@pytest.mark.slow
def test_a_start_in_motion_levels_the_world_once(monkeypatch):
    """The hand-held stand-in, switched on in motion: the gyro bias and gravity are solved from the first
    second's path, the live state moves once, and every pose given, before and after, is in a world
    whose z is up."""
    from stereopath.device.estimation.base import run_estimator
    from stereopath.device.estimation.live_state import LiveState
    from stereopath.device.estimation.moving_start import MovingStart
    from stereopath.device.estimation.registry import make_estimator
    from stereopath.device.estimation.stereo_vo import StereoEstimator
    from stereopath.host.evaluation.evaluate import evaluate

    seq = _handheld(40)
    moves, solved, taken = [], [], []
    apply, poll, take = LiveState.apply, MovingStart.poll, StereoEstimator._take_moving_start
    monkeypatch.setattr(LiveState, "apply", lambda self, G: (moves.append(np.array(G)), apply(self, G))[1])
    monkeypatch.setattr(MovingStart, "poll", lambda self: (s := poll(self), s and solved.append(s))[0])

    def take_and_look(self):  # the gyro bias in use right after the start is taken
        take(self)
        if self._start is None and not taken:
            taken.append((self._gyro.bias.copy(), self._bias.bias.copy()))

    monkeypatch.setattr(StereoEstimator, "_take_moving_start", take_and_look)
    est = make_estimator("stereo", seq.rig)
    run = run_estimator(est, iter(list(seq.frames())), seq.imu)
    assert run.world_frame == "gravity_aligned"
    seq_solved, G = est.world_rebase
    # solved on the first second's path; taken at the first frame after the worker finished (which frame
    # depends on the worker's pace beside the frame loop)
    assert len(solved) == 1 and 15 <= solved[0].seq <= 30 and solved[0].seq <= seq_solved < 40
    assert est.stats()["start_solved_frame"] == seq_solved
    assert sum(np.array_equal(M, G) for M in moves) == 1  # one leveling move among the keyframe corrections
    assert np.allclose(G[:3, 3], 0.0) and 2.0 < np.degrees(np.linalg.norm(so3_log(G[:3, :3])))
    true_bias = seq.imu_biases.gyro_rad_s[np.searchsorted(seq.imu.t_ns, seq.t_ns[seq_solved])]
    assert len(solved) == 1 and np.all(np.abs(solved[0].fit.gyro.bias_rad_s - true_bias) < 2e-4)  # 0.01 deg/s
    assert all(np.array_equal(b, solved[0].fit.gyro.bias_rad_s) for b in taken[0])  # taken as solved
    assert np.all(np.abs(est.gyro_bias_rad_s - true_bias) < 3e-4)
    # gravity: the truth's world is z up; every pose's z, before the move and after it, within 1 deg
    R_gt, R_est = seq.groundtruth.T_world_cam[:, :3, :3], run.trajectory.T_world_cam[:, :3, :3]
    up = np.einsum("nij,nkj,k->ni", R_gt, R_est, np.array([0.0, 0.0, 1.0]))  # the estimate's z in the truth's world
    assert np.degrees(np.arccos(np.clip(up[:, 2], -1, 1))).max() < 1.0
    assert evaluate(seq.groundtruth, run.trajectory)["ate_rmse_m"] < 0.003  # one path across the move


@pytest.mark.slow
def test_a_still_start_never_takes_the_moving_path(monkeypatch):
    """The sim's default scan rests before its first frame: gravity and bias by averaging, as before."""
    from stereopath.device.estimation import stereo_vo
    from stereopath.device.estimation.base import run_estimator
    from stereopath.device.estimation.registry import make_estimator
    from stereopath.device.formats.source import open_source

    def refuse(*a, **k):
        raise AssertionError("a still start solved from the path")

    monkeypatch.setattr(stereo_vo, "MovingStart", refuse)
    seq = open_source("sim:1", frames=20)
    est = make_estimator("stereo", seq.rig)
    run = run_estimator(est, iter(list(seq.frames())), seq.imu)
    assert run.world_frame == "gravity_aligned" and est.world_rebase is None
    assert est.stats()["start_solves"] == 0 and est.stats()["start_solved_frame"] == -1


def test_the_solve_waits_for_a_long_enough_path_and_runs_once():
    from stereopath.device.estimation.keyframe_jobs import Ready
    from stereopath.device.estimation.moving_start import MovingStart

    class InLine:
        calls = 0

        def run_aside(self, fn):
            InLine.calls += 1
            return Ready(fn())

    bias = np.array([0.003, 0.001, -0.002])
    imu, pose = _moving_start(np.eye(3), bias)
    T_body_cam = make_pose(so3_exp(np.array([0.1, 0.2, 0.3])), np.array([0.02, 0.0, 0.01]))
    start, worker = MovingStart(T_body_cam), InLine()
    t_all = np.arange(0.05, 2.5, 0.05)
    solved = None
    for k, t in enumerate(t_all):
        t_ns = int(t * 1e9)
        start.add_imu(imu.between(int((t - 0.05) * 1e9), t_ns))
        if start.add_pose(t_ns, pose(t) @ T_body_cam):  # the camera's pose
            start.submit(worker, k)
        solved = solved or start.poll()
        if solved is not None:
            break
    assert solved is not None and start.solved and 1.0 <= t <= 1.5
    assert InLine.calls == start.attempts and np.allclose(solved.fit.gyro.bias_rad_s, bias, atol=1e-4)
    assert not start.submit(worker, k + 1) and start.poll() is None  # once
    L = solved.leveling(np.eye(3), T_body_cam[:3, :3])
    g_new = L[:3, :3] @ solved.gravity_world
    assert np.degrees(np.arccos(-g_new[2] / np.linalg.norm(g_new))) < 0.1
    assert inertial_init.START_MIN_SPAN_S <= t


def test_a_path_the_imu_never_fits_is_given_up(monkeypatch):
    from stereopath.device.estimation import moving_start
    from stereopath.device.estimation.keyframe_jobs import Ready

    class InLine:
        def run_aside(self, fn):
            return Ready(fn())

    monkeypatch.setattr(moving_start, "MAX_ATTEMPTS", 3)
    imu, pose = _moving_start(np.eye(3), np.zeros(3))
    start, worker = moving_start.MovingStart(np.eye(4)), InLine()
    rng = np.random.default_rng(1)
    for k, t in enumerate(np.arange(0.05, 2.9, 0.05)):
        t_ns = int(t * 1e9)
        start.add_imu(imu.between(int((t - 0.05) * 1e9), t_ns))
        T = pose(t)
        T[:3, 3] += rng.normal(0.0, 0.01, 3)  # a path 1 cm off at every pose
        if start.add_pose(t_ns, T):
            start.submit(worker, k)
        assert start.poll() is None
    assert start.attempts == 3 and not start.open and not start.solved
    assert not start.add_pose(int(3e9), pose(3.0)) and not start.submit(worker, 99)
