"""Track observations aligned on a reference view (stereopath.host.backend.track_alignment)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from stereopath.host.backend.ba_common import as_observations
from stereopath.host.backend.track_alignment import facing_affine, refine_affine
from tests.backend.test_slanted_stereo import plane_wave_texture


def _warped_pair(A: np.ndarray, shift: np.ndarray, gain: float = 1.0, offset: float = 0.0):
    """A reference image and a target that shows its point ``p`` at ``c + A (p - c) + shift`` (c the
    image centre), both rendered exactly from the texture function, with mild noise."""
    h, w = 240, 320
    c = np.array([w / 2, h / 2])
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    Ai = np.linalg.inv(A)
    src = np.einsum("ij,jhw->ihw", Ai, np.stack([xs - c[0] - shift[0], ys - c[1] - shift[1]])) + c[:, None, None]
    rng = np.random.default_rng(7)
    ref = plane_wave_texture(xs, ys, 3) + rng.normal(0, 1.0, (h, w)).astype(np.float32)
    tgt = gain * plane_wave_texture(src[0], src[1], 3) + offset + rng.normal(0, 1.0, (h, w)).astype(np.float32)

    def true(p):
        return (p - c) @ A.T + c + shift

    return ref.clip(0, 255), tgt.clip(0, 255).astype(np.uint8), true


def _points(n: int, seed: int = 5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(70, 250, n), rng.uniform(50, 190, n)])


def test_an_affine_view_change_is_recovered_from_a_start_a_pixel_off():
    A = np.array([[1.08, 0.12], [-0.06, 0.93]])  # scale, shear and rotation: a surface seen from elsewhere
    ref, tgt, true = _warped_pair(A, np.array([2.3, -1.4]), gain=1.2, offset=-12.0)
    p = _points(300)
    start = true(p) + np.random.default_rng(1).normal(0, 0.6, p.shape)
    xy, A_fit, ok = refine_affine([ref], np.zeros(len(p), int), p, tgt, start, np.repeat(np.eye(2)[None], len(p), 0))
    assert ok.mean() > 0.95
    err = np.linalg.norm(xy[ok] - true(p[ok]), axis=1)
    assert np.median(err) < 0.02 and np.percentile(err, 95) < 0.05
    assert np.allclose(np.median(A_fit[ok], axis=0), A, atol=0.005)
    # the detector's start was 0.6 px off per axis: the fit is 40x closer
    assert np.median(np.linalg.norm(start - true(p), axis=1)) > 40 * np.median(err)


def test_a_window_without_texture_is_not_settled_and_left_where_it_was():
    ref = np.full((120, 160), 90.0, np.float32)
    tgt = np.full((120, 160), 90, np.uint8)
    p = np.array([[80.0, 60.0], [50.0, 40.0]])
    xy, _, ok = refine_affine([ref], np.zeros(2, int), p, tgt, p + 0.3, np.repeat(np.eye(2)[None], 2, 0))
    assert not ok.any()
    assert np.allclose(xy, p + 0.3)


def test_the_starting_warp_of_a_surface_facing_the_reference_camera():
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    uv = np.array([[320.0, 240.0], [400.0, 300.0]])
    X = np.array([[0.0, 0.0, 2.0], [0.32, 0.24, 2.0]])
    X = X / np.linalg.norm(X, axis=1, keepdims=True) * 2.0  # points on the rays, 2 m away
    # the camera 0.5 m closer along the optical axis: the centre's window grows by 2 / 1.5
    T = np.eye(4)
    T[2, 3] = -0.5
    A = facing_affine(K, uv[:1], X[:1] * [0, 0, 1], T)
    assert np.allclose(A[0], np.eye(2) * 2.0 / 1.5, atol=1e-9)
    # the camera turned by 10 deg about its optical axis: the window turns with it, no scale
    th = np.radians(10.0)
    R = np.eye(4)
    R[:2, :2] = [[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]
    A = facing_affine(K, uv, X, R)
    assert np.allclose(A, np.repeat(R[None, :2, :2], 2, 0), atol=1e-9)


def test_aligned_tracks_see_one_surface_point_where_detections_scatter():
    """On the simulated scan, each observation lifted to the scene with the true depth: the points
    of one track agree far better after the alignment than the detected keypoints did."""
    from stereopath.device.sim.session import SimConfig, SimSession
    from stereopath.host.backend.tracks import StereoMatch, TrackConfig, build_tracks, stereo_features

    s = SimSession(SimConfig(frames=60))
    frames = [0, 8, 16, 24, 32]
    T_gt = s.trajectory.pose(s.t_ns[frames] * 1e-9)
    cfg = TrackConfig(feature_preset="sift", max_features=800, window=4, align_window=21)
    rendered = [s.renderer.render(T) for T in T_gt]
    kfs = [stereo_features(s.rig, left, right, cfg) for left, right, _ in rendered]

    def spread(tracks) -> float:
        """Median over tracks of the points' distance from their median, in pixels at their depth."""
        K = s.rig.cam0.K
        world, ids, z_all = [], [], []
        rows = as_observations(tracks.observations)
        for k, (_, _, depth) in enumerate(rendered):
            o = rows[(rows[:, 0] == k) & (rows[:, 2] == 0)]
            x0, y0 = np.floor(o[:, 3]).astype(int), np.floor(o[:, 4]).astype(int)
            fx, fy = o[:, 3] - x0, o[:, 4] - y0
            corners = np.stack([depth[y0, x0], depth[y0, x0 + 1], depth[y0 + 1, x0], depth[y0 + 1, x0 + 1]])
            z = (corners[0] * (1 - fx) + corners[1] * fx) * (1 - fy) + (corners[2] * (1 - fx) + corners[3] * fx) * fy
            smooth = np.ptp(corners, axis=0) < 0.01 * z  # not on a depth edge
            Xc = np.column_stack([(o[:, 3] - K[0, 2]) / K[0, 0], (o[:, 4] - K[1, 2]) / K[1, 1], np.ones(len(o))]) * z[:, None]
            world.append((Xc @ T_gt[k][:3, :3].T + T_gt[k][:3, 3])[smooth])
            ids.append(o[smooth, 1].astype(int))
            z_all.append(z[smooth])
        world, ids, z_all = np.vstack(world), np.concatenate(ids), np.concatenate(z_all)
        out = []
        for i in np.unique(ids):
            m = ids == i
            if m.sum() >= 3:
                d = np.linalg.norm(world[m] - np.median(world[m], axis=0), axis=1) / z_all[m] * K[0, 0]
                out.append(np.median(d))
        return float(np.median(out))

    from stereopath.host.backend.track_alignment import align_tracks

    plain = build_tracks(s.rig, kfs, T_gt, dataclasses.replace(cfg, align_window=0))
    align = lambda k, of, tr: align_tracks(s.rig, [r[0] for r in rendered], [r[1] for r in rendered], T_gt, cfg, k, of, tr)  # noqa: E731
    aligned = build_tracks(s.rig, kfs, T_gt, cfg, align=align)
    assert aligned.stats["tracks"] > 0.8 * plain.stats["tracks"]
    before, after = spread(plain), spread(aligned)
    assert after < 0.5 * before


@pytest.mark.parametrize("window", [3, 4, 43])
def test_the_alignment_window_must_be_off_or_a_sensible_size(window):
    from stereopath.device.errors import ConfigError
    from stereopath.host.backend.tracks import StereoMatch, TrackConfig

    with pytest.raises(ConfigError, match="align_window"):
        TrackConfig(align_window=window)


@pytest.mark.parametrize("slanted_window", [0, 21])
def test_a_match_known_within_a_pixel_is_refined_from_there(slanted_window):
    """stereo_points from a right-image guess (an aligned observation's old match moved alike) finds
    the match the depth-seeded search finds."""
    import cv2

    from stereopath.device.core.features import gray
    from stereopath.device.sim.session import SimConfig, SimSession
    from stereopath.host.backend.tracks import StereoMatch, TrackConfig, stereo_points

    s = SimSession(SimConfig(frames=5))
    f = s.frame(2)
    L, R = gray(f.left), gray(f.right)
    xy = cv2.goodFeaturesToTrack(L, 300, 0.01, 10).reshape(-1, 2)
    cfg = TrackConfig(stereo=StereoMatch(slanted_window=slanted_window))
    _, uv1, _, ok = stereo_points(s.rig, L, R, xy, cfg)
    guess = uv1[ok] + np.random.default_rng(2).uniform(-0.4, 0.4, (int(ok.sum()), 2))  # no distortion: raw = undistorted
    _, uv1_g, _, ok_g = stereo_points(s.rig, L, R, xy[ok], cfg, guess_right=guess)
    assert ok_g.mean() > 0.9
    assert np.median(np.linalg.norm(uv1_g[ok_g] - uv1[ok][ok_g], axis=1)) < 0.02


def test_a_window_reaching_over_the_image_border_does_not_count_as_aligned():
    from stereopath.host.backend.track_alignment import _window_inside

    c = np.array([[15.0, 40.0], [9.0, 40.0], [100.0, 40.0]])
    A = np.repeat(np.eye(2)[None], 3, 0)
    A[2] = [[1.5, 0.0], [0.0, 1.0]]  # a wider window around a point well inside a 112 px wide image
    assert _window_inside(c, A, 10, 112, 80).tolist() == [True, False, False]
