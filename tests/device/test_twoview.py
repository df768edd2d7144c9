"""Two-view geometry: relative pose from matches, degenerate cases, rotation-only model."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.core.config import from_mapping
from stereopath.device.errors import ConfigError
from stereopath.device.core.geometry import euler_xyz_to_matrix, rotation_angle_deg, so3_exp
from stereopath.device.core.twoview import TwoViewConfig, euler_xyz_deg, relative_pose, rotation_only

K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])


def project(X, K):
    p = X @ K.T
    return p[:, :2] / p[:, 2:3]


def scene(R, t, n=500, noise=0.25, outliers=0.25, seed=0, planar=False, depth=(2.0, 10.0), K2=None):
    """Points in camera 1, seen by camera 2 with x2 = R x1 + t; a share of matches replaced by outliers."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(*depth, n)
    x = rng.uniform(-0.55, 0.55, n) * z
    y = rng.uniform(-0.42, 0.42, n) * z
    X = np.c_[x, y, z]
    if planar:  # a slanted wall: z = 5 + 0.4 x
        X[:, 2] = 5.0 + 0.4 * X[:, 0]
    p1 = project(X, K) + rng.normal(0, noise, (n, 2))
    p2 = project(X @ R.T + t, K if K2 is None else K2) + rng.normal(0, noise, (n, 2))
    bad = rng.random(n) < outliers
    p2[bad] = rng.uniform([0, 0], [640, 480], (int(bad.sum()), 2))
    return p1, p2, bad


def angle_deg(a, b):
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


R_TRUE = euler_xyz_to_matrix(np.radians([2.0, -6.0, 1.5]))
T_TRUE = np.array([0.4, 0.05, 0.15])


def test_recovers_rotation_and_translation_direction_with_outliers():
    p1, p2, bad = scene(R_TRUE, T_TRUE)
    res = relative_pose(p1, p2, K)
    assert res.status == "ok", res.message
    assert rotation_angle_deg(res.R.T @ R_TRUE) < 0.1
    assert angle_deg(res.t, T_TRUE) < 1.0
    assert np.linalg.norm(res.t) == pytest.approx(1.0)
    # inliers are (nearly) the clean matches
    assert res.inliers.shape == (len(p1),)
    assert (res.inliers & bad).sum() <= 0.02 * bad.sum() + 2
    assert res.n_inliers >= 0.9 * (~bad).sum()
    np.testing.assert_allclose(res.euler_xyz_deg, [2.0, -6.0, 1.5], atol=0.1)


def test_paper_settings_fundamental_ransac_10000_iterations_and_magsac():
    p1, p2, _ = scene(R_TRUE, T_TRUE, seed=3)
    for cfg in (TwoViewConfig(method="ransac", max_iters=10_000), TwoViewConfig(method="magsac", max_iters=2000)):
        res = relative_pose(p1, p2, K, cfg=cfg)
        assert res.status == "ok"
        assert rotation_angle_deg(res.R.T @ R_TRUE) < 0.1
        assert angle_deg(res.t, T_TRUE) < 1.0
        assert res.F is not None and res.E is not None


def test_different_intrinsics_per_camera():
    K2 = np.array([[620.0, 0.0, 300.0], [0.0, 615.0, 250.0], [0.0, 0.0, 1.0]])
    p1, p2, _ = scene(R_TRUE, T_TRUE, seed=4, K2=K2)
    res = relative_pose(p1, p2, K, K2)
    assert res.status == "ok"
    assert rotation_angle_deg(res.R.T @ R_TRUE) < 0.1
    assert angle_deg(res.t, T_TRUE) < 1.0


@pytest.mark.parametrize("n", [0, 3, 7])
def test_too_few_matches_is_reported(n):
    p1, p2, _ = scene(R_TRUE, T_TRUE, n=max(n, 1), outliers=0.0)
    res = relative_pose(p1[:n], p2[:n], K)
    assert res.status == "too_few_matches"
    assert res.R is None and res.t is None
    assert res.inliers.shape == (n,)
    assert not res.ok


def test_identical_and_non_finite_points_do_not_crash():
    same = np.tile([[100.0, 120.0]], (60, 1))
    assert relative_pose(same, same + 5.0, K).status == "too_few_matches"
    nan = np.full((60, 2), np.nan)
    assert relative_pose(nan, nan, K).status == "too_few_matches"
    p1, p2, _ = scene(R_TRUE, T_TRUE, outliers=0.0, seed=6)
    p1[::3] = np.nan  # a third unusable: still estimable from the rest
    res = relative_pose(p1, p2, K)
    assert res.status == "ok"
    assert not res.inliers[::3].any()
    assert rotation_angle_deg(res.R.T @ R_TRUE) < 0.2
    # collinear points: F is not determined; any status, no exception
    line = np.c_[np.linspace(0, 600, 80), np.linspace(10, 400, 80)]
    assert relative_pose(line, line + [3.0, 1.0], K).status in {"failed", "pure_rotation", "planar", "too_few_matches"}
    # pure noise
    rng = np.random.default_rng(1)
    r = relative_pose(rng.uniform(0, 640, (100, 2)), rng.uniform(0, 640, (100, 2)), K)
    assert r.status in {"ok", "failed", "planar", "pure_rotation"}


def test_pure_rotation_is_detected_with_the_rotation_and_no_translation():
    R = so3_exp(np.radians([1.0, 4.0, -2.0]))
    p1, p2, _ = scene(R, np.zeros(3), seed=7)
    res = relative_pose(p1, p2, K)
    assert res.status == "pure_rotation", res.message
    assert res.t is None
    assert rotation_angle_deg(res.R.T @ R) < 0.1


def test_planar_scene_is_reported():
    p1, p2, _ = scene(R_TRUE, T_TRUE, planar=True, seed=8)
    res = relative_pose(p1, p2, K)
    assert res.status == "planar", res.message
    assert res.H is not None
    assert rotation_angle_deg(res.R.T @ R_TRUE) < 1.5
    assert res.t is not None and abs(np.linalg.norm(res.t) - 1.0) < 1e-9


def test_rotation_only_model():
    R = so3_exp(np.radians([-3.0, 2.0, 5.0]))
    p1, p2, bad = scene(R, np.zeros(3), seed=9, outliers=0.4)
    res = rotation_only(p1, p2, K)
    assert res.status == "ok"
    assert res.t is None
    assert rotation_angle_deg(res.R.T @ R) < 0.05
    assert (res.inliers == ~bad).mean() > 0.97
    assert rotation_only(p1[:2], p2[:2], K).status == "too_few_matches"
    assert np.linalg.det(res.R) == pytest.approx(1.0)


def test_euler_xyz_deg_matches_the_papers_convention():
    R = euler_xyz_to_matrix(np.radians([10.0, -20.0, 30.0]))
    np.testing.assert_allclose(euler_xyz_deg(R), [10.0, -20.0, 30.0], atol=1e-9)


def test_config_and_argument_validation():
    cfg = from_mapping(TwoViewConfig, {"max_iters": 10000, "method": "magsac", "threshold_px": 1.5})
    assert cfg.max_iters == 10000 and cfg.method == "magsac"
    with pytest.raises(ConfigError, match="threshold_px"):
        TwoViewConfig(threshold_px=0.0)
    with pytest.raises(ConfigError, match="max_iter"):
        from_mapping(TwoViewConfig, {"max_iter": 5})
    p = np.zeros((20, 2))
    with pytest.raises(ConfigError, match="differ in length"):
        relative_pose(p, p[:10], K)
    with pytest.raises(ConfigError, match="K1"):
        relative_pose(p, p, np.zeros((3, 3)))
    with pytest.raises(ConfigError, match=r"\(N, 2\)"):
        relative_pose(np.zeros((20, 3)), np.zeros((20, 3)), K)
