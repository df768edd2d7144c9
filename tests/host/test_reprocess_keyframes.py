"""Offline keyframes of the tracks stage (stereopath.host.reprocess.stage_tracks): with a spreader the
chain of keyframes is guessed ahead from cheap stereo corners and the keypoints computed in batches of
independent pieces; the keyframes and keypoints stay those chosen one after another."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.host.backend.tracks import TrackConfig


def _session(trajectory: str, frames: int):
    from stereopath.device.sim.session import SimConfig, open_sim

    return open_sim(SimConfig(frames=frames, trajectory=trajectory, seed=3))


@pytest.fixture(scope="module")
def orbit():
    return _session("orbit", 28)  # still for its first 15 frames, then a keyframe at every frame or two


_KEYPOINTS: dict = {}


@pytest.fixture
def keypoints_once(monkeypatch):
    """Each frame's keypoints computed once for all the runs of a test (they depend on the images only)."""
    from stereopath.host.reprocess import stage_tracks

    compute, asked = stage_tracks._keyframe_features, []

    def once(shared, images):
        asked.append(1)
        key = (hash(images[0].tobytes()), shared[1])
        if key not in _KEYPOINTS:
            _KEYPOINTS[key] = compute(shared, images)
        return _KEYPOINTS[key]

    monkeypatch.setattr(stage_tracks, "_keyframe_features", once)
    return asked


def _estimate(sess) -> dict[str, np.ndarray]:
    n = len(sess.groundtruth.T_world_cam)
    return {"t_ns": sess.t_ns, "seq": np.arange(n), "status": np.zeros(n, np.int8),
            "T_world_cam": sess.groundtruth.T_world_cam, "keyframe": np.zeros(n, bool)}


def _in_reverse(calls):
    def spread(fn, shared, items):  # computes the last piece first, returns them in the items' order
        calls.append((fn.__name__, len(items)))
        return list(reversed([fn(shared, it) for it in reversed(items)]))
    return spread


@pytest.mark.slow
@pytest.mark.parametrize("trajectory, frames", [("orbit", 28), ("arc", 100)])
def test_keyframes_guessed_ahead_are_the_keyframes_chosen_one_after_another(trajectory, frames, keypoints_once,
                                                                             monkeypatch):
    """Guessing the chain ahead changes where the keypoints are computed, never which keyframes are
    chosen: with the corners' guesses and with bad ones (corners ten times as far), the keyframes and
    keypoints are those of the rule applied one keyframe after another."""
    from stereopath.host.reprocess import stage_tracks
    from stereopath.host.backend.parallel import spread_with

    sess = _session(trajectory, frames)
    cfg = TrackConfig(feature_preset="sift", max_features=0)
    est = _estimate(sess)
    images = {}

    def images_of(i):
        if i not in images:
            fr = sess.frame(i)
            images[i] = (fr.left, fr.right)
        return images[i]

    kf, feats = stage_tracks.keyframes_by_view_change(
        sess.rig, est, lambda i: stage_tracks._keyframe_features((sess.rig, cfg), images_of(i)), cfg)
    assert 4 <= len(kf) < len(est["seq"]) and len(keypoints_once) == len(kf)
    corners = stage_tracks.view_points

    def far_corners(rig, left, right, cfg):
        c = corners(rig, left, right, cfg)
        c.X_cam = c.X_cam * 10.0
        return c

    computed = {}
    for guess, name in ((corners, "corners"), (far_corners, "bad guesses")):
        monkeypatch.setattr(stage_tracks, "view_points", guess)
        calls, n0 = [], len(keypoints_once)
        with spread_with(_in_reverse(calls)):
            kf2, feats2 = stage_tracks.keyframes_ahead(sess.rig, est, images_of, cfg)
        computed[name] = len(keypoints_once) - n0
        assert list(kf2) == list(kf), name
        for a, b in zip(feats, feats2):
            assert np.array_equal(a.feats.xy, b.feats.xy) and np.array_equal(a.X_cam, b.X_cam), name
        assert calls, name  # batches of keypoints went to the spreader
    if trajectory == "orbit":  # good guesses: the batches grow, little is thrown away
        assert computed["corners"] <= len(kf) + 3 and max(n for _, n in calls) >= 4, computed
    else:  # sparse keyframes: the bad guesses were wrong and thrown away, the answer is the same
        assert computed["bad guesses"] > computed["corners"], computed


@pytest.mark.slow
def test_keyframe_keypoints_are_independent_pieces_with_offline_keyframes(orbit, keypoints_once):
    """With keyframes by viewpoint change and a spreader, the keypoints go to parallel_map in batches
    (a fleet task spreads them over idle cores), and the stage's output is that of the plain run."""
    import dataclasses

    from stereopath.host.reprocess.config import REPROCESS_PRESETS, StageInputs
    from stereopath.host.backend.parallel import spread_with
    from stereopath.host.reprocess import stage_tracks

    base = REPROCESS_PRESETS["quick"]
    config = dataclasses.replace(base, tracks=dataclasses.replace(base.tracks, feature_preset="sift", window=2,
                                                                  gaps=(1, 2)))
    assert config.tracks.keyframe_parallax_deg > 0
    est = _estimate(orbit)
    plain = stage_tracks.run(config, StageInputs(orbit, False, {"estimate": est}))
    calls = []
    with spread_with(_in_reverse(calls)):
        spread = stage_tracks.run(config, StageInputs(orbit, False, {"estimate": est}))
    n_kf = len(plain["kf_index"])
    batches = [n for name, n in calls if name != "_match_gap"]  # the keypoints' batches
    assert len(batches) >= 2 and max(batches) > 2 and sum(batches) >= n_kf - 2
    for name in plain:
        assert np.array_equal(plain[name], spread[name]), name


class _Cores:
    """A spreader whose idle cores come and go: ``idle()`` answers from ``pattern`` in turn."""

    def __init__(self, pattern: list[bool]) -> None:
        self.pattern, self.asked, self.calls = pattern, 0, []

    def idle(self) -> bool:
        self.asked += 1
        return self.pattern[(self.asked - 1) % len(self.pattern)]

    def __call__(self, fn, shared, items):
        self.calls.append(len(items))
        return [fn(shared, it) for it in items]


@pytest.mark.slow
@pytest.mark.parametrize("pattern", [[False], [False, False, True], [True, False]])
def test_nothing_is_guessed_while_every_core_is_busy(orbit, keypoints_once, monkeypatch, pattern):
    """Guesses are made only while the spreader has idle cores: with none, no corner is computed and
    every keypoint computed is a keyframe's (no work a busy core was not free for); as cores come
    and go the keyframes and keypoints are still those chosen one after another."""
    from stereopath.host.reprocess import stage_tracks
    from stereopath.host.backend.parallel import spread_with

    cfg = TrackConfig(feature_preset="sift", max_features=0)
    est = _estimate(orbit)
    images_of = lambda i: (orbit.frame(i).left, orbit.frame(i).right)  # noqa: E731
    kf, feats = stage_tracks.keyframes_by_view_change(
        orbit.rig, est, lambda i: stage_tracks._keyframe_features((orbit.rig, cfg), images_of(i)), cfg)
    corners, looked = stage_tracks.view_points, []
    monkeypatch.setattr(stage_tracks, "view_points", lambda *a: looked.append(1) or corners(*a))
    cores, n0 = _Cores(pattern), len(keypoints_once)
    with spread_with(cores):
        kf2, feats2 = stage_tracks.keyframes_ahead(orbit.rig, est, images_of, cfg)
    assert list(kf2) == list(kf)
    for a, b in zip(feats, feats2):
        assert np.array_equal(a.feats.xy, b.feats.xy) and np.array_equal(a.X_cam, b.X_cam)
    if pattern == [False]:
        assert looked == [] and cores.calls == [] and len(keypoints_once) - n0 == len(kf)
    else:
        assert looked and cores.calls  # guessed while cores were idle


@pytest.mark.slow
def test_keyframe_keypoints_stored_on_disk_give_the_same_tracks_and_resume(orbit, keypoints_once, tmp_path):
    """With a folder of partial results each keyframe's keypoints go to a file and are read back a
    batch at a time (one after another and guessed ahead alike): the stage's output is that of the run
    that holds them all; a run interrupted after them reads them back instead of computing them."""
    import dataclasses

    from stereopath.host.backend.parallel import spread_with
    from stereopath.host.reprocess import stage_tracks
    from stereopath.host.reprocess.config import REPROCESS_PRESETS, StageInputs

    base = REPROCESS_PRESETS["quick"]
    config = dataclasses.replace(base, tracks=dataclasses.replace(base.tracks, feature_preset="sift", window=2,
                                                                  gaps=(1, 2)))
    est = _estimate(orbit)
    held = stage_tracks.run(config, StageInputs(orbit, False, {"estimate": est}))
    stored = stage_tracks.run(config, StageInputs(orbit, False, {"estimate": est}, parts=tmp_path / "a"))
    with spread_with(_in_reverse([])):
        ahead = stage_tracks.run(config, StageInputs(orbit, False, {"estimate": est}, parts=tmp_path / "b"))
    files = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert len(files) == len(held["kf_index"]) and files == sorted(p.name for p in (tmp_path / "b").iterdir())
    n = len(keypoints_once)
    again = stage_tracks.run(config, StageInputs(orbit, False, {"estimate": est}, parts=tmp_path / "a"))
    assert len(keypoints_once) == n  # every keyframe's keypoints read back
    for name in held:
        for other in (stored, ahead, again):
            assert np.array_equal(held[name], other[name]), name
