"""Keyframe feature tracks (stereopath.host.reprocess.tracks) on rendered frames of the simulated scan."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.core.geometry import invert_pose
from stereopath.host.reprocess.gtsam_ba import bundle_adjust
from stereopath.host.reprocess.tracks import TrackConfig, build_tracks, frame_observations, stereo_features


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


def test_tracks_over_keyframes_fit_the_true_poses(scan):
    sess, frames = scan
    cfg = TrackConfig(feature_preset="sift", window=3)
    idx = [0, 4, 8, 12]
    T = sess.groundtruth.T_world_cam[idx]
    feats = [stereo_features(sess.rig, frames[i].left, frames[i].right, cfg) for i in idx]
    ticks = []
    tr = build_tracks(sess.rig, feats, T, cfg, progress=ticks.append)
    assert len(ticks) == 3
    assert tr.stats["tracks"] > 300 and tr.stats["mean_track_length"] > 2.0
    assert tr.observations.shape[1] == 6 and set(np.unique(tr.observations[:, 2])) == {0.0, 1.0}
    # no track holds two keypoints of one keyframe
    pairs = tr.observations[tr.observations[:, 2] == 0][:, :2]
    assert len(np.unique(pairs, axis=0)) == len(pairs)
    # with the true poses held fixed, the tracks' points reproject within a fraction of a pixel
    res = bundle_adjust(sess.rig, T, tr.points, tr.observations, n_fixed=len(T), outlier_rounds=0)
    assert res.rms_after_px < 0.4
    # per-keyframe bookkeeping matches the observations
    for k in range(len(idx)):
        ids = tr.observations[(tr.observations[:, 0] == k) & (tr.observations[:, 2] == 0), 1]
        assert np.array_equal(np.sort(ids), np.sort(tr.kf_ids[k].astype(float)))


def test_frame_observations_follow_keyframe_points_into_a_frame(scan):
    sess, frames = scan
    cfg = TrackConfig(feature_preset="sift")
    T = sess.groundtruth.T_world_cam
    kf = stereo_features(sess.rig, frames[12].left, frames[12].right, cfg)
    points = {i: X @ T[12][:3, :3].T + T[12][:3, 3] for i, X in enumerate(kf.X_cam)}
    ids = np.arange(len(kf))
    obs = frame_observations(sess.rig, frames[12].left, kf.feats.xy, ids, points, frames[14].left,
                             frames[14].right, T[14], cfg)
    left = obs[obs[:, 2] == 0]
    assert len(left) > 0.7 * len(kf) and np.sum(obs[:, 2] == 1) > 0.5 * len(kf)
    # the observed pixels agree with the points projected at the true pose
    Tcw = invert_pose(T[14])
    X = np.array([points[int(i)] for i in left[:, 1]]) @ Tcw[:3, :3].T + Tcw[:3, 3]
    K = sess.rig.cam0.K
    uv = X[:, :2] / X[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    assert np.median(np.linalg.norm(uv - left[:, 3:5], axis=1)) < 0.5
