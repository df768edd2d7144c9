"""Descriptor matching for SIFT / affine-view features.  Pure compute, arrays in and out.

:func:`match` is nearest-neighbour matching (brute force or a FLANN KD-tree,
chosen by problem size) with Lowe's ratio test and a mutual check, written for
feature sets that contain many near-duplicates: affine-simulated views detect
the same image location several times with slightly different descriptors.
Plain ratio testing would compare the best match with its own duplicate and
reject it.  Here

* with view labels (``per_view``, the default) each view of the first set is
  matched against each view of the second on its own, as in Morel & Yu's ASIFT,
  so one view's descriptors are never distractors in another view's ratio test;
* the ratio test compares the best candidate with the best candidate at a
  *different* location (more than ``distinct_px`` away);
* the mutual check accepts a reverse nearest neighbour at the same location
  (within ``distinct_px``), whichever view it came from;
* surviving matches collapse so that each location (in either image) keeps only
  its best match (one-to-one at the level of locations).

Extra views therefore turn into extra correct matches rather than rejections.

:func:`match_epipolar_rectified` matches rectified stereo pairs inside a band
``|dy| <= max_dy`` and a disparity range; :func:`match_guided` matches inside a
window around predicted positions (e.g. from a gyro prior).
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Collection, Literal, Mapping

import numpy as np

from stereopath.device.core.config import check_ranges, from_mapping, ranged
from stereopath.device.errors import ConfigError
from stereopath.device.core.features import Features
from stereopath.device.core.nn_index import NNConfig, NNIndex
from stereopath.device.core.radius_search import radius_nearest, strip_rank

log = logging.getLogger(__name__)

__all__ = ["MatchConfig", "Matches", "NNConfig", "NNIndex", "knn", "match", "match_candidates", "collapse_duplicates", "match_epipolar_rectified", "match_guided"]


@dataclass(frozen=True)
class MatchConfig:
    """Matching parameters (build from a mapping with ``stereopath.device.core.config.from_mapping``)."""

    ratio: float = ranged(0.8, 0.1, 1.0)  # Lowe's ratio: best < ratio * best-at-another-location
    mutual: bool = True
    distinct_px: float = ranged(2.5, 0.0, 100.0)  # keypoints closer than this are one location
    k: int = ranged(8, 2, 64)  # neighbours searched to find the best match at another location
    index: NNConfig = NNConfig()  # brute force or FLANN
    max_distance: float = ranged(0.0, 0.0, 1e9)  # absolute descriptor distance cap, 0 = none
    per_view: bool = True  # match view against view (features with view labels), then merge
    rank_by: Literal["ratio", "distance"] = "ratio"  # which duplicate survives the collapse
    # per_view: which view pairs are matched: all, or only pairs with the original view
    # on one side ("original"), optionally plus each view with itself ("original+same").
    view_pairs: Literal["all", "original", "original+same"] = "all"
    threads: int = ranged(1, 1, 64)  # thread pool over views of the second set

    def __post_init__(self) -> None:
        check_ranges(self)

    @staticmethod
    def from_mapping(mapping: Mapping[str, object]) -> "MatchConfig":
        return from_mapping(MatchConfig, mapping)


@dataclass(frozen=True, eq=False)
class Matches:
    """Index pairs ``idx[:, 0]`` into the first and ``idx[:, 1]`` into the second set."""

    idx: np.ndarray  # (M, 2) int32
    distance: np.ndarray  # (M,) float32, L2 descriptor distance

    def __len__(self) -> int:
        return int(self.idx.shape[0])

    @staticmethod
    def empty() -> "Matches":
        return Matches(np.zeros((0, 2), np.int32), np.zeros(0, np.float32))

    def points(self, xy1: np.ndarray | Features, xy2: np.ndarray | Features) -> tuple[np.ndarray, np.ndarray]:
        """Matched pixel positions ``(p1, p2)``, each (M, 2) float64."""
        a = xy1.xy if isinstance(xy1, Features) else np.asarray(xy1)
        b = xy2.xy if isinstance(xy2, Features) else np.asarray(xy2)
        return a[self.idx[:, 0]].astype(np.float64), b[self.idx[:, 1]].astype(np.float64)

    def subset(self, index: np.ndarray) -> "Matches":
        return Matches(self.idx[index], self.distance[index])


def knn(query: np.ndarray, ref: np.ndarray, k: int, cfg: MatchConfig = MatchConfig()) -> tuple[np.ndarray, np.ndarray]:
    """``k`` nearest rows of ``ref`` for every row of ``query`` (see :class:`NNIndex`)."""
    return NNIndex(ref, cfg.index, cfg.k, expected_queries=len(query)).query(query, k)


# --------------------------------------------------------------------------- location helpers


def _neighbor_pairs(xy: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    """All pairs ``(a, b)``, ``a < b``, of points closer than or equal to ``r`` (grid hashing)."""
    n = len(xy)
    if n < 2 or r <= 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    xy = np.asarray(xy, np.float64)
    cell = np.floor(xy / r).astype(np.int64)
    cell -= cell.min(axis=0) - 1
    big = int(cell[:, 1].max()) + 3
    key = cell[:, 0] * big + cell[:, 1]
    order = np.argsort(key, kind="stable")
    sk = key[order]
    aa, bb = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            target = key + dx * big + dy
            lo = np.searchsorted(sk, target, "left")
            hi = np.searchsorted(sk, target, "right")
            cnt = hi - lo
            total = int(cnt.sum())
            if total == 0:
                continue
            a = np.repeat(np.arange(n), cnt)
            start = np.repeat(lo - (np.cumsum(cnt) - cnt), cnt)
            b = order[start + np.arange(total)]
            keep = a < b
            aa.append(a[keep])
            bb.append(b[keep])
    if not aa:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    a = np.concatenate(aa)
    b = np.concatenate(bb)
    d = np.linalg.norm(xy[a] - xy[b], axis=1)
    keep = d <= r
    return a[keep], b[keep]


def _greedy_suppress(rank_order: np.ndarray, a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """Greedy non-maximum suppression on a conflict graph, vectorised.

    ``rank_order`` lists items best first; an item is kept unless a kept item of
    better rank conflicts with it.  Returns a boolean keep mask.
    """
    if len(a) == 0:
        return np.ones(n, bool)
    rank = np.empty(n, np.int64)
    rank[rank_order] = np.arange(n)
    first = np.where(rank[a] < rank[b], a, b)  # the better of each conflicting pair
    second = np.where(rank[a] < rank[b], b, a)
    state = np.zeros(n, np.int8)  # 0 undecided, 1 kept, -1 suppressed
    for _ in range(n + 1):
        undecided = state == 0
        if not undecided.any():
            break
        suppressed_now = np.zeros(n, bool)
        suppressed_now[second[state[first] == 1]] = True
        blocked = np.zeros(n, bool)
        blocked[second[state[first] != -1]] = True
        state[undecided & suppressed_now] = -1
        state[undecided & ~suppressed_now & ~blocked] = 1
    return state == 1


def collapse_duplicates(xy1: np.ndarray, xy2: np.ndarray, score: np.ndarray, radius_px: float) -> np.ndarray:
    """Keep-mask making matches one-to-one at the level of locations.

    A match is dropped when a better (smaller ``score``: distance or ratio) kept match lies within
    ``radius_px`` of it in the first image or in the second image.
    """
    n = len(score)
    if n < 2 or radius_px <= 0:
        return np.ones(n, bool)
    a1, b1 = _neighbor_pairs(xy1, radius_px)
    a2, b2 = _neighbor_pairs(xy2, radius_px)
    a = np.concatenate([a1, a2])
    b = np.concatenate([b1, b2])
    order = np.lexsort((np.arange(n), score))
    return _greedy_suppress(order, a, b, n)


def _ratio_at_other_location(nn_idx: np.ndarray, nn_dist: np.ndarray, xy_ref: np.ndarray, distinct_px: float) -> np.ndarray:
    """Distance of the best neighbour farther than ``distinct_px`` from the best one.

    When all ``k`` neighbours sit at the best one's location the k-th distance is
    returned (a lower bound of the true value, so the ratio test stays conservative);
    with a single neighbour, ``inf``.
    """
    n, k = nn_idx.shape
    if k < 2:
        return np.full(n, np.inf, np.float32)
    p0 = xy_ref[nn_idx[:, :1]]  # (n, 1, 2)
    pk = xy_ref[nn_idx[:, 1:]]  # (n, k-1, 2)
    far = np.linalg.norm(pk - p0, axis=2) > distinct_px
    far &= np.isfinite(nn_dist[:, 1:])
    has = far.any(axis=1)
    first = np.argmax(far, axis=1)
    second = nn_dist[np.arange(n), 1 + first]
    last = nn_dist[:, -1]
    return np.where(has, second, last).astype(np.float32)


# --------------------------------------------------------------------------- matching


def _view_groups(f: Features, per_view: bool) -> list[np.ndarray]:
    if not per_view or len(f) == 0 or (f.view < 0).any():
        return [np.arange(len(f))]
    views, inverse = np.unique(f.view, return_inverse=True)
    if len(views) == 1:
        return [np.arange(len(f))]
    order = np.argsort(inverse, kind="stable")
    bounds = np.cumsum(np.bincount(inverse.reshape(-1)))[:-1]
    return np.split(order, bounds)


def match(f1: Features, f2: Features, cfg: MatchConfig = MatchConfig(), only_pairs: Collection[tuple[int, int]] | None = None) -> Matches:
    """Match ``f1`` (e.g. SIFT on the earlier image) to ``f2`` (e.g. affine views of the later one).

    With ``cfg.per_view`` and view labels on the features, each view of ``f1`` is
    matched against each view of ``f2`` on its own (as in Morel & Yu's ASIFT: no
    view's descriptors act as distractors in another view's ratio test); the
    results are merged and each location keeps its most distinctive match.
    Without labels (``view == -1``) one global location-aware matching is done.
    ``only_pairs`` (view of ``f1``, view of ``f2``) restricts per-view matching to those
    view pairs (e.g. the ones :mod:`~stereopath.device.core.view_selection` chose).
    """
    i, j, d, r = match_candidates(f1, f2, cfg, only_pairs)
    if len(i) > 1:
        keep = collapse_duplicates(f1.xy[i], f2.xy[j], r if cfg.rank_by == "ratio" else d, cfg.distinct_px)
        i, j, d = i[keep], j[keep], d[keep]
    return Matches(np.stack([i, j], axis=1).astype(np.int32), d.astype(np.float32))


def match_candidates(f1: Features, f2: Features, cfg: MatchConfig = MatchConfig(), only_pairs: Collection[tuple[int, int]] | None = None) -> tuple[np.ndarray, ...]:
    """:func:`match` before the duplicate collapse: ``(i, j, distance, ratio)`` arrays of the
    candidates that passed the ratio test and the mutual check, from every matched view pair."""
    none = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.float32))
    if len(f1) == 0 or len(f2) == 0:
        return none
    if f1.desc.shape[1] != f2.desc.shape[1]:
        raise ConfigError(f"descriptor sizes differ: {f1.desc.shape[1]} vs {f2.desc.shape[1]}")
    groups1 = _view_groups(f1, cfg.per_view)
    groups2 = _view_groups(f2, cfg.per_view)
    view1 = [int(f1.view[g[0]]) for g in groups1]
    view2 = [int(f2.view[g[0]]) for g in groups2]
    labelled = cfg.per_view and bool((f1.view >= 0).all() and (f2.view >= 0).all())
    chosen = None if only_pairs is None or not labelled else {(int(a), int(b)) for a, b in only_pairs}

    def wanted(a: int, b: int) -> bool:
        if chosen is not None:
            return (a, b) in chosen
        if cfg.view_pairs == "all" or len(groups1) == 1 or len(groups2) == 1:
            return True
        return a == 0 or b == 0 or (cfg.view_pairs == "original+same" and a == b)

    def forward(g2i: int) -> list[tuple[np.ndarray, ...]]:
        # every (wanted) f1 view against view g2i of f2, one index per f2 view
        g1s = [g1 for g1, v1 in zip(groups1, view1) if wanted(v1, view2[g2i])]
        return _forward(f1, f2, g1s, groups2[g2i], cfg) if g1s else []

    if cfg.threads > 1 and len(groups2) > 1:
        with ThreadPoolExecutor(max_workers=cfg.threads) as pool:
            results = list(pool.map(forward, range(len(groups2))))
    else:
        results = [forward(g) for g in range(len(groups2))]
    parts = [p for res in results for p in res]
    if not parts:
        return none
    i, j, d, r = (np.concatenate([p[c] for p in parts]) for c in range(4))
    d, r = d.astype(np.float32), r.astype(np.float32)
    if cfg.mutual and len(i):
        keep = _mutual(f1, f2, groups1, i, j, cfg)
        i, j, d, r = i[keep], j[keep], d[keep], r[keep]
    return i, j, d, r


def _forward(f1: Features, f2: Features, g1s: list[np.ndarray], g2: np.ndarray, cfg: MatchConfig) -> list[tuple[np.ndarray, ...]]:
    """Ratio-tested nearest neighbours of each f1 view in ``g1s`` among f2 view ``g2``."""
    index = NNIndex(f2.desc[g2], cfg.index, cfg.k, expected_queries=sum(len(g) for g in g1s))
    out = []
    for g1 in g1s:
        nn_idx, nn_dist = index.query(f1.desc[g1], cfg.k)
        d0 = nn_dist[:, 0]
        d_other = _ratio_at_other_location(nn_idx, nn_dist, f2.xy[g2], cfg.distinct_px)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(d_other > 0, d0 / d_other, np.where(d0 > 0, np.inf, 0.0))
        ok = np.isfinite(d0) & (ratio < cfg.ratio)
        if cfg.max_distance > 0:
            ok &= d0 <= cfg.max_distance
        sel = np.nonzero(ok)[0]
        out.append((g1[sel], g2[nn_idx[sel, 0]], d0[sel], ratio[sel]))
    return out


def _mutual(f1: Features, f2: Features, groups1: list[np.ndarray], i: np.ndarray, j: np.ndarray, cfg: MatchConfig) -> np.ndarray:
    """Reverse check: the nearest f1 keypoint (in the same f1 view) of each candidate's f2
    keypoint must lie at the candidate's location.  Returns a keep mask."""
    group_of_1 = np.zeros(len(f1), np.int64)
    for gi, g in enumerate(groups1):
        group_of_1[g] = gi
    keep = np.zeros(len(i), bool)
    gi_of = group_of_1[i]
    for gi, g1 in enumerate(groups1):
        sel = np.nonzero(gi_of == gi)[0]
        if len(sel) == 0:
            continue
        rev_idx, _ = NNIndex(f1.desc[g1], cfg.index, cfg.k, expected_queries=len(sel)).query(f2.desc[j[sel]], 1)
        rev = g1[rev_idx[:, 0]]
        keep[sel] = np.linalg.norm(f1.xy[rev] - f1.xy[i[sel]], axis=1) <= cfg.distinct_px
    return keep


def _pairs_in_boxes(query_xy: np.ndarray, ref_xy: np.ndarray, x_lo: np.ndarray, x_hi: np.ndarray, y_lo: np.ndarray, y_hi: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Candidate pairs ``(q, r)`` with ref point inside the query's box ``[x_lo, x_hi] x [y_lo, y_hi]``.

    Ref points are bucketed in vertical strips of width ``cell`` and sorted by y
    inside each strip; each query scans the strips its box overlaps.
    """
    nq, nr = len(query_xy), len(ref_xy)
    if nq == 0 or nr == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cell = max(float(cell), 1.0)
    rx = ref_xy[:, 0].astype(np.float64)
    ry = ref_xy[:, 1].astype(np.float64)
    x0 = min(rx.min(), float(np.min(x_lo)))
    strip = np.floor((rx - x0) / cell).astype(np.int64)
    ymin = min(ry.min(), float(np.min(y_lo))) - 1.0
    yspan = max(ry.max(), float(np.max(y_hi))) - ymin + 2.0
    key = strip * yspan + (ry - ymin)
    order = np.argsort(key, kind="stable")
    sk = key[order]
    s_lo = np.floor((np.asarray(x_lo, np.float64) - x0) / cell).astype(np.int64)
    s_hi = np.floor((np.asarray(x_hi, np.float64) - x0) / cell).astype(np.int64)
    s_lo = np.maximum(s_lo, 0)
    s_hi = np.minimum(s_hi, int(strip.max()))
    qs, rs = [], []
    max_strips = int(np.max(s_hi - s_lo, initial=-1)) + 1
    for off in range(max(max_strips, 0)):
        s = s_lo + off
        valid = s <= s_hi
        if not valid.any():
            continue
        qv = np.nonzero(valid)[0]
        sv = s[qv]
        lo = np.searchsorted(sk, sv * yspan + (np.asarray(y_lo)[qv] - ymin), "left")
        hi = np.searchsorted(sk, sv * yspan + (np.asarray(y_hi)[qv] - ymin), "right")
        cnt = hi - lo
        total = int(cnt.sum())
        if total == 0:
            continue
        q = np.repeat(qv, cnt)
        start = np.repeat(lo - (np.cumsum(cnt) - cnt), cnt)
        r = order[start + np.arange(total)]
        qs.append(q)
        rs.append(r)
    if not qs:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    q = np.concatenate(qs)
    r = np.concatenate(rs)
    inside = (rx[r] >= x_lo[q]) & (rx[r] <= x_hi[q]) & (ry[r] >= y_lo[q]) & (ry[r] <= y_hi[q])
    return q[inside], r[inside]


def _pair_distances(d1: np.ndarray, d2: np.ndarray, q: np.ndarray, r: np.ndarray, chunk: int = 65536) -> np.ndarray:
    out = np.empty(len(q), np.float32)
    n1 = np.einsum("ij,ij->i", d1, d1)
    n2 = np.einsum("ij,ij->i", d2, d2)
    for s in range(0, len(q), chunk):
        qq, rr = q[s:s + chunk], r[s:s + chunk]
        dot = np.einsum("ij,ij->i", d1[qq], d2[rr])
        out[s:s + chunk] = np.sqrt(np.maximum(n1[qq] + n2[rr] - 2.0 * dot, 0.0))
    return out


def _match_pairs(q: np.ndarray, r: np.ndarray, dist: np.ndarray, nq: int, nr: int, xy_q: np.ndarray, xy_r: np.ndarray, cfg: MatchConfig) -> Matches:
    """Ratio test (best vs best at another location), mutual check and duplicate collapse on candidate pairs."""
    if len(q) == 0:
        return Matches.empty()
    order = np.lexsort((dist, q))  # by query, then distance
    q, r, dist = q[order], r[order], dist[order]
    starts = np.r_[0, np.nonzero(np.diff(q))[0] + 1]
    counts = np.diff(np.r_[starts, len(q)])
    best_r = r[starts]
    # best candidate of the same query at another location
    best_xy = np.repeat(xy_r[best_r], counts, axis=0)
    far = np.linalg.norm(xy_r[r] - best_xy, axis=1) > cfg.distinct_px
    second = np.minimum.reduceat(np.where(far, dist, np.inf), starts)
    best_q_of_r = np.full(nr, -1, np.int64)
    if cfg.mutual:
        # best query (location) for every ref point among the same candidate pairs
        order_r = np.lexsort((dist, r))
        r_sorted = r[order_r]
        rs = np.r_[0, np.nonzero(np.diff(r_sorted))[0] + 1]
        best_q_of_r[r_sorted[rs]] = q[order_r][rs]
    return _accept(q[starts], best_r, dist[starts], second, best_q_of_r, xy_q, xy_r, cfg)


def _accept(qi: np.ndarray, best_r: np.ndarray, best_d: np.ndarray, second: np.ndarray, best_q_of_r: np.ndarray,
            xy_q: np.ndarray, xy_r: np.ndarray, cfg: MatchConfig) -> Matches:
    """Matches of queries ``qi`` (ascending) to their nearest candidates ``best_r``: ratio test against
    the nearest candidate at another location (``second``), mutual check (``best_q_of_r``: the
    nearest query of every ref point, -1 = none) and duplicate collapse."""
    ok = best_d < cfg.ratio * second
    if cfg.max_distance > 0:
        ok &= best_d <= cfg.max_distance
    if cfg.mutual:
        back = best_q_of_r[best_r]
        ok &= back >= 0
        back = np.where(back >= 0, back, qi)
        ok &= np.linalg.norm(xy_q[back] - xy_q[qi], axis=1) <= cfg.distinct_px
    i, j, d = qi[ok], best_r[ok], best_d[ok]
    if len(i) > 1:
        keep = collapse_duplicates(xy_q[i], xy_r[j], d, cfg.distinct_px)
        i, j, d = i[keep], j[keep], d[keep]
    return Matches(np.stack([i, j], axis=1).astype(np.int32), d.astype(np.float32))


def match_epipolar_rectified(
    xy_left_rect: np.ndarray,
    xy_right_rect: np.ndarray,
    desc_l: np.ndarray,
    desc_r: np.ndarray,
    max_dy: float = 1.0,
    min_disp: float = 0.0,
    max_disp: float = 1e9,
    cfg: MatchConfig = MatchConfig(),
) -> Matches:
    """Match rectified stereo keypoints: ``|y_l - y_r| <= max_dy`` and ``min_disp <= x_l - x_r <= max_disp``.

    Disparity must be positive (``x_l > x_r``) even when ``min_disp`` is 0.
    Candidate pairs come from a banded search (right points sorted by row), so
    the cost grows with the number of points per band, not with ``n_l * n_r``.
    """
    xl = np.asarray(xy_left_rect, np.float64).reshape(-1, 2)
    xr = np.asarray(xy_right_rect, np.float64).reshape(-1, 2)
    dl = np.ascontiguousarray(desc_l, np.float32)
    dr = np.ascontiguousarray(desc_r, np.float32)
    if len(xl) != len(dl) or len(xr) != len(dr):
        raise ConfigError("match_epipolar_rectified: point and descriptor counts differ")
    if max_dy < 0 or max_disp < min_disp:
        raise ConfigError(f"match_epipolar_rectified: bad band max_dy={max_dy}, disparity [{min_disp}, {max_disp}]")
    if len(xl) == 0 or len(xr) == 0:
        return Matches.empty()
    vl = np.nonzero(np.isfinite(xl).all(axis=1))[0]
    vr = np.nonzero(np.isfinite(xr).all(axis=1))[0]
    if len(vl) == 0 or len(vr) == 0:
        return Matches.empty()
    span = float(np.ptp(xr[vr, 0])) + float(np.ptp(xl[vl, 0])) + 1.0
    hi_disp = min(max_disp, span + max(0.0, min_disp))
    ql = xl[vl]
    q, r = _pairs_in_boxes(ql, xr[vr], ql[:, 0] - hi_disp, ql[:, 0] - max(min_disp, 0.0), ql[:, 1] - max_dy, ql[:, 1] + max_dy, cell=span + hi_disp + 1.0)
    q, r = vl[q], vr[r]
    disp = xl[q, 0] - xr[r, 0]
    keep = (disp > 0) & (disp >= min_disp) & (disp <= max_disp)
    q, r = q[keep], r[keep]
    dist = _pair_distances(dl, dr, q, r)
    return _match_pairs(q, r, dist, len(xl), len(xr), xl, xr, cfg)


def match_guided(f1: Features, f2: Features, predicted_xy2: np.ndarray, radius_px: float, cfg: MatchConfig = MatchConfig()) -> Matches:
    """Match each ``f1`` keypoint only to ``f2`` keypoints within ``radius_px`` of its predicted position.

    ``predicted_xy2`` is (N1, 2) in the second image; rows with NaN are skipped.  The nearest
    candidates come from :func:`~stereopath.device.core.radius_search.radius_nearest` (cell-batched
    products); then the ratio test, mutual check and duplicate collapse of :func:`match_epipolar_rectified`.
    """
    pred = np.asarray(predicted_xy2, np.float64).reshape(-1, 2)
    if len(pred) != len(f1):
        raise ConfigError(f"match_guided: {len(pred)} predictions for {len(f1)} features")
    if radius_px <= 0:
        raise ConfigError(f"match_guided: radius_px must be positive, got {radius_px}")
    if len(f1) == 0 or len(f2) == 0:
        return Matches.empty()
    vq = np.nonzero(np.isfinite(pred).all(axis=1))[0]
    if len(vq) == 0:
        return Matches.empty()
    p = pred[vq]
    xy_q, xy_r = f1.xy.astype(np.float64), f2.xy.astype(np.float64)
    nn = radius_nearest(p, f1.desc[vq], xy_r, f2.desc, radius_px, cfg.distinct_px, strip_rank(xy_r, p, radius_px))
    has = nn.best >= 0
    best_q_of_r = np.where(nn.ref_best >= 0, vq[nn.ref_best], -1)
    return _accept(vq[has], nn.best[has], nn.best_dist[has], nn.second_dist[has], best_q_of_r, xy_q, xy_r, cfg)
