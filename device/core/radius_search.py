"""Nearest descriptors among the keypoints within a pixel radius of predicted positions.  Pure compute.

The search behind guided matching (:func:`stereopath.device.core.matching.match_guided`): each query
has a predicted position and a descriptor; its candidates are the reference keypoints inside the
circle of ``radius`` px around the prediction (and inside the circle's bounding box, tested as
well so that points on the border count exactly as the predicate says).  Returned per query:
the nearest candidate (descriptor distance), the nearest candidate at another location (farther
than ``distinct_px`` from the nearest one, for Lowe's ratio test), and per reference keypoint
the nearest query that has it as a candidate (for the mutual check).

The queries are grouped in square cells of ``cell_radii`` radii; the queries of a cell are
compared with the reference keypoints of the 3 x 3 cells around it in one matrix product and the
result is masked to each query's circle.  The cost is a few dense products per cell instead of a
gather of two descriptors per candidate pair.

Distances are ``sqrt(|a|^2 + |b|^2 - 2 a.b)`` in float32.  For integer-valued descriptors (SIFT's
are 0..255 with squared norms far below 2**24) every term is exact whatever the summation order,
so the result does not depend on the grouping.  Equally distant candidates are resolved by
``ref_rank`` (lowest first; default the index) and equally distant queries by the lowest index.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RadiusNearest", "radius_nearest", "strip_rank"]


@dataclass(frozen=True, eq=False)
class RadiusNearest:
    """Result of :func:`radius_nearest` (``-1`` / ``inf`` where there is no candidate)."""

    best: np.ndarray  # (Nq,) int64: index of the query's nearest candidate
    best_dist: np.ndarray  # (Nq,) float32: its descriptor distance
    second_dist: np.ndarray  # (Nq,) float32: distance of the nearest candidate farther than distinct_px from it
    ref_best: np.ndarray  # (Nr,) int64: the nearest query having this reference keypoint as a candidate


def _empty(nq: int, nr: int) -> RadiusNearest:
    return RadiusNearest(np.full(nq, -1, np.int64), np.full(nq, np.inf, np.float32),
                         np.full(nq, np.inf, np.float32), np.full(nr, -1, np.int64))


def _grid(p: np.ndarray, rxy: np.ndarray, radius: float, k: int) -> tuple[np.ndarray, np.ndarray, int] | None:
    """Integer keys of square cells of ``radius / k`` px (a candidate is at most ``k`` cells away in
    x and y) of the queries near the references (others: -1) and of the references, and the key
    stride of one cell row; None when no query is near."""
    lo = rxy.min(axis=0) - radius - 1.0
    hi = rxy.max(axis=0) + radius + 1.0
    with np.errstate(invalid="ignore"):
        near = np.all((p >= lo) & (p <= hi), axis=1)  # False for NaN predictions
    if not near.any():
        return None
    size = radius / k + 1e-6
    cq = np.floor((p[near] - lo) / size).astype(np.int64) + k + 1
    cr = np.floor((rxy - lo) / size).astype(np.int64) + k + 1
    stride = int(max(cq[:, 0].max(), cr[:, 0].max())) + k + 2
    qkey = np.full(len(p), -1, np.int64)
    qkey[near] = cq[:, 1] * stride + cq[:, 0]
    return qkey, cr[:, 1] * stride + cr[:, 0], stride


def _windows(keys: np.ndarray, rsorted: np.ndarray, stride: int, k: int) -> np.ndarray:
    """(cells, M) positions in ``rsorted`` (the references' sorted cell keys) of the references in the
    (2k+1)^2 cells around each cell ``keys``, padded with ``len(rsorted)``."""
    rows = [(np.searchsorted(rsorted, keys + dy * stride - k, "left"),
             np.searchsorted(rsorted, keys + dy * stride + k, "right")) for dy in range(-k, k + 1)]
    counts = [hi - lo for lo, hi in rows]
    total = np.sum(counts, axis=0)
    win = np.full((len(keys), max(int(total.max()), 1)), len(rsorted), np.int64)
    filled = np.zeros(len(keys), np.int64)
    for (lo, _), cnt in zip(rows, counts):
        n = int(cnt.sum())
        if n:
            cell = np.repeat(np.arange(len(keys)), cnt)
            within = np.arange(n) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            win[cell, filled[cell] + within] = lo[cell] + within
        filled += cnt
    return win


def _pow2(n: np.ndarray, least: int) -> np.ndarray:
    return np.maximum(least, 1 << np.ceil(np.log2(np.maximum(n, 1))).astype(np.int64))


def radius_nearest(pred: np.ndarray, desc_q: np.ndarray, ref_xy: np.ndarray, desc_ref: np.ndarray,
                   radius: float, distinct_px: float, ref_rank: np.ndarray | None = None,
                   cells_per_radius: int = 2) -> RadiusNearest:
    """Nearest candidates of every query among the reference keypoints within ``radius`` px of
    its predicted position ``pred`` (see the module doc).  NaN predictions have no candidate."""
    p = np.asarray(pred, np.float64).reshape(-1, 2)
    rxy = np.asarray(ref_xy, np.float64).reshape(-1, 2)
    nq, nr = len(p), len(rxy)
    out = _empty(nq, nr)
    grid = _grid(p, rxy, float(radius), cells_per_radius) if nq and nr else None
    if grid is None:
        return out
    qkey, rkey, stride = grid
    qsel = np.flatnonzero(qkey >= 0)
    qorder = qsel[np.argsort(qkey[qsel], kind="stable")]  # by cell, then index
    rorder = np.argsort(rkey, kind="stable")
    keys, qstart, qcount = np.unique(qkey[qorder], return_index=True, return_counts=True)
    # cells' queries and window references as positions in qorder / rorder (both padded): the
    # arrays are gathered in those orders, so a window reads a few runs of consecutive rows
    qmat = np.full((len(keys), int(qcount.max())), len(qorder), np.int64)
    qmat[np.repeat(np.arange(len(keys)), qcount), np.arange(len(qorder)) - np.repeat(qstart, qcount)] = np.arange(len(qorder))
    win = _windows(keys, rkey[rorder], stride, cells_per_radius)
    wcount = (win < nr).sum(axis=1)
    # cells of similar size together: one batch of products per (queries, references) size class
    qb, mb = _pow2(qcount, 1), _pow2(wcount, 8)
    cls = qb * (int(mb.max()) + 1) + mb
    order = np.argsort(cls, kind="stable")
    bounds = np.flatnonzero(np.diff(cls[order])) + 1
    e = _Padded(p[qorder], rxy[rorder], np.asarray(desc_q)[qorder], np.asarray(desc_ref)[rorder])
    found = []
    for same in np.split(order, bounds):
        q, m = int(qb[same[0]]), int(mb[same[0]])
        pairs = _candidates(qmat[same, :q], win[same, :m], e, float(radius))
        if pairs is not None:
            found.append(pairs)
    if found:
        q, r, dist = (np.concatenate([f[i] for f in found]) for i in range(3))
        _reduce(qorder[q], rorder[r], dist, rxy, ref_rank, distinct_px, out)
    return out


class _Padded:
    """Positions with one padding row (NaN: never a candidate); descriptors and their squared norms."""

    def __init__(self, p, rxy, desc_q, desc_ref) -> None:
        nan = np.full((1, 2), np.nan)
        self.p, self.rxy = np.vstack([p, nan]), np.vstack([rxy, nan])
        self.dq = np.ascontiguousarray(desc_q, np.float32).reshape(len(p), -1)
        self.dr = np.ascontiguousarray(desc_ref, np.float32).reshape(len(rxy), -1)
        self.nq2 = np.einsum("ij,ij->i", self.dq, self.dq)
        self.nr2 = np.einsum("ij,ij->i", self.dr, self.dr)


def _candidates(qi: np.ndarray, ri: np.ndarray, e: _Padded, radius: float) -> tuple[np.ndarray, ...] | None:
    """Candidate pairs (query, reference, distance) of cells with queries ``qi`` (cells, Q) and window
    references ``ri`` (cells, M), both padded with the padding row; grouped by query."""
    P, R = e.p[qi], e.rxy[ri]
    px, py = P[:, :, 0, None], P[:, :, 1, None]
    rx, ry = R[:, None, :, 0], R[:, None, :, 1]
    cand = (rx >= px - radius) & (rx <= px + radius) & (ry >= py - radius) & (ry <= py + radius)
    dx, dy = rx - px, ry - py
    cand &= np.sqrt(dx * dx + dy * dy) <= radius
    cell, qs, rs = np.nonzero(cand)  # by cell, then query: each query's pairs together
    if len(cell) == 0:
        return None
    qi_d, ri_d = np.minimum(qi, len(e.dq) - 1), np.minimum(ri, len(e.dr) - 1)  # padding: any row, masked out
    g = np.matmul(e.dq[qi_d], e.dr[ri_d].transpose(0, 2, 1))
    q, r = qi[cell, qs], ri[cell, rs]
    d2 = e.nq2[q] + e.nr2[r] - 2.0 * g[cell, qs, rs]
    return q, r, np.sqrt(np.maximum(d2, 0.0))


def _reduce(q: np.ndarray, r: np.ndarray, dist: np.ndarray, rxy: np.ndarray, ref_rank: np.ndarray | None,
            distinct_px: float, out: RadiusNearest) -> None:
    """``out`` from the candidate pairs (grouped by query)."""
    starts = np.flatnonzero(np.r_[True, q[1:] != q[:-1]])
    counts = np.diff(np.r_[starts, len(q)])
    nearest = np.minimum.reduceat(dist, starts)
    if ref_rank is None:
        rank, by_rank = r, np.arange(len(rxy))
    else:
        ref_rank = np.asarray(ref_rank, np.int64)
        rank, by_rank = ref_rank[r], np.argsort(ref_rank)
    tie = np.where(dist == np.repeat(nearest, counts), rank, np.iinfo(np.int64).max)
    best = by_rank[np.minimum.reduceat(tie, starts)]  # the lowest rank among the nearest
    far = np.linalg.norm(rxy[r] - np.repeat(rxy[best], counts, axis=0), axis=1) > distinct_px
    qi = q[starts]
    out.best[qi], out.best_dist[qi] = best, nearest
    out.second_dist[qi] = np.minimum.reduceat(np.where(far, dist, np.float32(np.inf)), starts)
    # each reference's nearest query, the lowest index among equals (distances >= 0: bit order = value order)
    key = (dist.astype(np.float32).view(np.int32).astype(np.int64) << 32) | q
    top = np.full(len(out.ref_best), np.iinfo(np.int64).max)
    np.minimum.at(top, r, key)
    hit = top < np.iinfo(np.int64).max
    out.ref_best[hit] = top[hit] & 0xFFFFFFFF


def strip_rank(xy_r: np.ndarray, p: np.ndarray, radius_px: float) -> np.ndarray:
    """A tie order for :func:`radius_nearest` (``ref_rank``): the rank of each reference point
    ``xy_r`` in a scan of vertical strips ``radius_px`` wide from the leftmost edge of the search
    boxes around the predictions ``p``, by y inside a strip, then by index.  This is the order in
    which guided matching's earlier pair search met the candidates; resolving equal distances in
    it keeps the matches what they were."""
    rx, ry = xy_r[:, 0], xy_r[:, 1]
    cell = max(float(radius_px), 1.0)
    x0 = min(rx.min(), float(np.min(p[:, 0] - radius_px)))
    strip = np.floor((rx - x0) / cell).astype(np.int64)
    ymin = min(ry.min(), float(np.min(p[:, 1] - radius_px))) - 1.0
    yspan = max(ry.max(), float(np.max(p[:, 1] + radius_px))) - ymin + 2.0
    rank = np.empty(len(rx), np.int64)
    rank[np.argsort(strip * yspan + (ry - ymin), kind="stable")] = np.arange(len(rx))
    return rank
