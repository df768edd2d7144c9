"""The on-line disparity offset: two-keyframe bundle adjustment and its bounded fusion (synthetic, exact truth)."""

import numpy as np

from types import SimpleNamespace

from stereopath.device.core.geometry import invert_pose, make_pose, so3_exp
from stereopath.device.estimation.disparity_offset import (
    OffsetFilter,
    PairEstimate,
    motion_with_offset,
    offset_correction_of_motion,
    offset_from_two_keyframes,
)

F, CX, CY, B = 450.0, 320.0, 240.0, 0.05


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
        est = offset_from_two_keyframes(A, Bo, np.eye(3), np.zeros(3), F, CX, CY, B)
        assert est is not None and abs(est.d0 - d0) < 1e-3
    # noisy measurements: within a few formal sigmas, and the sigma is honest (not tiny)
    errs = []
    for _ in range(10):
        A, Bo, R, t = _pair(rng, 0.2, 0.1)
        est = offset_from_two_keyframes(A, Bo, np.eye(3), np.zeros(3), F, CX, CY, B)
        errs.append((est.d0 - 0.2) / est.sigma)
        assert 0.005 < est.sigma < 0.2 and 0.0 <= est.coupling <= 1.0
    assert np.sqrt(np.mean(np.square(errs))) < 3.0


def test_outliers_do_not_carry_the_offset_and_degenerate_input_gives_none():
    rng = np.random.default_rng(4)
    A, Bo, R, t = _pair(rng, -0.1, 0.05)
    Bo[:25, 2] += rng.uniform(3, 8, 25)  # 10 % gross disparity errors at B
    est = offset_from_two_keyframes(A, Bo, R, t, F, CX, CY, B)
    assert est is not None and abs(est.d0 + 0.1) < 0.05
    assert offset_from_two_keyframes(A[:10], Bo[:10], R, t, F, CX, CY, B) is None  # too few points
    Anan = A.copy()
    Anan[:, 2] = np.nan
    assert offset_from_two_keyframes(Anan, Bo, R, t, F, CX, CY, B) is None
    # the known motion held fixed gives the offset as well
    fixed = offset_from_two_keyframes(A, Bo, R, t, F, CX, CY, B, fix_pose=True)
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
    side = offset_from_two_keyframes(A, Bo, R, t, F, CX, CY, B)
    # the same scene approached by 8 cm: the offset bends near and far points differently (~4)
    A, Bo, R, t = _scene_pair(rng, (0.0, 0.0, -0.08), (0.5, 3.0))
    forward = offset_from_two_keyframes(A, Bo, R, t, F, CX, CY, B)
    assert side is not None and forward is not None
    assert side.inflation > 20.0 > forward.inflation >= 1.0
    f = OffsetFilter()
    assert not f.update(side) and f.unidentified == 1 and f.n == 0
    assert f.update(forward) and f.n == 1
    # with the motion known there is nothing to inflate
    fixed = offset_from_two_keyframes(A, Bo, R, t, F, CX, CY, B, fix_pose=True)
    assert fixed.inflation == 1.0
    # approaching an object with little depth range tells it from a turn no better (~40)
    A, Bo, R, t = _scene_pair(rng, (0.0, 0.0, -0.08), (0.9, 1.3))
    assert offset_from_two_keyframes(A, Bo, R, t, F, CX, CY, B).inflation > 20.0


def test_a_pair_past_the_inflation_limit_is_not_solved():
    rng = np.random.default_rng(8)
    A, Bo, R, t = _scene_pair(rng, (-0.08, 0.0, 0.0), (0.5, 3.0))
    full = offset_from_two_keyframes(A, Bo, R, t, F, CX, CY, B)
    quick = offset_from_two_keyframes(A, Bo, R, t, F, CX, CY, B, max_inflation=10.0)
    assert np.isnan(quick.d0) and quick.inflation > 10.0
    assert abs(quick.inflation - full.inflation) < 0.2 * full.inflation  # the initial motion's is close to the final
    f = OffsetFilter(max_inflation=10.0)
    assert not f.update(quick) and f.unidentified == 1
    A, Bo, R, t = _scene_pair(rng, (0.0, 0.0, -0.08), (0.5, 3.0))
    kept = offset_from_two_keyframes(A, Bo, R, t, F, CX, CY, B, max_inflation=10.0)
    assert np.isfinite(kept.d0) and kept.inflation < 10.0


def test_the_motion_under_the_true_offset_is_the_true_motion_and_the_correction_maps_one_to_the_other():
    """Driving forward past a deep scene: measured with no offset where there is one, the motion is too
    long; under the true offset it is the true one; ``offset_correction_of_motion`` is the change."""
    rng = np.random.default_rng(6)
    t_true = np.array([0.02, -0.01, 1.0])
    A, Bo, R, t = _pair(rng, -0.2, 0.02, t=t_true)
    R0, t0 = motion_with_offset(A, Bo, np.eye(3), np.zeros(3), 0.0, F, CX, CY, B)
    R1, t1 = motion_with_offset(A, Bo, np.eye(3), np.zeros(3), -0.2, F, CX, CY, B)
    assert np.linalg.norm(t1 - t_true) < 2e-3 and np.linalg.norm(R1 - R) < 1e-3
    assert np.linalg.norm(t0) > np.linalg.norm(t_true) + 5e-3  # depths too long without the offset
    assert motion_with_offset(A[:10], Bo[:10], R, t, -0.2, F, CX, CY, B) is None
    # in camera frames (here the rectified ones: R0 = I); poses of A and B in a world
    rect = SimpleNamespace(R0=np.eye(3), f=F, P0=np.array([[F, 0, CX, 0], [0, F, CY, 0], [0, 0, 1, 0]]), baseline_m=B)
    T_world_a = make_pose(so3_exp(np.array([0.1, 0.2, -0.1])), np.array([1.0, 2.0, 3.0]))
    T_ba_used = make_pose(R0, t0)
    T_world_b = T_world_a @ invert_pose(T_ba_used)
    D = offset_correction_of_motion(rect, A, Bo, T_world_a, T_world_b, 0.0, -0.2)
    np.testing.assert_allclose(D @ T_ba_used, make_pose(R1, t1), atol=1e-6)
    assert offset_correction_of_motion(rect, A[:10], Bo[:10], T_world_a, T_world_b, 0.0, -0.2) is None
