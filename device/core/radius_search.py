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

__all__ = ["RadiusNearest", "radius_nearest"]


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


def _cells(p: np.ndarray, rxy: np.ndarray, radius: float, cell_radii: float
           ) -> tuple[np.ndarray, np.ndarray, int] | None:
    """Integer cell keys of the queries near the references (others: -1) and of the references,
    and the key stride of one cell row; None when no query is near."""
    lo = rxy.min(axis=0) - radius - 1.0
    hi = rxy.max(axis=0) + radius + 1.0
    with np.errstate(invalid="ignore"):
        near = np.all((p >= lo) & (p <= hi), axis=1)  # False for NaN predictions
    if not near.any():
        return None
    size = max(cell_radii * radius, radius + 1.0)  # a candidate is never more than one cell away
    cq = np.floor((p[near] - lo) / size).astype(np.int64) + 1
    cr = np.floor((rxy - lo) / size).astype(np.int64) + 1
    stride = int(max(cq[:, 0].max(), cr[:, 0].max())) + 2
    qkey = np.full(len(p), -1, np.int64)
    qkey[near] = cq[:, 1] * stride + cq[:, 0]
    return qkey, cr[:, 1] * stride + cr[:, 0], stride


def radius_nearest(pred: np.ndarray, desc_q: np.ndarray, ref_xy: np.ndarray, desc_ref: np.ndarray,
                   radius: float, distinct_px: float, ref_rank: np.ndarray | None = None,
                   cell_radii: float = 2.0) -> RadiusNearest:
    """Nearest candidates of every query among the reference keypoints within ``radius`` px of
    its predicted position ``pred`` (see the module doc).  NaN predictions have no candidate."""
    p = np.asarray(pred, np.float64).reshape(-1, 2)
    rxy = np.asarray(ref_xy, np.float64).reshape(-1, 2)
    nq, nr = len(p), len(rxy)
    out = _empty(nq, nr)
    if nq == 0 or nr == 0:
        return out
    cells = _cells(p, rxy, float(radius), cell_radii)
    if cells is None:
        return out
    qkey, rkey, stride = cells
    rank = np.arange(nr) if ref_rank is None else np.asarray(ref_rank, np.int64)
    rorder = np.lexsort((rank, rkey))  # by cell, then rank
    rsorted = rkey[rorder]
    qsel = np.flatnonzero(qkey >= 0)
    qorder = qsel[np.argsort(qkey[qsel], kind="stable")]  # by cell, then index
    keys, starts = np.unique(qkey[qorder], return_index=True)
    bounds = np.r_[starts, len(qorder)]
    spans = [(np.searchsorted(rsorted, keys + dy * stride - 1, "left"),
              np.searchsorted(rsorted, keys + dy * stride + 1, "right")) for dy in (-1, 0, 1)]
    dq = np.ascontiguousarray(desc_q, np.float32)
    dr = np.ascontiguousarray(desc_ref, np.float32)
    norms = (np.einsum("ij,ij->i", dq, dq), np.einsum("ij,ij->i", dr, dr))
    ref_d = np.full(nr, np.inf, np.float32)
    for c in range(len(keys)):
        rs = np.concatenate([rorder[a[c]:b[c]] for a, b in spans])
        if len(rs) == 0:
            continue
        rs = rs[np.argsort(rank[rs], kind="stable")]
        _cell(qorder[bounds[c]:bounds[c + 1]], rs, p, rxy, dq, dr, norms, float(radius), distinct_px, out, ref_d)
    return out


def _cell(qs: np.ndarray, rs: np.ndarray, p: np.ndarray, rxy: np.ndarray, dq: np.ndarray, dr: np.ndarray,
          norms: tuple[np.ndarray, np.ndarray], radius: float, distinct_px: float, out: RadiusNearest,
          ref_d: np.ndarray) -> None:
    """One cell: queries ``qs`` (ascending) against references ``rs`` (ascending rank); updates ``out``
    and ``ref_d`` (the distance of ``out.ref_best``) in place."""
    P, R = p[qs], rxy[rs]
    px, py, rx, ry = P[:, :1], P[:, 1:], R[None, :, 0], R[None, :, 1]
    cand = (rx >= px - radius) & (rx <= px + radius) & (ry >= py - radius) & (ry <= py + radius)
    dx, dy = rx - px, ry - py
    cand &= np.sqrt(dx * dx + dy * dy) <= radius
    if not cand.any():
        return
    g = dq[qs] @ dr[rs].T
    d2 = norms[0][qs][:, None] + norms[1][rs][None, :] - 2.0 * g
    dist = np.where(cand, np.sqrt(np.maximum(d2, 0.0)), np.float32(np.inf))
    rows = np.arange(len(qs))
    b = np.argmin(dist, axis=1)  # first minimum: the lowest rank among equals
    bd = dist[rows, b]
    has = np.isfinite(bd)
    bx, by = R[b, :1], R[b, 1:]
    fx, fy = rx - bx, ry - by
    far = np.sqrt(fx * fx + fy * fy) > distinct_px
    second = np.where(far, dist, np.float32(np.inf)).min(axis=1)
    q = qs[has]
    out.best[q], out.best_dist[q], out.second_dist[q] = rs[b[has]], bd[has], second[has]
    c = np.argmin(dist, axis=0)  # first minimum: the lowest query index among equals
    cd = dist[c, np.arange(len(rs))]
    cq = qs[c]
    cur_d, cur_q = ref_d[rs], out.ref_best[rs]
    upd = np.isfinite(cd) & ((cd < cur_d) | ((cd == cur_d) & (cq < cur_q)))
    ref_d[rs[upd]] = cd[upd]
    out.ref_best[rs[upd]] = cq[upd]
