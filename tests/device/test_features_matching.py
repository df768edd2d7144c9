"""Descriptor matching: near-duplicates from affine views, ratio/mutual checks, rectified and guided search."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereopath.device.core.config import from_mapping
from stereopath.device.errors import ConfigError
from stereopath.device.core.features import Features
from stereopath.device.core.matching import (
    NNConfig,
    MatchConfig,
    Matches,
    collapse_duplicates,
    knn,
    match,
    match_epipolar_rectified,
    match_guided,
)


def make_features(xy, desc, view=None) -> Features:
    xy = np.asarray(xy, np.float32)
    n = len(xy)
    return Features(
        xy,
        np.asarray(desc, np.float32),
        np.full(n, 4.0, np.float32),
        np.zeros(n, np.float32),
        np.ones(n, np.float32),
        np.zeros(n, np.int16) if view is None else np.asarray(view, np.int16),
    )


def random_desc(rng, n):
    d = rng.random((n, 128)).astype(np.float32) ** 3 * 255.0
    return d


def duplicated_scene(seed=0, n=200, n_views=4, jitter_px=1.2, desc_noise=4.0, n_distractors=300):
    """f1: n points; f2: every point seen in n_views views (near-duplicates) plus distractors."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(10, 630, (n, 2))
    desc = random_desc(rng, n)
    f1 = make_features(xy, desc)
    xy2, d2, v2, truth = [], [], [], []
    for v in range(n_views):
        xy2.append(xy + rng.uniform(-jitter_px, jitter_px, xy.shape) * (v > 0))
        d2.append(desc + rng.normal(0, desc_noise, desc.shape))
        v2.append(np.full(n, v))
        truth.append(np.arange(n))
    xy2.append(rng.uniform(10, 630, (n_distractors, 2)))
    d2.append(random_desc(rng, n_distractors))
    v2.append(rng.integers(0, n_views, n_distractors))
    truth.append(np.full(n_distractors, -1))
    f2 = make_features(np.concatenate(xy2), np.concatenate(d2), np.concatenate(v2))
    return f1, f2, np.concatenate(truth)


def plain_lowe(f1: Features, f2: Features, ratio=0.8) -> int:
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(f1.desc, f2.desc, k=2)
    return sum(1 for a, b in pairs if a.distance < ratio * b.distance)


@pytest.mark.parametrize("per_view", [True, False])
def test_near_duplicates_from_views_become_matches_not_rejections(per_view):
    f1, f2, truth = duplicated_scene()
    # Plain Lowe ratio testing sees each point's own duplicate as the runner-up.
    assert plain_lowe(f1, f2) < 0.1 * len(f1)
    m = match(f1, f2, MatchConfig(per_view=per_view))
    assert len(m) >= 0.95 * len(f1)
    assert (truth[m.idx[:, 1]] == m.idx[:, 0]).mean() >= 0.99
    # one match per location: no f1 point is matched twice, no f2 location twice
    assert len(np.unique(m.idx[:, 0])) == len(m)
    p2 = f2.xy[m.idx[:, 1]]
    dd = np.linalg.norm(p2[:, None] - p2[None], axis=2) + np.eye(len(p2)) * 1e9
    assert dd.min() > 2.5


def test_duplicates_on_both_sides_collapse_to_one_match_per_location():
    _, f2, truth = duplicated_scene(seed=1, n=150, n_views=3, n_distractors=0)
    # the same 3-view feature set on both sides: 450 keypoints, 150 locations
    m = match(f2, f2, MatchConfig(per_view=False))
    assert len(m) <= 150  # 150 locations, 450 keypoints on each side
    assert len(m) >= 140
    loc = truth[m.idx[:, 0]]
    assert len(np.unique(loc)) == len(m)
    assert (truth[m.idx[:, 0]] == truth[m.idx[:, 1]]).all()


def test_ambiguous_points_at_two_locations_are_rejected():
    rng = np.random.default_rng(5)
    desc = random_desc(rng, 50)
    xy = rng.uniform(0, 600, (50, 2))
    f1 = make_features(xy, desc)
    # second image: every point appears at two far-apart places with the same look
    xy2 = np.concatenate([xy, xy + 100.0])
    d2 = np.concatenate([desc + rng.normal(0, 2, desc.shape), desc + rng.normal(0, 2, desc.shape)])
    f2 = make_features(xy2, d2)
    assert len(match(f1, f2)) <= 2
    # with only one copy they all match
    assert len(match(f1, make_features(xy, d2[:50]))) == 50


def test_match_handles_empty_and_mismatched_inputs():
    rng = np.random.default_rng(0)
    f = make_features(rng.uniform(0, 100, (5, 2)), random_desc(rng, 5))
    assert len(match(f, Features.empty())) == 0
    assert len(match(Features.empty(), f)) == 0
    one = f.subset(np.array([0]))
    m = match(one, f)
    assert len(m) == 1 and tuple(m.idx[0]) == (0, 0)
    bad = Features(f.xy, f.desc[:, :64], f.size, f.angle, f.response, f.view)
    with pytest.raises(ConfigError, match="descriptor sizes differ"):
        match(f, bad)


def test_brute_force_and_flann_agree_on_easy_data():
    f1, f2, truth = duplicated_scene(seed=3, n=300, n_views=1, n_distractors=500)
    a = match(f1, f2, MatchConfig(index=NNConfig(method="bf")))
    b = match(f1, f2, MatchConfig(index=NNConfig(method="flann", flann_checks=128)))
    assert len(a) >= 290
    common = len(set(map(tuple, a.idx)) & set(map(tuple, b.idx)))
    assert common >= 0.95 * len(a)


def test_knn_sorted_and_exact():
    rng = np.random.default_rng(2)
    q, r = random_desc(rng, 20), random_desc(rng, 50)
    idx, dist = knn(q, r, 3, MatchConfig(index=NNConfig(method="bf")))
    full = np.linalg.norm(q[:, None] - r[None], axis=2)
    np.testing.assert_array_equal(idx[:, 0], full.argmin(axis=1))
    np.testing.assert_allclose(dist[:, 0], full.min(axis=1), rtol=1e-4)
    assert (np.diff(dist, axis=1) >= 0).all()
    idx, dist = knn(q, r[:2], 5)  # fewer references than k
    assert idx.shape == (20, 2)


def test_collapse_duplicates_is_one_to_one_per_location():
    xy1 = np.array([[0, 0], [1, 0], [50, 50], [52.0, 50], [100, 100]])
    xy2 = np.array([[10, 10], [10.5, 10], [60, 60], [90, 90], [60.5, 60]])
    score = np.array([0.5, 0.3, 0.2, 0.4, 0.1])
    keep = collapse_duplicates(xy1, xy2, score, 2.5)
    # 0/1 same place in both images -> keep 1 (better); 2/3 same place in image 1 -> keep 2;
    # 4 shares image-2 location with 2 but is better -> keep 4 and drop 2, so 3 survives.
    assert keep.tolist() == [False, True, False, True, True]


def test_match_config_validation():
    assert from_mapping(MatchConfig, {"ratio": 0.7, "index": {"method": "bf"}}).ratio == 0.7
    with pytest.raises(ConfigError, match="ratio"):
        MatchConfig(ratio=1.5)
    with pytest.raises(ConfigError, match=r"index\.method"):
        from_mapping(MatchConfig, {"index": {"method": "annoy"}})


# --------------------------------------------------------------------------- rectified stereo


def stereo_scene(seed=0, n=400, w=640, h=480):
    rng = np.random.default_rng(seed)
    xl = np.c_[rng.uniform(80, w - 1, n), rng.uniform(0, h - 1, n)]
    disp = rng.uniform(2, 70, n)
    xr = np.c_[xl[:, 0] - disp, xl[:, 1] + rng.uniform(-0.6, 0.6, n)]
    dl = random_desc(rng, n)
    dr = dl + rng.normal(0, 3, dl.shape)
    return xl, xr, dl, dr.astype(np.float32), disp


def test_rectified_matcher_finds_true_pairs_and_respects_the_band():
    xl, xr, dl, dr, _ = stereo_scene()
    rng = np.random.default_rng(9)
    n = len(xl)
    # decoys: identical descriptors that break the constraints
    dec_xy = np.concatenate([xr + [0, 3.0], xl + [4.0, 0]])  # 3 px off the row; negative disparity
    dec_d = np.concatenate([dl, dl])
    xr_all = np.concatenate([xr, dec_xy])
    dr_all = np.concatenate([dr, dec_d])
    order = rng.permutation(len(xr_all))
    xr_all, dr_all = xr_all[order], dr_all[order]
    truth = np.argsort(order)[:n]  # position of true right point i after shuffling
    m = match_epipolar_rectified(xl, xr_all, dl, dr_all, max_dy=1.0, min_disp=0.0, max_disp=100.0)
    li, ri = m.idx[:, 0], m.idx[:, 1]
    assert len(m) >= 0.95 * n
    assert (np.abs(xl[li, 1] - xr_all[ri, 1]) <= 1.0).all()
    assert (xl[li, 0] - xr_all[ri, 0] > 0).all()
    assert (truth[li] == ri).mean() >= 0.99


def test_rectified_matcher_disparity_window_and_degenerate_inputs():
    xl, xr, dl, dr, disp = stereo_scene(seed=1)
    m = match_epipolar_rectified(xl, xr, dl, dr, max_dy=1.0, min_disp=10.0, max_disp=40.0)
    d = xl[m.idx[:, 0], 0] - xr[m.idx[:, 1], 0]
    assert len(m) > 0.3 * len(xl)
    assert ((d >= 10.0) & (d <= 40.0)).all()
    # NaN rows and empty inputs
    xl2 = xl.copy()
    xl2[:50] = np.nan
    m2 = match_epipolar_rectified(xl2, xr, dl, dr)
    assert (m2.idx[:, 0] >= 50).all()
    assert len(match_epipolar_rectified(np.zeros((0, 2)), xr, np.zeros((0, 128)), dr)) == 0
    with pytest.raises(ConfigError, match="counts differ"):
        match_epipolar_rectified(xl, xr, dl[:5], dr)
    with pytest.raises(ConfigError, match="bad band"):
        match_epipolar_rectified(xl, xr, dl, dr, min_disp=50.0, max_disp=10.0)


def test_guided_matching_stays_inside_the_window():
    rng = np.random.default_rng(4)
    n = 300
    xy1 = rng.uniform(0, 640, (n, 2))
    d1 = random_desc(rng, n)
    shift = np.array([12.0, -7.0])
    xy2 = xy1 + shift + rng.normal(0, 0.5, (n, 2))
    d2 = d1 + rng.normal(0, 3, d1.shape)
    f1, f2 = make_features(xy1, d1), make_features(xy2, d2)
    pred = xy1 + shift + rng.normal(0, 3, (n, 2))
    m = match_guided(f1, f2, pred, radius_px=10.0)
    assert len(m) >= 0.95 * n
    assert (m.idx[:, 0] == m.idx[:, 1]).mean() >= 0.99
    assert (np.linalg.norm(xy2[m.idx[:, 1]] - pred[m.idx[:, 0]], axis=1) <= 10.0).all()
    # a wrong prediction finds nothing rather than a wrong match
    far = match_guided(f1, f2, xy1 + [200.0, 0.0], radius_px=5.0)
    assert (far.idx[:, 0] == far.idx[:, 1]).sum() == 0
    pred_nan = pred.copy()
    pred_nan[:100] = np.nan
    assert (match_guided(f1, f2, pred_nan, 10.0).idx[:, 0] >= 100).all()
    with pytest.raises(ConfigError, match="predictions"):
        match_guided(f1, f2, pred[:5], 10.0)


def test_matches_points_helper():
    rng = np.random.default_rng(0)
    f = make_features(rng.uniform(0, 10, (4, 2)), random_desc(rng, 4))
    m = Matches(np.array([[0, 1], [2, 3]], np.int32), np.zeros(2, np.float32))
    p1, p2 = m.points(f, f)
    np.testing.assert_allclose(p1, f.xy[[0, 2]])
    np.testing.assert_allclose(p2, f.xy[[1, 3]])

