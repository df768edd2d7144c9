"""The cell-batched radius search behind guided matching equals a brute-force reference, exactly."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.core.features import Features
from stereopath.device.core.matching import MatchConfig, _match_pairs, match_guided
from stereopath.device.core.radius_search import radius_nearest, strip_rank


def _brute(pred, dq, rxy, dr, radius, distinct_px, rank):
    """Every query against every reference; integer squared distances, the same predicates."""
    nq, nr = len(pred), len(rxy)
    best, bd, sd = np.full(nq, -1), np.full(nq, np.inf, np.float32), np.full(nq, np.inf, np.float32)
    ref_key = [None] * nr
    sq = ((dq[:, None, :].astype(np.int64) - dr[None, :, :].astype(np.int64)) ** 2).sum(axis=2)
    dist = np.sqrt(sq.astype(np.float32))
    for i, p in enumerate(pred):
        if not np.isfinite(p).all():
            continue
        box = (rxy[:, 0] >= p[0] - radius) & (rxy[:, 0] <= p[0] + radius) & (rxy[:, 1] >= p[1] - radius) & (rxy[:, 1] <= p[1] + radius)
        cand = np.flatnonzero(box & (np.linalg.norm(rxy - p, axis=1) <= radius))
        if len(cand) == 0:
            continue
        b = min(cand, key=lambda j: (dist[i, j], rank[j]))
        best[i], bd[i] = b, dist[i, b]
        far = [j for j in cand if np.linalg.norm(rxy[j] - rxy[b]) > distinct_px]
        sd[i] = min((dist[i, j] for j in far), default=np.float32(np.inf))
        for j in cand:
            if ref_key[j] is None or (dist[i, j], i) < ref_key[j]:
                ref_key[j] = (dist[i, j], i)
    ref_best = np.array([-1 if k is None else k[1] for k in ref_key])
    return best, bd, sd, ref_best


def _scene(rng, nq, nr, radius):
    """Points on a half-pixel lattice (many exactly on a circle's border or its box's edge, some
    at one position twice), descriptors from a small set (equal distances), a few NaN and far
    predictions."""
    rxy = rng.integers(0, 80, (nr, 2)) * 0.5
    rxy[nr // 2:nr // 2 + 5] = rxy[:5]  # duplicate positions
    pred = rng.integers(-10, 90, (nq, 2)) * 0.5
    pred[:3] = rxy[:3] + [radius, 0.0]  # a reference exactly on the border
    pred[3:6] = rxy[3:6] + [0.6 * radius, 0.8 * radius]  # on the circle, inside the box
    pred[6] = np.nan
    pred[7] = [1e7, -1e7]
    words = rng.integers(0, 6, (12, 16)).astype(np.float32)
    dq = words[rng.integers(0, 12, nq)]
    dr = words[rng.integers(0, 12, nr)]
    return pred, dq, rxy, dr


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("cells", [1, 2, 3])
def test_radius_search_equals_brute_force(seed, cells):
    rng = np.random.default_rng(seed)
    radius = 5.0
    pred, dq, rxy, dr = _scene(rng, 150, 160, radius)
    for rank in (None, rng.permutation(len(rxy))):
        got = radius_nearest(pred, dq, rxy, dr, radius, 2.5, rank, cells_per_radius=cells)
        want = _brute(pred, dq, rxy, dr, radius, 2.5, np.arange(len(rxy)) if rank is None else rank)
        for g, w in zip((got.best, got.best_dist, got.second_dist, got.ref_best), want):
            np.testing.assert_array_equal(g, w)
        assert (got.best >= 0).sum() > 50 and np.isfinite(got.second_dist).sum() > 20


def test_radius_search_empty_and_far_inputs():
    d = np.zeros((0, 16), np.float32)
    r = radius_nearest(np.zeros((0, 2)), d, np.ones((3, 2)), np.ones((3, 16), np.float32), 4.0, 2.5)
    assert len(r.best) == 0 and (r.ref_best == -1).all()
    r = radius_nearest(np.ones((2, 2)), np.ones((2, 16), np.float32), np.zeros((0, 2)), d, 4.0, 2.5)
    assert (r.best == -1).all() and np.isinf(r.best_dist).all() and len(r.ref_best) == 0
    r = radius_nearest(np.array([[1e9, 0.0], [np.nan, 1.0]]), np.ones((2, 16), np.float32), np.zeros((1, 2)),
                       np.ones((1, 16), np.float32), 4.0, 2.5)
    assert (r.best == -1).all() and r.ref_best[0] == -1


def test_guided_matching_equals_the_pair_list_matcher_on_all_pairs():
    """match_guided (cell-batched search) gives the matches of the pair-list matcher fed with every
    pair within the radius, listed in the scan order that resolves equal distances."""
    rng = np.random.default_rng(7)
    radius = 5.0
    pred, dq, rxy, dr = _scene(rng, 300, 320, radius)
    xy1 = rng.uniform(0, 40, (len(pred), 2)).astype(np.float32)
    z = np.zeros(len(pred), np.float32)
    f1 = Features(xy1, dq, z, z, z, np.full(len(pred), -1, np.int16))
    z2 = np.zeros(len(rxy), np.float32)
    f2 = Features(rxy.astype(np.float32), dr, z2, z2, z2, np.full(len(rxy), -1, np.int16))
    cfg = MatchConfig(per_view=False)
    got = match_guided(f1, f2, pred, radius, cfg)
    ok = np.isfinite(pred).all(axis=1)
    xr = f2.xy.astype(np.float64)
    rank = strip_rank(xr, pred[ok], radius)
    q, r = [], []
    for i in np.flatnonzero(ok):
        p = pred[i]
        box = (xr[:, 0] >= p[0] - radius) & (xr[:, 0] <= p[0] + radius) & (xr[:, 1] >= p[1] - radius) & (xr[:, 1] <= p[1] + radius)
        js = np.flatnonzero(box & (np.linalg.norm(xr - p, axis=1) <= radius))
        js = js[np.argsort(rank[js])]
        q += [i] * len(js)
        r += list(js)
    q, r = np.array(q), np.array(r)
    dist = np.sqrt(((dq[q] - dr[r]) ** 2).sum(axis=1)).astype(np.float32)
    want = _match_pairs(q, r, dist, len(f1), len(f2), f1.xy.astype(np.float64), xr, cfg)
    assert len(want) > 20
    np.testing.assert_array_equal(got.idx, want.idx)
    np.testing.assert_array_equal(got.distance, want.distance)
