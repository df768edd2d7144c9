"""Loop closure (stereopath.host.backend.loops) on keyframes of a synthetic scene that repeats."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from stereopath.device.core.features import Features
from stereopath.device.core.geometry import invert_pose, make_pose, so3_exp
from stereopath.device.core.rig import CameraModel, paper_rig
from stereopath.host.backend.loops import LoopCandidate, LoopConfig, detect_loops, guided_matches, verify_pair
from stereopath.host.backend.tracks import KeyframeFeatures

SHIFT = np.array([3.0, 0.0, 0.0])  # the second copy of the textured wall


@pytest.fixture(scope="module")
def scene():
    """A textured wall of 400 points and an exact copy of it (same descriptors) 3 m to the right."""
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-0.9, 0.9, 400), rng.uniform(-0.6, 0.6, 400), rng.uniform(1.8, 2.4, 400)])
    desc = rng.normal(0, 1, (400, 128)).astype(np.float32)
    desc = np.abs(desc) / np.linalg.norm(desc, axis=1, keepdims=True) * 512
    return np.vstack([X, X + SHIFT]), np.vstack([desc, desc])


def _keyframe(rig, X_world, desc, T_world_cam, rng) -> KeyframeFeatures:
    """What stereo_features would give: visible points, noisy left pixels and stereo 3D points."""
    Tcw = invert_pose(T_world_cam)
    Xc = X_world @ Tcw[:3, :3].T + Tcw[:3, 3]
    K = rig.cam0.K
    uv = Xc[:, :2] / Xc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    vis = (Xc[:, 2] > 0.1) & np.all((uv > 5) & (uv < [635, 475]), axis=1)
    uv = uv[vis] + rng.normal(0, 0.3, (vis.sum(), 2))
    Xs = Xc[vis] * (1 + rng.normal(0, 0.002, (vis.sum(), 1)))  # stereo depth noise
    n = int(vis.sum())
    xy = uv  # the raw pixels: with the rig's distortion when it has one
    if np.any(rig.cam0.dist):
        xy = cv2.projectPoints(Xc[vis].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, rig.cam0.dist)[0].reshape(-1, 2)
        xy = xy + (uv - Xc[vis, :2] / Xc[vis, 2:] * [K[0, 0], K[1, 1]] - K[:2, 2])  # the same noise
    f = Features(xy.astype(np.float32), desc[vis], np.full(n, 4, np.float32), np.zeros(n, np.float32),
                 np.ones(n, np.float32), np.zeros(n, np.int32))
    return KeyframeFeatures(f, uv, uv, Xs)


def _path(n: int) -> np.ndarray:
    """n keyframes out along a 1 m loop and back to the start (true poses)."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / (n - 1)
        out.append(make_pose(so3_exp([0, 0.05 * np.sin(a), 0]), [0.25 * np.sin(a), 0.1 * (1 - np.cos(a)), 0]))
    return np.array(out)


def test_a_true_loop_is_found_and_measures_the_drift(scene):
    rig, rng = paper_rig(), np.random.default_rng(1)
    X, desc = scene
    T_true = _path(40)
    kfs = [_keyframe(rig, X, desc, T, rng) for T in T_true]
    drift = np.array([make_pose(so3_exp([0, 0.0004 * k, 0]), [0.0004 * k, 0, 0.0002 * k]) for k in range(40)])
    T_est = np.array([T @ D for T, D in zip(T_true, drift)])  # 16 mm and 0.9 deg off at the end
    loops = detect_loops(rig, kfs, T_est, LoopConfig(min_separation=25))
    assert loops, "the return to the start must close a loop"
    for lp in loops:
        assert lp.j - lp.i > 25 and lp.inliers >= 40
        T_ij_true = invert_pose(T_true[lp.i]) @ T_true[lp.j]
        assert np.linalg.norm(lp.T_ci_cj[:3, 3] - T_ij_true[:3, 3]) < 0.003
        assert lp.correction_m > 0.005  # it does see the drift


def test_a_repeated_texture_gives_no_false_loop(scene):
    rig, rng = paper_rig(), np.random.default_rng(2)
    X, desc = scene
    T_a = make_pose(np.eye(3), [0.0, 0.0, 0.0])
    T_b = make_pose(np.eye(3), SHIFT)  # looks at the copy: the same image as from T_a
    a, b = _keyframe(rig, X, desc, T_a, rng), _keyframe(rig, X, desc, T_b, rng)
    cfg = LoopConfig(min_separation=0, max_distance_m=10.0)  # let the pair through the space gate
    loop, why = verify_pair(rig, LoopCandidate(a, b, T_a, T_b, path_m=6.0), cfg)
    assert loop is None and "disagrees with the path" in why
    # the same in a whole path: out to the copy and back, every keyframe a candidate of every other
    T_path = np.array([T_a, *[make_pose(np.eye(3), SHIFT * s) for s in np.linspace(0.1, 0.9, 8)], T_b])
    kfs = [_keyframe(rig, X, desc, T, rng) for T in T_path]
    loops = detect_loops(rig, kfs, T_path, LoopConfig(min_separation=2, max_distance_m=10.0, nearest_checked=20))
    for lp in loops:  # any accepted loop must be a true one (the same place), never the copy
        T_ij = invert_pose(T_path[lp.i]) @ T_path[lp.j]
        assert np.linalg.norm(lp.T_ci_cj[:3, 3] - T_ij[:3, 3]) < 0.01
    assert not any(abs(lp.i - lp.j) == 9 for lp in loops)


def _count_matches(monkeypatch, kfs, matched: list, full: list) -> None:
    """Record each keyframe pair the loops module matches (once, guided or full) and the fully matched ones."""
    from stereopath.host.backend import loops as loops_mod

    def pair(a, b):
        return next(k for k, f in enumerate(kfs) if f is a), next(k for k, f in enumerate(kfs) if f is b)

    real_full, real_guided = loops_mod.descriptor_matches, loops_mod.guided_matches

    def counting_full(a, b):
        p = pair(a, b)
        full.append(p)
        if not matched or matched[-1] != p:
            matched.append(p)
        return real_full(a, b)

    def counting_guided(rig, cand, radius_px):
        matched.append(pair(cand.a, cand.b))
        return real_guided(rig, cand, radius_px)

    monkeypatch.setattr(loops_mod, "descriptor_matches", counting_full)
    monkeypatch.setattr(loops_mod, "guided_matches", counting_guided)


def test_the_guided_match_finds_a_loop_within_its_radius_and_the_full_match_one_beyond(scene, monkeypatch):
    from stereopath.host.backend import loops as loops_mod

    rig, rng = paper_rig(), np.random.default_rng(5)
    X, desc = scene
    T_a, T_b = make_pose(np.eye(3), [0.0, 0.0, 0.0]), make_pose(so3_exp([0, 0.03, 0]), [0.05, 0.02, 0.0])
    a, b = _keyframe(rig, X, desc, T_a, rng), _keyframe(rig, X, desc, T_b, rng)
    full: list = []
    real = loops_mod.descriptor_matches
    monkeypatch.setattr(loops_mod, "descriptor_matches", lambda x, y: full.append(1) or real(x, y))
    for drift_m, guided in ((0.004, True), (0.09, False)):  # 2 px and 45 px off at the wall (16 px radius)
        T_b_est = T_b @ make_pose(np.eye(3), [drift_m, 0.0, 0.0])
        full.clear()
        loop, why = verify_pair(rig, LoopCandidate(a, b, T_a, T_b_est, path_m=6.0), LoopConfig(min_separation=0))
        assert loop is not None and why.endswith("(guided)") == guided and len(full) == (0 if guided else 1)
        assert abs(loop.correction_m - drift_m) < 0.003  # the measured pose is the true one either way
        T_ab = invert_pose(T_a) @ T_b
        assert np.linalg.norm(loop.T_ci_cj[:3, 3] - T_ab[:3, 3]) < 0.003


def test_the_guided_match_predicts_raw_pixels_of_a_distorting_lens(scene):
    """The keypoints' raw pixels are distorted: the prediction must be too (a pinhole prediction is
    tens of pixels off towards the corners of this lens)."""
    rig = paper_rig()
    rig_d = dataclasses.replace(rig, cam0=CameraModel(rig.cam0.K, np.array([-0.3, 0.1, 0.0, 0.0, 0.0]), rig.cam0.size))
    X, desc = scene
    T_a, T_b = make_pose(np.eye(3), [0.0, 0.0, 0.0]), make_pose(so3_exp([0, 0.02, 0]), [0.03, 0.0, 0.0])
    T_ba = invert_pose(T_b) @ T_a
    found = []
    for r in (rig, rig_d):
        rng = np.random.default_rng(6)
        a, b = _keyframe(r, X, desc, T_a, rng), _keyframe(r, X, desc, T_b, rng)
        m = guided_matches(r, LoopCandidate(a, b, T_a, T_b, path_m=1.0), 3.0)
        same = np.linalg.norm(a.X_cam[m[:, 0]] @ T_ba[:3, :3].T + T_ba[:3, 3] - b.X_cam[m[:, 1]], axis=1)
        assert len(m) > 100 and np.median(same) < 0.02  # pairs of the same wall points
        found.append(len(m))
    assert found[1] >= 0.95 * found[0]


def test_candidates_are_tried_nearest_first_and_none_after_an_accepted_loop(scene, monkeypatch):
    from stereopath.host.backend import loops as loops_mod

    rig, rng = paper_rig(), np.random.default_rng(3)
    X, desc = scene
    T_true = _path(40)
    kfs = [_keyframe(rig, X, desc, T, rng) for T in T_true]
    matched: list[tuple[int, int]] = []  # the pairs matched (guided or full), in order, once each
    full: list[tuple[int, int]] = []  # the pairs fully matched
    _count_matches(monkeypatch, kfs, matched, full)
    cfg = LoopConfig(min_separation=25, nearest_checked=3)
    loops = detect_loops(rig, kfs, T_true, cfg)
    by_i: dict[int, list[int]] = {}
    for i, j in loops_mod.candidate_pairs(T_true, cfg):
        by_i.setdefault(i, []).append(j)
    assert len(loops) >= 3 and len({lp.i for lp in loops}) == len(loops)  # one loop per keyframe at most
    accepted = {lp.i: lp.j for lp in loops}
    for i, js in by_i.items():
        tried = [j for ii, j in matched if ii == i]
        assert tried == js[:len(tried)]  # nearest first
        if i in accepted:  # nothing matched after the accepted one
            assert tried[-1] == accepted[i]
        else:  # every candidate tried
            assert tried == js
    # the true path's nearest candidate sees the same view: it is the one accepted, and the only one matched,
    # by the guided match alone
    assert sum(len([j for ii, j in matched if ii == i]) for i in accepted) == len(accepted)
    assert not [p for p in full if p[0] in accepted]
    # a nearest candidate that fails (its stereo points at the wrong scale: every match rejected) is passed over
    # for the next one
    i0 = min(accepted)
    j_near = by_i[i0][0]
    bad = kfs[j_near]
    kfs[j_near] = KeyframeFeatures(bad.feats, bad.uv0, bad.uv1, 1.2 * bad.X_cam)
    matched.clear()
    again = {lp.i: lp.j for lp in detect_loops(rig, kfs, T_true, cfg)}
    assert len(by_i[i0]) > 1 and again.get(i0) == by_i[i0][1]


def test_the_live_closer_tries_the_nearest_earlier_keyframe_first(scene, monkeypatch):
    from stereopath.host.backend import loops as loops_mod
    from stereopath.host.live.live_loops import LiveLoopCloser

    rig, rng = paper_rig(), np.random.default_rng(4)
    X, desc = scene
    T_true = _path(40)
    kfs = [_keyframe(rig, X, desc, T, rng) for T in T_true]
    closer = LiveLoopCloser(rig, LoopConfig(min_separation=25, nearest_checked=3))
    for f, T in zip(kfs, T_true):  # what add() does once a keyframe's features are known
        closer.feats.append(f)
        closer.graph.add(T)
    pairs: list[tuple[int, int]] = []
    _count_matches(monkeypatch, kfs, pairs, [])
    j = 39
    loop = closer._check(j)
    C = T_true[:, :3, 3]
    earlier = [i for i, jj in loops_mod.candidate_pairs(T_true, closer.cfg) if jj == j]
    nearest = min(earlier, key=lambda i: np.linalg.norm(C[i] - C[j]))
    assert len(earlier) >= 2 and loop is not None and loop.i == nearest and [p[0] for p in pairs] == [nearest]
    # the nearest one failing (its stereo points at the wrong scale), the next nearest is taken
    bad = kfs[nearest]
    kfs[nearest] = closer.feats[nearest] = KeyframeFeatures(bad.feats, bad.uv0, bad.uv1, 1.2 * bad.X_cam)
    pairs.clear()
    second = sorted(earlier, key=lambda i: np.linalg.norm(C[i] - C[j]))[1]
    loop = closer._check(j)
    assert loop is not None and loop.i == second and [p[0] for p in pairs] == [nearest, second]
