"""The gyro's rotation as a prior of the frame's pose solve: its error model, the pixel noise it is
weighed against, and what it does to a solve whose visual constraint is weak."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.core.geometry import invert_pose, make_pose, rotation_angle_deg, so3_exp
from stereopath.device.errors import ConfigError
from stereopath.device.estimation.gyro_prior import (MIN_PIXEL_SIGMA_PX, GyroRotation, GyroRotationModel,
                                                      gyro_rotation, pixel_sigma)
from stereopath.device.estimation.stereo_measure import PoseGuess
from tests.device.test_estimation_units import _rendered_points


def test_the_error_model_adds_noise_bias_and_relative_error():
    m = GyroRotationModel(2e-4, 0.005)
    R = so3_exp(np.array([0.0, 0.03, 0.0]))  # 30 mrad over 50 ms
    expect = np.sqrt(2e-4**2 * 0.05 + (1e-3 * 0.05) ** 2 + (0.005 * 0.03) ** 2)
    assert m.sigma_rad(R, 0.05, 1e-3) == pytest.approx(expect)
    # an unknown bias (a MEMS gyro's whole range) makes the prior weak: a few mrad over a frame
    assert m.sigma_rad(R, 0.05, 0.1) > 4e-3 > 50 * m.sigma_rad(np.eye(3), 0.05, 0.0)
    with pytest.raises(ConfigError):
        GyroRotationModel(-1.0, 0.0)


def test_pixel_noise_is_the_inliers_rms_within_bounds():
    rng = np.random.default_rng(0)
    e = np.abs(rng.normal(0.0, 0.3, 400))
    e[:20] = 50.0  # outliers: not pixel noise
    assert pixel_sigma(e, 2.0, 1.0) == pytest.approx(np.sqrt(np.sum(e[20:] ** 2) / (2 * 380 - 6)), rel=1e-9)
    assert pixel_sigma(np.zeros(100), 2.0, 1.0) == MIN_PIXEL_SIGMA_PX
    assert pixel_sigma(np.full(100, 1.9), 2.0, 1.0) == 1.0  # beyond the loss's width: its width
    assert pixel_sigma(np.array([0.1, 0.2]), 2.0, 1.0) == 1.0  # too few to say: the ceiling


def test_the_prior_holds_the_rotation_where_the_points_are_few_and_noisy():
    """Twelve noisy points leave the rotation loose; the gyro's rotation (true, to 0.05 mrad) fixes it.  The
    same prior with a loose sigma (an unknown bias) leaves the visual solve as it was."""
    geo, left, right, xy, X = _rendered_points()
    T_true = np.eye(4)  # the world is camera 1's frame
    T_guess = make_pose(so3_exp(np.array([0.003, -0.002, 0.002])), np.array([0.001, 0.0, -0.002]))
    rng = np.random.default_rng(7)
    errs = {"none": [], "tight": [], "loose": []}
    for seed in range(8):
        pick = rng.choice(len(xy), 14, replace=False)
        uv = (xy[pick] + rng.normal(0.0, 0.8, (14, 2))).astype(np.float32)
        truth = GyroRotation(T_true[:3, :3].T.copy(), 5e-5)
        loose = GyroRotation(so3_exp(np.array([0.02, 0.0, 0.0])), 1.0)  # wrong, but says it knows nothing
        for name, gyro in (("none", None), ("tight", truth), ("loose", loose)):
            T, n, _ = geo.solve_pose(left, right, X[pick], uv, PoseGuess(T_guess, gyro=gyro), seed)
            assert T is not None
            errs[name].append(rotation_angle_deg(T[:3, :3]))
    assert np.median(errs["tight"]) < 0.2 * np.median(errs["none"])
    np.testing.assert_allclose(errs["loose"], errs["none"], atol=2e-3)


def test_the_prediction_carries_the_anchor_pose_and_the_gyro_rotation():
    T_prev = make_pose(so3_exp(np.array([0.1, 0.2, -0.1])), np.array([1.0, 2.0, 3.0]))
    R_step = so3_exp(np.array([0.0, 0.02, 0.0]))
    T_pred = T_prev @ make_pose(R_step, np.zeros(3))
    g = gyro_rotation(T_pred, R_step, 0.05, 1e-3, GyroRotationModel(2e-4, 0.0))
    np.testing.assert_allclose(g.R_cam_world, invert_pose(T_pred)[:3, :3], atol=1e-12)
    assert g.prior(0.5).weight == pytest.approx(0.5 / g.sigma_rad)


def test_the_rotation_since_the_keyframe_chains_and_breaks():
    from stereopath.device.estimation.gyro_prior import GyroSinceKeyframe

    g = GyroSinceKeyframe()
    step = (so3_exp(np.array([0.0, 0.01, 0.0])), 0.05)
    g.add(step)
    assert not g.unbroken  # no keyframe anchors it yet
    g.restart()
    for _ in range(3):
        g.add(step)
    np.testing.assert_allclose(g.R_cam, so3_exp(np.array([0.0, 0.03, 0.0])), atol=1e-12)
    assert g.dt_s == pytest.approx(0.15)
    g.add(None)  # a frame the gyro did not cover: no prior until the next keyframe
    g.add(step)
    assert not g.unbroken
    g.restart()
    assert g.unbroken and g.dt_s == 0.0
