"""The on-line disparity offset: two-keyframe bundle adjustment and its bounded fusion (synthetic, exact truth)."""

import numpy as np
import pytest

from types import SimpleNamespace

from stereopath.device.core.geometry import invert_pose, make_pose, so3_exp
from stereopath.device.estimation.disparity_offset import (
    KeyframeObservations,
    KeyframePair,
    OffsetFilter,
    PairEstimate,
    RectifiedCamera,
    SolveOptions,
    motion_with_offset,
    offset_correction_of_motion,
    offset_from_two_keyframes,
)
from stereopath.device.estimation.offset_window import offset_from_keyframes, offset_over_keyframes

F, CX, CY, B = 450.0, 320.0, 240.0, 0.05
CAM = RectifiedCamera(F, CX, CY, B)


def _pair(rng, d0, noise, t=(0.03, -0.02, 0.12), n=250):
    X = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-0.7, 0.7, n), np.ones(n)]) * rng.uniform(0.5, 4, n)[:, None]
    R = so3_exp(np.array([0.02, -0.05, 0.01]))
    XB = X @ R.T + np.asarray(t)

    def obs(P):
        return np.column_stack([F * P[:, 0] / P[:, 2] + CX, F * P[:, 1] / P[:, 2] + CY, F * B / P[:, 2] + d0])

    return obs(X) + rng.normal(0, noise, (n, 3)), obs(XB) + rng.normal(0, noise, (n, 3)), R, np.asarray(t)


def test_two_keyframes_recover_a_disparity_offset_from_a_poor_initial_motion():
    rng = np.random.default_rng(3)
    for d0 in (-0.3, 0.0, 0.25):
        A, Bo, R, t = _pair(rng, d0, 0.0)
        est = offset_from_two_keyframes(KeyframePair(A, Bo, np.eye(3), np.zeros(3)), CAM)
        assert est is not None and abs(est.d0 - d0) < 1e-3
    # noisy measurements: within a few formal sigmas, and the sigma is honest (not tiny)
    errs = []
    for _ in range(10):
        A, Bo, R, t = _pair(rng, 0.2, 0.1)
        est = offset_from_two_keyframes(KeyframePair(A, Bo, np.eye(3), np.zeros(3)), CAM)
        errs.append((est.d0 - 0.2) / est.sigma)
        assert 0.005 < est.sigma < 0.2 and 0.0 <= est.coupling <= 1.0
    assert np.sqrt(np.mean(np.square(errs))) < 3.0


def test_outliers_do_not_carry_the_offset_and_degenerate_input_gives_none():
    rng = np.random.default_rng(4)
    A, Bo, R, t = _pair(rng, -0.1, 0.05)
    Bo[:25, 2] += rng.uniform(3, 8, 25)  # 10 % gross disparity errors at B
    est = offset_from_two_keyframes(KeyframePair(A, Bo, R, t), CAM)
    assert est is not None and abs(est.d0 + 0.1) < 0.05
    assert offset_from_two_keyframes(KeyframePair(A[:10], Bo[:10], R, t), CAM) is None  # too few points
    Anan = A.copy()
    Anan[:, 2] = np.nan
    assert offset_from_two_keyframes(KeyframePair(Anan, Bo, R, t), CAM) is None
    # the known motion held fixed gives the offset as well
    fixed = offset_from_two_keyframes(KeyframePair(A, Bo, R, t), CAM, fix_pose=True)
    assert fixed is not None and abs(fixed.d0 + 0.1) < 0.05


def test_offset_filter_is_slow_gated_and_bounded():
    f = OffsetFilter(prior=0.0, bound=0.5, min_pairs=3)
    assert f.value == 0.0 and not f.ready
    assert not f.update(None) and not f.update(PairEstimate(0.1, 0.5, 100))  # too uncertain
    for _ in range(3):
        assert f.update(PairEstimate(-0.2, 0.05, 100))
    assert f.ready and -0.2 < f.value < -0.1  # the prior still holds some weight
    assert not f.update(PairEstimate(3.0, 0.05, 100)) and f.rejected == 1  # far from the value: gated out
    for _ in range(200):
        f.update(PairEstimate(f.value - 0.25, 0.1, 100))  # a steady pull cannot take it past the bound
    assert f.value >= -0.5


def _scene_pair(rng, t, depth_range, d0=0.0, noise=0.05, n=300):
    """Points in front of the camera (depths in ``depth_range``) seen from A and from B = A moved by ``t``."""
    Z = rng.uniform(*depth_range, n)
    X = np.column_stack([rng.uniform(-0.6, 0.6, n) * Z, rng.uniform(-0.45, 0.45, n) * Z, Z])
    R = so3_exp(np.array([0.0, 0.01, 0.0]))
    XB = X @ R.T + np.asarray(t)

    def obs(P):
        return np.column_stack([F * P[:, 0] / P[:, 2] + CX, F * P[:, 1] / P[:, 2] + CY, F * B / P[:, 2] + d0])

    return obs(X) + rng.normal(0, noise, (n, 3)), obs(XB) + rng.normal(0, noise, (n, 3)), R, np.asarray(t, float)


def test_sliding_sideways_past_a_scene_leaves_the_offset_unidentified_and_the_filter_ignores_it():
    rng = np.random.default_rng(7)
    # a scene 0.5-3 m deep; the camera slides 8 cm sideways (measured ~55)
    A, Bo, R, t = _scene_pair(rng, (-0.08, 0.0, 0.0), (0.5, 3.0))
    side = offset_from_two_keyframes(KeyframePair(A, Bo, R, t), CAM)
    # the same scene approached by 8 cm: the offset bends near and far points differently (~4)
    A, Bo, R, t = _scene_pair(rng, (0.0, 0.0, -0.08), (0.5, 3.0))
    forward = offset_from_two_keyframes(KeyframePair(A, Bo, R, t), CAM)
    assert side is not None and forward is not None
    assert side.inflation > 20.0 > forward.inflation >= 1.0
    f = OffsetFilter()
    assert not f.update(side) and f.unidentified == 1 and f.n == 0
    assert f.update(forward) and f.n == 1
    # with the motion known there is nothing to inflate
    fixed = offset_from_two_keyframes(KeyframePair(A, Bo, R, t), CAM, fix_pose=True)
    assert fixed.inflation == 1.0
    # approaching an object with little depth range tells it from a turn no better (~40)
    A, Bo, R, t = _scene_pair(rng, (0.0, 0.0, -0.08), (0.9, 1.3))
    assert offset_from_two_keyframes(KeyframePair(A, Bo, R, t), CAM).inflation > 20.0


def test_a_pair_past_the_inflation_limit_is_not_solved():
    rng = np.random.default_rng(8)
    A, Bo, R, t = _scene_pair(rng, (-0.08, 0.0, 0.0), (0.5, 3.0))
    full = offset_from_two_keyframes(KeyframePair(A, Bo, R, t), CAM)
    quick = offset_from_two_keyframes(KeyframePair(A, Bo, R, t), CAM, SolveOptions(max_inflation=10.0))
    assert np.isnan(quick.d0) and quick.inflation > 10.0
    assert abs(quick.inflation - full.inflation) < 0.2 * full.inflation  # the initial motion's is close to the final
    f = OffsetFilter(max_inflation=10.0)
    assert not f.update(quick) and f.unidentified == 1
    A, Bo, R, t = _scene_pair(rng, (0.0, 0.0, -0.08), (0.5, 3.0))
    kept = offset_from_two_keyframes(KeyframePair(A, Bo, R, t), CAM, SolveOptions(max_inflation=10.0))
    assert np.isfinite(kept.d0) and kept.inflation < 10.0


def test_the_motion_under_the_true_offset_is_the_true_motion_and_the_correction_maps_one_to_the_other():
    """Driving forward past a deep scene: measured with no offset where there is one, the motion is too
    long; under the true offset it is the true one; ``offset_correction_of_motion`` is the change."""
    rng = np.random.default_rng(6)
    t_true = np.array([0.02, -0.01, 1.0])
    A, Bo, R, t = _pair(rng, -0.2, 0.02, t=t_true)
    R0, t0 = motion_with_offset(KeyframePair(A, Bo, np.eye(3), np.zeros(3)), 0.0, CAM)
    R1, t1 = motion_with_offset(KeyframePair(A, Bo, np.eye(3), np.zeros(3)), -0.2, CAM)
    assert np.linalg.norm(t1 - t_true) < 2e-3 and np.linalg.norm(R1 - R) < 1e-3
    assert np.linalg.norm(t0) > np.linalg.norm(t_true) + 5e-3  # depths too long without the offset
    assert motion_with_offset(KeyframePair(A[:10], Bo[:10], R, t), -0.2, CAM) is None
    # in camera frames (here the rectified ones: R0 = I); poses of A and B in a world
    rect = SimpleNamespace(R0=np.eye(3), f=F, P0=np.array([[F, 0, CX, 0], [0, F, CY, 0], [0, 0, 1, 0]]), baseline_m=B)
    T_world_a = make_pose(so3_exp(np.array([0.1, 0.2, -0.1])), np.array([1.0, 2.0, 3.0]))
    T_ba_used = make_pose(R0, t0)
    T_world_b = T_world_a @ invert_pose(T_ba_used)
    D = offset_correction_of_motion(rect, KeyframeObservations(A, Bo, T_world_a, T_world_b), 0.0, -0.2)
    np.testing.assert_allclose(D @ T_ba_used, make_pose(R1, t1), atol=1e-6)
    assert offset_correction_of_motion(rect, KeyframeObservations(A[:10], Bo[:10], T_world_a, T_world_b), 0.0,
                                       -0.2) is None


def _drive(rng, d0, noise, K, step=(0.02, -0.01, 0.6), depth=(3.0, 40.0), n=400, seen=0.8):
    """A forward drive past a deep scene at K keyframes: per keyframe the (ids, rows) of the points it sees
    (each point at a random ``seen`` share of the keyframes, in front) and the true motions from the first."""
    Z = rng.uniform(*depth, n)
    X = np.column_stack([rng.uniform(-0.6, 0.6, n) * Z, rng.uniform(-0.3, 0.2, n) * Z, Z])
    views, motions = [], []
    for j in range(K):
        R = so3_exp(np.array([0.0, 0.004 * j, 0.0]))
        t = -np.asarray(step) * j
        Xj = X @ R.T + t
        vis = (rng.random(n) < seen) & (Xj[:, 2] > 1.0)
        rows = np.column_stack([F * Xj[:, 0] / Xj[:, 2] + CX, F * Xj[:, 1] / Xj[:, 2] + CY, F * B / Xj[:, 2] + d0])
        views.append((np.flatnonzero(vis), rows[vis] + rng.normal(0, noise, (int(vis.sum()), 3))))
        motions.append((R, t))
    return views, motions


def test_a_window_of_keyframes_is_the_pair_for_two_and_measures_the_offset_better_with_more():
    rng = np.random.default_rng(11)
    views, motions = _drive(rng, -0.2, 0.3, 2, seen=1.0)
    (ia, A), (ib, Bo) = views
    Bo[:20, 2] += rng.uniform(3, 8, 20)  # gross disparity errors: the same points are left out by both
    Bo[20:40, :2] += rng.uniform(0.8, 1.4, (20, 2))
    common = np.intersect1d(ia, ib)
    pair = offset_from_two_keyframes(
        KeyframePair(A[np.searchsorted(ia, common)], Bo[np.searchsorted(ib, common)], *motions[1]), CAM)
    win = offset_from_keyframes(views, motions, CAM)
    # the same solve (the window stops once the offset moves by less than SolveOptions.offset_step_px)
    assert win.d0 == pytest.approx(pair.d0, abs=SolveOptions().offset_step_px)
    assert win.sigma == pytest.approx(pair.sigma, rel=1e-2)
    assert win.inflation == pytest.approx(pair.inflation, rel=1e-3) and win.n_points == pair.n_points
    # the same drives seen as consecutive pairs and as windows of four (each started from a perturbed motion)
    err_pairs, err_windows, sig = [], [], []
    for trial in range(8):
        views, motions = _drive(rng, -0.2, 0.2, 4, depth=(2.0, 20.0))
        start = [motions[0]] + [(so3_exp(rng.normal(0, 0.003, 3)) @ R, t + rng.normal(0, 0.03, 3)) for R, t in motions[1:]]
        w = offset_from_keyframes(views, start, CAM)
        err_windows.append(w.d0 + 0.2)
        sig.append(w.sigma)
        for j in range(3):
            (ia, A), (ib, Bo) = views[j], views[j + 1]
            c = np.intersect1d(ia, ib)
            Rj = motions[j + 1][0] @ motions[j][0].T
            p = offset_from_two_keyframes(KeyframePair(A[np.searchsorted(ia, c)], Bo[np.searchsorted(ib, c)], Rj,
                                                       motions[j + 1][1] - Rj @ motions[j][1]), CAM)
            err_pairs.append(p.d0 + 0.2)
    rms = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    assert rms(err_windows) < 0.8 * rms(err_pairs)  # 0.30-0.67 over five seeds
    assert rms(err_windows) < 2.5 * np.median(sig)  # the formal sigma is honest
    # a point seen at one keyframe only carries nothing; too few shared points give None
    few = [(ids[:20], rows[:20]) for ids, rows in views]
    assert offset_from_keyframes(few, motions, CAM) is None
    assert offset_from_keyframes(views[:1], motions[:1], CAM) is None


def test_a_window_sliding_sideways_is_not_solved_and_poses_give_the_motions():
    rng = np.random.default_rng(12)
    views, motions = _drive(rng, 0.0, 0.05, 4, step=(0.08, 0.0, 0.0), depth=(0.5, 3.0))
    quick = offset_from_keyframes(views, motions, CAM, SolveOptions(max_inflation=10.0))
    assert np.isnan(quick.d0) and quick.inflation > 10.0
    f = OffsetFilter()
    assert not f.update(quick) and f.unidentified == 1
    # from world poses of the keyframes (camera to world, the rectified frame = the camera's here)
    rect = SimpleNamespace(R0=np.eye(3), f=F, P0=np.array([[F, 0, CX, 0], [0, F, CY, 0], [0, 0, 1, 0]]), baseline_m=B)
    views, motions = _drive(rng, -0.2, 0.05, 4)
    T_world = [invert_pose(make_pose(R, t)) for R, t in motions]
    T_world = [make_pose(so3_exp(np.array([0.3, -0.2, 0.1])), np.array([5.0, 1.0, -2.0])) @ T for T in T_world]
    est = offset_over_keyframes(rect, [(ids, rows, T) for (ids, rows), T in zip(views, T_world)], 10.0)
    assert abs(est.d0 + 0.2) < 0.02 and est.inflation < 10.0
