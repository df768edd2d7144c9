"""Keyframe feature tracks (stereopath.host.backend.tracks) on rendered frames of the simulated scan."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.core.geometry import invert_pose
from stereopath.host.backend.tracks import (
    PairMatch,
    TrackConfig,
    TrackedKeypoints,
    build_tracks,
    frame_observations,
    stereo_features,
)
from stereopath.host.backend.ba_common import as_observations
from stereopath.host.backend.observations import OBSERVATION_DTYPE
from tests.backend.ba_support import adjust


@pytest.fixture(scope="module")
def scan():
    from stereopath.device.sim.session import SimConfig, open_sim

    sess = open_sim(SimConfig(frames=40))
    frames = {i: sess.render(i) for i in (0, 4, 8, 12, 14)}
    return sess, frames


def test_stereo_keypoints_have_accurate_depth():
    from stereopath.device.sim.session import SimConfig, open_sim

    sess = open_sim(SimConfig(frames=40, with_depth=True))
    fr = sess.render(4)
    kf = stereo_features(sess.rig, fr.left, fr.right, TrackConfig())
    assert len(kf) > 300
    depth = fr.meta["depth0"]
    u, v = np.round(kf.feats.xy[:, 0]).astype(int), np.round(kf.feats.xy[:, 1]).astype(int)
    z_true = depth[v, u]
    ok = z_true > 0
    rel = np.abs(kf.X_cam[ok, 2] - z_true[ok]) / z_true[ok]
    assert np.median(rel) < 0.01


@pytest.mark.parametrize("preset", ["fast_asym", "sift"])
def test_keypoints_on_threads_of_their_own_are_the_ones_found_in_line(scan, preset):
    """Views and parts of the keypoints side by side (OpenCV at one thread meanwhile, as it was after):
    the same keypoints, descriptors and stereo points as one after another; a blank image has none."""
    import cv2

    sess, frames = scan
    cfg = TrackConfig(feature_preset=preset, max_features=3000)
    fr = frames[8]
    before = cv2.getNumThreads()
    one = stereo_features(sess.rig, fr.left, fr.right, cfg, workers=1)
    three = stereo_features(sess.rig, fr.left, fr.right, cfg, workers=3)
    assert cv2.getNumThreads() == before
    assert len(one) > 300 and len(three) == len(one)
    for a, b in [(one.uv0, three.uv0), (one.uv1, three.uv1), (one.X_cam, three.X_cam),
                 (one.feats.xy, three.feats.xy), (one.feats.desc, three.feats.desc), (one.feats.view, three.feats.view)]:
        assert np.array_equal(a, b)
    blank = np.zeros_like(fr.left)
    for workers in (1, 2):
        none = stereo_features(sess.rig, blank, blank, cfg, workers=workers)
        assert len(none) == 0 and none.X_cam.shape == (0, 3)


def test_tracks_over_keyframes_fit_the_true_poses(scan):
    sess, frames = scan
    cfg = TrackConfig(feature_preset="sift", window=3)
    idx = [0, 4, 8, 12]
    T = sess.groundtruth.T_world_cam[idx]
    feats = [stereo_features(sess.rig, frames[i].left, frames[i].right, cfg) for i in idx]
    ticks = []
    tr = build_tracks(sess.rig, feats, T, cfg, progress=ticks.append)
    assert sum(ticks) == len(feats)  # every keyframe matched, a batch at a time
    assert tr.stats["tracks"] > 300 and tr.stats["mean_track_length"] > 2.0
    # held compact: 21 bytes a row, int32 ids, float32 pixels
    assert tr.observations.dtype == OBSERVATION_DTYPE and tr.observations.dtype.itemsize == 21
    obs = as_observations(tr.observations)
    assert obs.shape == (len(tr.observations), 6) and set(np.unique(obs[:, 2])) == {0.0, 1.0}
    # no track holds two keypoints of one keyframe
    pairs = obs[obs[:, 2] == 0][:, :2]
    assert len(np.unique(pairs, axis=0)) == len(pairs)
    # with the true poses held fixed, the tracks' points reproject within a fraction of a pixel
    res = adjust(sess.rig, T, tr.points, tr.observations, n_fixed=len(T), outlier_rounds=0)
    assert res.rms_after_px < 0.4
    # per-keyframe bookkeeping matches the observations
    for k in range(len(idx)):
        ids = obs[(obs[:, 0] == k) & (obs[:, 2] == 0), 1]
        assert tr.kf_ids[k].dtype == np.int32
        assert np.array_equal(np.sort(ids), np.sort(tr.kf_ids[k].astype(float)))


def test_frame_observations_follow_keyframe_points_into_a_frame(scan):
    sess, frames = scan
    cfg = TrackConfig(feature_preset="sift")
    T = sess.groundtruth.T_world_cam
    kf = stereo_features(sess.rig, frames[12].left, frames[12].right, cfg)
    points = {i: X @ T[12][:3, :3].T + T[12][:3, 3] for i, X in enumerate(kf.X_cam)}
    ids = np.arange(len(kf))
    obs = frame_observations(sess.rig, TrackedKeypoints(frames[12].left, kf.feats.xy, ids), points,
                             (frames[14].left, frames[14].right), T[14], cfg)
    left = obs[obs[:, 2] == 0]
    assert len(left) > 0.7 * len(kf) and np.sum(obs[:, 2] == 1) > 0.5 * len(kf)
    # the observed pixels agree with the points projected at the true pose
    Tcw = invert_pose(T[14])
    X = np.array([points[int(i)] for i in left[:, 1]]) @ Tcw[:3, :3].T + Tcw[:3, 3]
    K = sess.rig.cam0.K
    uv = X[:, :2] / X[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    assert np.median(np.linalg.norm(uv - left[:, 3:5], axis=1)) < 0.5


def _forward_rig():
    """A KITTI-like rectified rig (718 px focal length, 0.54 m baseline, 1241 x 376 images)."""
    from stereopath.device.core.rig import make_camera, make_rig

    K = np.array([[718.0, 0.0, 607.0], [0.0, 718.0, 185.0], [0.0, 0.0, 1.0]])
    return make_rig(make_camera("cam0", K, None, (1241, 376)), make_camera("cam1", K, None, (1241, 376)),
                    np.eye(3), [-0.54, 0.0, 0.0])


def _keyframe(rig, X_cam, desc, disparity_noise_px, rng):
    """KeyframeFeatures of camera points whose stereo depth carries a disparity error."""
    from stereopath.device.core.features import Features
    from stereopath.host.backend.tracks import KeyframeFeatures

    K = rig.cam0.K
    f, b = K[0, 0], rig.baseline_m
    uv0 = X_cam[:, :2] / X_cam[:, 2:] * f + K[:2, 2]
    d = f * b / X_cam[:, 2] + rng.normal(0.0, disparity_noise_px, len(X_cam))
    z = f * b / d
    X = np.column_stack([(uv0 - K[:2, 2]) / f * z[:, None], z])
    uv1 = uv0 - np.column_stack([d, np.zeros(len(d))])
    n = len(X_cam)
    feats = Features(uv0.astype(np.float32), desc.astype(np.float32), np.full(n, 4.0, np.float32),
                     np.zeros(n, np.float32), np.ones(n, np.float32), np.zeros(n, np.int16))
    return KeyframeFeatures(feats, uv0, uv1, X)


def test_matches_after_driving_forward_are_kept_and_wrong_ones_rejected():
    """Driving 2.4 m towards points 5-40 m away: a's stereo depth error (0.25 px disparity noise) moves
    the predicted position along the epipolar line by up to ~1 px near the image's sides.  Correct
    matches are kept (the check allows the shift the depth uncertainty explains); matches 2 px off
    the epipolar line are rejected."""
    from stereopath.host.backend.tracks import match_keyframes

    rig, rng = _forward_rig(), np.random.default_rng(3)
    n = 1500
    z = rng.uniform(5.0, 40.0, n)
    K = rig.cam0.K
    uv = np.column_stack([rng.uniform(20, 1220, n), rng.uniform(20, 356, n)])
    Xa = np.column_stack([(uv - K[:2, 2]) / K[0, 0] * z[:, None], z])
    T_b = np.eye(4)
    T_b[2, 3] = 2.4
    Xb = Xa - T_b[:3, 3]
    desc = rng.normal(size=(n, 128))
    a = _keyframe(rig, Xa, desc, 0.25, rng)
    b = _keyframe(rig, Xb, desc + rng.normal(scale=0.05, size=desc.shape), 0.25, rng)
    # every 10th match is wrong: b's pixel moved 2 px across the epipolar line (radial from the centre)
    wrong = np.arange(n) % 10 == 0
    radial = b.feats.xy - K[:2, 2]
    across = np.column_stack([-radial[:, 1], radial[:, 0]]) / np.linalg.norm(radial, axis=1)[:, None]
    b.feats.xy[wrong] += (2.0 * across[wrong]).astype(np.float32)
    b.feats.xy[:] += rng.normal(0.0, 0.1, b.feats.xy.shape).astype(np.float32)  # keypoint noise
    def kept(cfg):
        idx = match_keyframes(rig, a, b, np.eye(4), T_b, cfg)
        assert np.all(idx[:, 0] == idx[:, 1])
        return np.isin(np.arange(n), idx[:, 0])

    # the matches the descriptors find at all (keypoints closer than a few pixels collapse)
    found = kept(TrackConfig(match=PairMatch(verify_px=50.0, verify_disparity_px=50.0)))
    ok = found & ~wrong
    new = kept(TrackConfig())
    assert new[ok].mean() > 0.97 and new[found & wrong].mean() < 0.05
    # without the depth allowance many correct matches were lost
    old = kept(TrackConfig(match=PairMatch(verify_depth_sigmas=0.0)))
    assert old[ok].mean() < 0.8


def test_offline_keyframes_follow_the_viewpoint_change_not_the_estimators_keyframes():
    """Offline keyframes: a new one when the view of the last one's points changed by more than
    ``keyframe_parallax_deg`` (or its points moved more than ``keyframe_motion_px``): sparse while
    the camera turns on the spot or moves slowly, every frame when it drives fast towards the scene;
    the estimator's keyframe flags play no part."""
    from stereopath.device.core.geometry import so3_exp
    from stereopath.host.reprocess.stage_tracks import keyframes_by_view_change
    from stereopath.host.backend.tracks import view_change

    rig, rng = _forward_rig(), np.random.default_rng(4)
    n_frames = 40
    T = np.repeat(np.eye(4)[None], n_frames, axis=0)
    for i in range(1, n_frames):  # 10 frames turning on the spot (1.5 deg each), then slow, then fast forward
        T[i] = T[i - 1].copy()
        if i < 10:
            T[i, :3, :3] = T[i - 1, :3, :3] @ so3_exp(np.radians([0.0, 1.5, 0.0]))
        else:
            T[i, :3, 3] = T[i - 1, :3, 3] + T[i - 1, :3, 2] * (0.2 if i < 25 else 3.0)
    K = rig.cam0.K
    z = rng.uniform(8.0, 30.0, 800)
    uv = np.column_stack([rng.uniform(100, 1140, 800), rng.uniform(40, 340, 800)])
    X = np.column_stack([(uv - K[:2, 2]) / K[0, 0] * z[:, None], z])
    feats = _keyframe(rig, X, rng.normal(size=(800, 128)), 0.0, rng)
    est = {"status": np.zeros(n_frames, np.int8), "T_world_cam": T,
           "keyframe": np.arange(n_frames) % 10 == 0}  # the estimator's choice: ignored
    cfg = TrackConfig()
    asked = []
    kf, fs = keyframes_by_view_change(rig, est, lambda i: asked.append(i) or feats, cfg)
    assert kf[0] == 0 and kf[-1] == n_frames - 1 and list(kf) == asked and len(fs) == len(kf)

    def within(k0, k1):
        angle, motion = view_change(rig, feats, T[k0], T[k1], cfg.stereo.min_depth_m)
        return angle <= cfg.keyframe_parallax_deg and motion <= cfg.keyframe_motion_px

    for k0, k1 in zip(kf[:-1], kf[1:]):
        assert k1 == k0 + 1 or within(k0, k1)
        if k1 + 1 < n_frames:  # the last frame within the limits: the next one is beyond them
            assert not within(k0, k1 + 1)
    assert 3 <= kf[1] <= 9  # turning on the spot: no viewpoint change, a keyframe when the points moved ~100 px
    assert np.sum((kf > 10) & (kf < 25)) <= 2  # 0.2 m a frame: few keyframes
    assert np.all(np.diff(kf)[-10:] == 1)  # 3 m a frame towards points 8-30 m away: every frame
