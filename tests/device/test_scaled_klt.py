"""Frame-to-frame KLT with the previous image resampled at each point's predicted scale."""

import cv2
import numpy as np
import pytest

from stereopath.device.core.scaled_klt import scale_groups, track_scaled

KLT = dict(winSize=(19, 19), maxLevel=2, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))


def _texture(h=360, w=480, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for sigma, amp in ((1.0, 60.0), (3.0, 90.0), (8.0, 120.0)):
        img += amp * cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), sigma)
    return np.clip(img + 128.0, 0, 255).astype(np.uint8)


def _zoomed(img: np.ndarray, s: float, centre) -> tuple[np.ndarray, np.ndarray]:
    """``img`` magnified by ``s`` about ``centre`` (the view of a camera that moved towards a wall), and the map."""
    M = np.array([[s, 0.0, centre[0] * (1 - s)], [0.0, s, centre[1] * (1 - s)]])
    return cv2.warpAffine(img, M, img.shape[::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT), M


def test_scale_groups_are_rungs_of_a_geometric_ladder():
    k = scale_groups(np.array([1.0, 1.02, 1.04, 1.06, 1.0 / 1.05, 1.05**4, np.nan, -1.0, 0.0, 100.0]), 0.05)
    assert k.tolist() == [0, 0, 1, 1, -1, 4, 0, 0, 0, round(np.log(4.0) / np.log(1.05))]
    assert scale_groups(np.array([1.3, 0.7]), 0.0).tolist() == [0, 0]  # step 0: plain KLT for every point
    assert scale_groups(np.zeros(0), 0.05).shape == (0,)


def test_points_at_scale_one_are_tracked_exactly_as_opencv_tracks_them():
    prev = _texture()
    cur = np.roll(prev, (2, 3), axis=(0, 1))
    p0 = cv2.goodFeaturesToTrack(prev, 200, 0.01, 8).reshape(-1, 2)
    guess = p0 + (2.5, 1.5)
    p1, ok, fb = track_scaled(prev, cur, p0, guess, np.full(len(p0), 1.01), 0.05, KLT, 1)
    q1, st, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0.reshape(-1, 1, 2), guess.reshape(-1, 1, 2).astype(np.float32),
                                         flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **KLT)
    assert np.array_equal(p1, q1.reshape(-1, 2))
    assert np.array_equal(ok & (st.ravel() == 1), ok)
    assert ok.mean() > 0.9 and np.median(fb[ok]) < 0.05


@pytest.mark.parametrize("s", [1.15, 1.3, 1 / 1.2])
def test_a_magnified_view_is_tracked_onto_the_points_where_plain_klt_drifts_off(s):
    prev = _texture()
    centre = (250.0, 170.0)
    cur, M = _zoomed(prev, s, centre)
    mask = np.zeros_like(prev)
    mask[110:250, 150:330] = 255  # points that stay inside both views
    p0 = cv2.goodFeaturesToTrack(prev, 300, 0.01, 6, mask=mask).reshape(-1, 2)
    truth = p0 @ M[:, :2].T + M[:, 2]
    guess = truth + np.random.default_rng(1).normal(0, 1.0, truth.shape)  # a prediction good to a pixel
    scale = np.full(len(p0), s)
    plain, ok_plain, _ = track_scaled(prev, cur, p0, guess, scale, 0.0, KLT, 1)
    scaled, ok, fb = track_scaled(prev, cur, p0, guess, scale, 0.05, KLT, 1)
    err_plain = np.linalg.norm(plain - truth, axis=1)[ok_plain]
    err = np.linalg.norm(scaled - truth, axis=1)[ok]
    assert ok.mean() > 0.9 and np.median(fb[ok]) < 0.1  # the backward check is in pixels of the previous image
    assert np.median(err) < 0.1
    assert np.median(err) < 0.5 * np.median(err_plain)


@pytest.mark.parametrize("wild", [(900.0, -400.0), (3000.0, -2000.0), (-1500.0, 900.0), (300.0, 40.0)])
def test_a_point_predicted_far_off_does_not_break_the_others(wild):
    """A point barely in front of the camera (or on a moving car) can be predicted anywhere, also
    inside the image; the others of its group are tracked as if it were not there."""
    prev = _texture()
    cur, M = _zoomed(prev, 1.2, (240.0, 180.0))
    for p0 in (np.array([[200.0, 150.0], [260.0, 200.0], [470.0, 20.0]], np.float32),
               np.array([[200.0, 150.0], [470.0, 20.0]], np.float32)):
        guess = p0 @ M[:, :2].T + M[:, 2]
        guess[-1] = wild
        p1, ok, fb = track_scaled(prev, cur, p0, guess, np.full(len(p0), 1.2), 0.05, KLT, 1)
        truth = p0[:-1] @ M[:, :2].T + M[:, 2]
        assert ok[:-1].all() and fb[:-1].max() < 0.1
        assert np.linalg.norm(p1[:-1] - truth, axis=1).max() < 0.2


def test_points_at_scale_one_are_tracked_as_before_beside_other_groups():
    prev = _texture()
    cur, _ = _zoomed(prev, 1.1, (240.0, 180.0))
    p0 = cv2.goodFeaturesToTrack(prev, 150, 0.01, 8).reshape(-1, 2)
    guess = p0 + 1.0
    scale = np.where(np.arange(len(p0)) % 3 == 0, 1.0, 1.1)
    scale[1::3] = 1.3
    p1, ok, fb = track_scaled(prev, cur, p0, guess, scale, 0.05, KLT, 1)
    one = scale == 1.0
    q1, q_ok, q_fb = track_scaled(prev, cur, p0[one], guess[one], scale[one], 0.05, KLT, 1)
    assert np.array_equal(p1[one], q1) and np.array_equal(ok[one], q_ok) and np.array_equal(fb[one], q_fb)


def test_the_estimator_takes_0_or_a_step_of_at_least_1_percent():
    from stereopath.device.errors import ConfigError
    from stereopath.device.core.stereo_config import KltConfig

    assert KltConfig(klt_scale_step=0.0).klt_scale_step == 0.0
    assert KltConfig().klt_scale_step == 0.05
    for bad in (1e-6, 0.005, -0.05, 0.6, float("nan")):
        with pytest.raises(ConfigError, match="klt_scale_step"):
            KltConfig(klt_scale_step=bad)


def test_the_previous_image_pose_moves_with_the_live_state():
    """The scales compare each map point's depth in the previous image with its predicted depth now:
    a keyframe correction that moves the map must move the previous image's pose with it."""
    from stereopath.device.core.geometry import make_pose, so3_exp
    from stereopath.device.core.rig import paper_rig
    from stereopath.device.estimation.stereo_vo import StereoEstimator

    est = StereoEstimator(paper_rig())
    T = make_pose(so3_exp(np.array([0.0, 0.1, 0.0])), np.array([0.2, 0.0, 1.0]))
    st = est._state
    st.T_world_cam, st.T_prev_left = T.copy(), T.copy()
    G = make_pose(so3_exp(np.array([0.0, 0.0, 0.02])), np.array([0.01, -0.02, 0.0]))
    st.apply(G)
    assert np.allclose(st.T_prev_left, G @ T) and np.allclose(st.T_world_cam, st.T_prev_left)
    est.close()
