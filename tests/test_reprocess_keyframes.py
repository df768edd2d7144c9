"""Offline keyframes of the tracks stage (stereopath.host.reprocess.stage_tracks): chosen from cheap
stereo corners, then every keyframe's keypoints computed as independent pieces."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.host.reprocess.tracks import TrackConfig


@pytest.fixture(scope="module")
def orbit():
    from stereopath.device.sim.session import SimConfig, open_sim

    return open_sim(SimConfig(frames=40, trajectory="orbit", seed=3))


def _estimate(sess) -> dict[str, np.ndarray]:
    n = len(sess.groundtruth.T_world_cam)
    return {"t_ns": sess.t_ns, "seq": np.arange(n), "status": np.zeros(n, np.int8),
            "T_world_cam": sess.groundtruth.T_world_cam, "keyframe": np.zeros(n, bool)}


def test_corners_see_the_viewpoint_change_the_keypoints_see(orbit):
    """The corners that choose the keyframes measure the same median parallax and image motion as the
    keyframe's keypoints (both medians over stereo points of the same scene), at a small part of the work."""
    from stereopath.host.reprocess.stage_tracks import view_points
    from stereopath.host.reprocess.tracks import stereo_features, view_change

    cfg = TrackConfig(feature_preset="sift", max_features=0)  # every keypoint, as the presets
    fr = orbit.frame(30)  # the session starts still
    corners = view_points(orbit.rig, fr.left, fr.right, cfg)
    keypoints = stereo_features(orbit.rig, fr.left, fr.right, cfg)
    assert 300 < len(corners) and corners.feats.desc.shape == (len(corners), 0)
    T = orbit.groundtruth.T_world_cam
    for j in (31, 32, 34):
        a = view_change(orbit.rig, corners, T[30], T[j], cfg.min_depth_m)
        b = view_change(orbit.rig, keypoints, T[30], T[j], cfg.min_depth_m)
        assert a[0] > 0.5 and a[1] > 5.0
        assert a[0] == pytest.approx(b[0], rel=0.15) and a[1] == pytest.approx(b[1], rel=0.15)


def test_keyframe_keypoints_are_independent_pieces_with_offline_keyframes(orbit):
    """With keyframes by viewpoint change, the keypoints of every chosen keyframe go to parallel_map in
    one call (a fleet task spreads them over idle cores), and the stage's output is that of the plain run."""
    import dataclasses

    from stereopath.host.reprocess.config import REPROCESS_PRESETS, StageInputs
    from stereopath.host.reprocess.parallel import spread_with
    from stereopath.host.reprocess import stage_tracks

    base = REPROCESS_PRESETS["quick"]
    config = dataclasses.replace(base, tracks=dataclasses.replace(base.tracks, feature_preset="sift", window=3,
                                                                  gaps=(1, 2, 3)))
    assert config.tracks.keyframe_parallax_deg > 0
    est = _estimate(orbit)
    plain = stage_tracks.run(config, StageInputs(orbit, False, {"estimate": est}))
    calls = []

    def in_reverse(fn, shared, items):
        calls.append((fn.__name__, len(items)))
        return list(reversed([fn(shared, it) for it in reversed(items)]))

    with spread_with(in_reverse):
        spread = stage_tracks.run(config, StageInputs(orbit, False, {"estimate": est}))
    n_kf = len(plain["kf_index"])
    assert 3 <= n_kf < len(est["seq"])
    assert calls[0] == ("_keyframe_features", n_kf)
    for name in plain:
        assert np.array_equal(plain[name], spread[name]), name
