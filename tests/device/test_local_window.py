"""The local window: its solve on synthetic keyframes, its gauge, its gyro residuals, its records and
its path through the keyframe worker."""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np
import pytest

from stereopath.device.core.geometry import invert_pose, make_pose, so3_exp, so3_log
from stereopath.device.core.stereo_config import StereoConfig, WindowConfig
from stereopath.device.errors import ConfigError
from stereopath.device.estimation.disparity_offset import RectifiedCamera
from stereopath.device.estimation.live_state import LiveState, StereoStats
from stereopath.device.estimation.local_window import WindowJob, WindowKeyframes, solve_window

CAM = RectifiedCamera(400.0, 320.0, 240.0, 0.1)
R0 = so3_exp(np.array([0.01, -0.02, 0.005]))  # a rectifying rotation that is not the identity


def _scene(K: int = 6, seed: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
    """True camera-1 poses (a sideways sweep that turns) and world points in front of them."""
    rng = np.random.default_rng(seed)
    poses = [make_pose(so3_exp(np.array([0.0, 0.03 * k, 0.01 * k])), np.array([0.08 * k, 0.01 * k, 0.0]))
             for k in range(K)]
    X = np.column_stack([rng.uniform(-1.0, 1.5, 400), rng.uniform(-0.8, 0.8, 400), rng.uniform(1.5, 4.0, 400)])
    return poses, X


def _observe(T_world_cam: np.ndarray, X: np.ndarray, noise_px: float = 0.0,
             rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Point ids seen in the rectified left image and their (u, v, disparity) rows."""
    T_cw = invert_pose(T_world_cam)
    Xr = (X @ T_cw[:3, :3].T + T_cw[:3, 3]) @ R0.T
    z = Xr[:, 2]
    u, v = CAM.f * Xr[:, 0] / z + CAM.cx, CAM.f * Xr[:, 1] / z + CAM.cy
    ok = (z > 0.2) & (u > 0) & (u < 640) & (v > 0) & (v < 480)
    obs = np.column_stack([u, v, CAM.fb / z])[ok]
    if noise_px and rng is not None:
        obs = obs + rng.normal(0.0, noise_px, obs.shape)
    return np.flatnonzero(ok), obs


def _perturbed(poses: list[np.ndarray], rng: np.random.Generator, rot: float = 0.01,
               trans: float = 0.02) -> list[np.ndarray]:
    out = [poses[0].copy()]
    for T in poses[1:]:
        out.append(make_pose(so3_exp(rng.normal(0, rot, 3)) @ T[:3, :3], T[:3, 3] + rng.normal(0, trans, 3)))
    return out


def _errors(a: list[np.ndarray], b: list[np.ndarray]) -> tuple[float, float]:
    t = max(float(np.linalg.norm(x[:3, 3] - y[:3, 3])) for x, y in zip(a, b))
    r = max(float(np.linalg.norm(so3_log(x[:3, :3].T @ y[:3, :3]))) for x, y in zip(a, b))
    return t, r


def _job(poses: list[np.ndarray], views: list[tuple[np.ndarray, np.ndarray]],
         gyro: list[tuple[np.ndarray, float] | None] | None = None, offset_px: float = 0.0) -> WindowJob:
    return WindowJob(len(poses) - 1, poses, list(range(len(poses))), views, gyro or [None] * len(poses), offset_px,
                     np.eye(4))


def test_window_removes_pose_noise_and_holds_the_oldest_keyframe() -> None:
    rng = np.random.default_rng(1)
    truth, X = _scene()
    views = [_observe(T, X) for T in truth]
    start = _perturbed(truth, rng)
    res = solve_window(_job(start, views), CAM, R0, WindowConfig(iterations=10, fixed=1))
    assert res is not None and res.n_points > 100
    t0, r0 = _errors(start, truth)
    t1, r1 = _errors(res.T_after, truth)
    assert t0 > 0.01 and r0 > 0.005
    assert t1 < 1e-5 and r1 < 1e-6  # exact observations: the true poses
    np.testing.assert_array_equal(res.T_after[0], start[0])  # the gauge: the held keyframe does not move
    assert res.rms_px < 1e-3 and res.cpu_ms > 0.0


def test_two_held_keyframes_stay_and_noisy_observations_still_help() -> None:
    rng = np.random.default_rng(2)
    truth, X = _scene(K=7)
    views = [_observe(T, X, 0.3, rng) for T in truth]
    start = _perturbed(truth, rng)
    start[1] = truth[1].copy()
    res = solve_window(_job(start, views), CAM, R0, WindowConfig(keyframes=7, fixed=2, iterations=10))
    assert res is not None
    np.testing.assert_array_equal(res.T_after[1], start[1])
    t0, r0 = _errors(start, truth)
    t1, r1 = _errors(res.T_after, truth)
    assert t1 < 0.1 * t0 and r1 < 0.1 * r0


def test_disparity_offset_is_removed_from_the_observations() -> None:
    truth, X = _scene()
    views = [(ids, obs + np.array([0.0, 0.0, 0.4])) for ids, obs in (_observe(T, X) for T in truth)]
    rng = np.random.default_rng(3)
    start = _perturbed(truth, rng)
    with_offset = solve_window(_job(start, views, offset_px=0.4), CAM, R0, WindowConfig(iterations=10, fixed=1))
    ignored = solve_window(_job(start, views, offset_px=0.0), CAM, R0, WindowConfig(iterations=10, fixed=1))
    assert _errors(with_offset.T_after, truth)[0] < 1e-5
    assert _errors(ignored.T_after, truth)[0] > 3e-4  # an offset left in scales the path


def test_gyro_rotations_pull_the_rotations_where_vision_is_weak() -> None:
    """Few, noisy points: the gyro's exact relative rotations make the window's rotations better."""
    rng = np.random.default_rng(4)
    truth, X = _scene()
    X = X[:40]
    views = [_observe(T, X, 1.0, rng) for T in truth]
    start = _perturbed(truth, rng)
    gyro: list[tuple[np.ndarray, float] | None] = [None] + [
        (truth[k - 1][:3, :3].T @ truth[k][:3, :3], 1e-4) for k in range(1, len(truth))]
    cfg = WindowConfig(iterations=10, min_points=10, fixed=1)
    vision = solve_window(_job(start, views), CAM, R0, cfg)
    both = solve_window(_job(start, views, gyro), CAM, R0, cfg)
    r_vision, r_both = _errors(vision.T_after, truth)[1], _errors(both.T_after, truth)[1]
    assert r_both < 0.5 * r_vision


def test_too_few_shared_points_is_no_solve() -> None:
    truth, X = _scene(K=3)
    views = [(ids + 1000 * k, obs) for k, (ids, obs) in enumerate(_observe(T, X) for T in truth)]
    assert solve_window(_job(truth, views), CAM, R0, WindowConfig(fixed=1)) is None


def test_records_slide_follow_the_live_state_and_take_the_refined_poses() -> None:
    truth, X = _scene(K=5)
    win = WindowKeyframes(WindowConfig(keyframes=3, fixed=1, gyro=True))
    C = np.eye(4)
    R_body_cam = so3_exp(np.array([0.2, 0.1, -0.3]))
    for k, T in enumerate(truth):
        if k:
            R_cam = truth[k - 1][:3, :3].T @ T[:3, :3]
            win.gyro_step((R_body_cam @ R_cam @ R_body_cam.T, 0.05), R_body_cam)
        ids, obs = _observe(T, X)
        win.add(k, T, ids, obs, C)
    assert [r.seq for r in win.records] == [2, 3, 4]
    job = win.job(C, 0.0, None)
    np.testing.assert_allclose(job.gyro[1][0], truth[2][:3, :3].T @ truth[3][:3, :3], atol=1e-12)
    assert job.gyro[0] is None and job.gyro[1][1] > 0
    # a correction G of the live state moves the records with it
    G = make_pose(so3_exp(np.array([0.0, 0.0, 0.01])), np.array([0.01, 0.0, 0.0]))
    st = LiveState(T_world_cam=truth[-1].copy())
    st.apply(G)
    moved = win.job(st.C, 0.0, None)
    np.testing.assert_allclose(moved.poses[0], G @ truth[2], atol=1e-12)
    # a window's own correction: the refined poses are kept where it put them
    res = solve_window(moved, CAM, R0, WindowConfig(iterations=3, fixed=1))
    counts = StereoStats()
    G2 = make_pose(np.eye(3), np.array([0.0, 0.002, 0.0]))
    win.joined(res, G2, np.eye(4), st, counts)
    assert counts.window_corrections == 1 and counts.window_cpu_us > 0
    again = win.job(st.C, 0.0, None)
    for a, b in zip(again.poses, res.T_after):
        np.testing.assert_allclose(a, b, atol=1e-9)


def test_a_restarted_map_cuts_the_window() -> None:
    truth, X = _scene(K=4)
    win = WindowKeyframes(WindowConfig(keyframes=6, fixed=1))
    for k, T in enumerate(truth):
        ids, obs = _observe(T, X)
        win.add(k, T, ids + (10000 if k >= 2 else 0), obs, np.eye(4))
    assert [r.seq for r in win.linked()] == [2, 3]


def test_window_config_is_checked() -> None:
    with pytest.raises(ConfigError, match="window.fixed"):
        WindowConfig(keyframes=3, fixed=3)
    with pytest.raises(ConfigError, match="window.keyframes"):
        WindowConfig(keyframes=1, fixed=1)
    with pytest.raises(ConfigError, match="window.fixed"):
        WindowConfig(keyframes=3)  # three held need a fourth keyframe


def test_the_window_needs_no_gtsam() -> None:
    """The device's window is NumPy: the estimator with the window on imports and solves in a process
    where GTSAM cannot be imported."""
    import subprocess
    from pathlib import Path

    code = """
import sys
sys.modules["gtsam"] = None  # import gtsam raises ImportError
sys.path.insert(0, sys.argv[1])
import numpy as np
from test_local_window import CAM, R0, _errors, _job, _observe, _perturbed, _scene
from stereopath.device.core.stereo_config import StereoConfig, WindowConfig
from stereopath.device.estimation.local_window import solve_window
from stereopath.device.estimation.stereo_vo import StereoEstimator
truth, X = _scene()
views = [_observe(T, X) for T in truth]
start = _perturbed(truth, np.random.default_rng(5))
res = solve_window(_job(start, views), CAM, R0, WindowConfig(iterations=10, fixed=1))
assert _errors(res.T_after, truth)[0] < 1e-5
assert "gtsam" not in {m for m in sys.modules if sys.modules[m] is not None}
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code, str(Path(__file__).parent)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().endswith("ok")


@pytest.mark.parametrize("background", [False, True])
def test_estimator_with_window_corrects_through_poll(background: bool) -> None:
    """The estimator on the simulated scan's first frames with the window on: solves are submitted and
    their corrections applied on the frame loop (never from the worker thread)."""
    from stereopath.device.core.config import from_mapping
    from stereopath.device.estimation.base import run_estimator
    from stereopath.device.estimation.stereo_vo import StereoEstimator
    from stereopath.device.formats.source import open_source

    import threading

    seq = open_source("sim:1", frames=80)
    cfg = from_mapping(StereoConfig, {"window": {"enabled": True}, "keyframes": {"background": background}})
    est = StereoEstimator(seq.rig, cfg)
    applied_on: list[threading.Thread] = []
    real_apply = LiveState.apply

    def recording_apply(self: LiveState, G: np.ndarray) -> None:
        applied_on.append(threading.current_thread())
        real_apply(self, G)

    LiveState.apply = recording_apply  # type: ignore[method-assign]
    try:
        run = run_estimator(est, seq.frames(), seq.imu)
    finally:
        LiveState.apply = real_apply  # type: ignore[method-assign]
        est.close()
    c = est.counts
    assert run.frames_tracked == 80
    assert applied_on and {t.ident for t in applied_on} == {threading.main_thread().ident}
    assert c.window_solves >= 2 and c.window_corrections >= 1 and c.window_cpu_us > 0


def test_the_map_prior_carries_what_left_the_window() -> None:
    """The held keyframe sees few of the window's points and the others see them noisily: the window
    alone drifts; the map's points (known from keyframes that left the window) as a prior hold it."""
    rng = np.random.default_rng(6)
    truth, X = _scene(K=4)
    views = [_observe(T, X, 0.5, rng) for T in truth]
    ids0, obs0 = views[0]
    views[0] = (ids0[:15], obs0[:15])
    start = _perturbed(truth, rng)
    points = (np.arange(len(X)), X.copy(), np.full(len(X), 9.0))
    job = WindowJob(3, start, [0, 1, 2, 3], views, [None] * 4, 0.0, np.eye(4), points)
    cfg = WindowConfig(keyframes=4, iterations=10, min_points=10, fixed=1)
    alone = solve_window(job, CAM, R0, cfg)
    prior = solve_window(job, CAM, R0, replace(cfg, map_prior_weight=1.0))
    assert alone.n_points == prior.n_points
    assert _errors(prior.T_after, truth)[0] < 0.5 * _errors(alone.T_after, truth)[0]


def test_a_non_finite_window_result_is_refused_not_raised() -> None:
    """A window whose solve diverged (non-finite poses) is refused on the frame loop: no correction, no
    exception into the estimator."""
    from stereopath.device.estimation.keyframe_jobs import KeyframeWorker
    from stereopath.device.estimation.local_window import WindowResult

    truth, _ = _scene(K=3)
    bad = [T.copy() for T in truth]
    bad[-1][0, 3] = np.nan
    res = WindowResult(2, [0, 1, 2], [T.copy() for T in truth], bad, 0.5, 100, 1.0)
    worker = KeyframeWorker.__new__(KeyframeWorker)
    worker.cfg = StereoConfig()
    corr = worker._window_correction(res, np.eye(4))
    assert corr.G is None
    ok = WindowResult(2, [0, 1, 2], [T.copy() for T in truth], [T.copy() for T in truth], 0.5, 100, 1.0)
    assert worker._window_correction(ok, np.eye(4)).G is not None


def test_a_window_shift_beyond_the_angle_at_its_points_depth_is_refused() -> None:
    """The newest keyframe's shift is gated as its rotation is: ``max_correction_deg`` (2 deg) at the
    median depth of its points (2 m: 0.07 m)."""
    from stereopath.device.estimation.keyframe_jobs import KeyframeWorker
    from stereopath.device.estimation.local_window import WindowResult

    truth, _ = _scene(K=3)
    worker = KeyframeWorker.__new__(KeyframeWorker)
    worker.cfg = StereoConfig()
    for shift, taken in ((0.05, True), (0.10, False)):
        after = [T.copy() for T in truth]
        after[-1][:3, 3] += np.array([0.0, shift, 0.0])
        res = WindowResult(2, [0, 1, 2], [T.copy() for T in truth], after, 0.5, 100, 1.0, depth_m=2.0)
        assert (worker._window_correction(res, np.eye(4)).G is not None) is taken, shift


def test_a_window_whose_steps_raise_the_cost_is_no_correction(monkeypatch) -> None:
    """Steps are kept only while they lower the robust cost: a solve that never does gives no result, one
    that overshoots later keeps its best state."""
    import stereopath.device.estimation.local_window as lw

    rng = np.random.default_rng(3)
    truth, X = _scene()
    views = [_observe(T, X) for T in truth]
    start = _perturbed(truth, rng)
    real = lw._gauss_newton_step
    calls = []

    def overshoot(*args, **kw):
        out = real(*args, **kw)
        calls.append(1)
        if out is None or len(calls) < first_bad:
            return out
        dg, dX, rms = out
        return dg + 0.3, dX, rms  # every pose thrown 0.3 m and 0.3 rad away

    first_bad = 1
    monkeypatch.setattr(lw, "_gauss_newton_step", overshoot)
    assert solve_window(_job(start, views), CAM, R0, WindowConfig(iterations=5, fixed=1)) is None
    calls.clear()
    first_bad = 3
    res = solve_window(_job(start, views), CAM, R0, WindowConfig(iterations=5, fixed=1))
    assert res is not None and len(calls) == 3
    assert _errors(res.T_after, truth)[0] < 1e-3  # the second step's state: converged, not the thrown one


def test_a_zero_disparity_weight_is_refused() -> None:
    """Without the disparity residual a point seen along its ray has no depth: the solve would be singular."""
    with pytest.raises(ConfigError, match="window.disparity_weight"):
        WindowConfig(disparity_weight=0.0)
    assert WindowConfig(disparity_weight=0.01).disparity_weight == 0.01
