"""Stereo correspondences refined with a slanted window (offline, sub-pixel, unbiased on slanted surfaces).

A translational window (KLT) measures the disparity at its *gradient-energy centroid*, not its centre;
on a surface seen at a slant perspective packs more texture into the far side, so near points come out
too far and the path too long, an error a constant disparity offset cannot model.
:func:`refine_slanted` starts from the translational match and fits, per point, the right-image position
as an affine function of the window offset in x plus a vertical shift, brightness gain and offset free,
by inverse-compositional Gauss-Newton (the template's Jacobian computed once; bilinear sampling with
exact weights).  Pure NumPy and OpenCV on arrays: grey images ``(h, w)``, pixels ``(n, 2)``.
See docs/architecture.md, "Reprocessing".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# points per block: a block's windows stay in the CPU caches
BLOCK = 1024


def window_samples(img: np.ndarray, xy: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``(2 half + 1)^2`` windows of ``img`` around the sub-pixel points ``xy`` and their x and y
    derivatives (central differences), each ``(n, m)`` float32, bilinear with exact weights.  Every
    sample of one window shares the point's fractional offset, so one integer patch per point (a
    pixel wider than the window) and four weights give them all."""
    import cv2

    n, side = len(xy), 2 * half + 4
    ix, iy = np.floor(xy[:, 0]), np.floor(xy[:, 1])
    fx = (xy[:, 0] - ix).astype(np.float32)[:, None, None]
    fy = (xy[:, 1] - iy).astype(np.float32)[:, None, None]
    off = np.arange(-half - 1, half + 3, dtype=np.float32)
    mx = np.broadcast_to((ix.astype(np.float32)[:, None, None] + off[None, None, :]), (n, side, side))
    my = np.broadcast_to((iy.astype(np.float32)[:, None, None] + off[None, :, None]), (n, side, side))
    P = cv2.remap(np.asarray(img, np.float32), np.ascontiguousarray(mx).reshape(n, -1),
                  np.ascontiguousarray(my).reshape(n, -1), cv2.INTER_NEAREST,
                  borderMode=cv2.BORDER_REPLICATE).reshape(n, side, side)
    top = P[:, :-1, :-1] + fx * (P[:, :-1, 1:] - P[:, :-1, :-1])
    bot = P[:, 1:, :-1] + fx * (P[:, 1:, 1:] - P[:, 1:, :-1])
    grid = top + fy * (bot - top)  # samples at offsets -half-1 .. half+1
    T = grid[:, 1:-1, 1:-1]
    gx = 0.5 * (grid[:, 1:-1, 2:] - grid[:, 1:-1, :-2])
    gy = 0.5 * (grid[:, 2:, 1:-1] - grid[:, :-2, 1:-1])
    return tuple(np.ascontiguousarray(v).reshape(n, -1) for v in (T, gx, gy))


def _corners(img: np.ndarray) -> np.ndarray:
    """``(h, w, 4)`` float32: each pixel with its right, lower and lower-right neighbours (edges repeated)."""
    f = np.pad(np.asarray(img, np.float32), ((0, 1), (0, 1)), mode="edge")
    return np.ascontiguousarray(np.stack([f[:-1, :-1], f[:-1, 1:], f[1:, :-1], f[1:, 1:]], axis=2))


def _warped(corners: np.ndarray, x: np.ndarray, row0: np.ndarray, fy: np.ndarray) -> np.ndarray:
    """Bilinear samples at ``(x, row0)`` plus the fraction ``fy`` (a row offset shared by each point's
    window), with exact weights: ``cv2.remap``'s own bilinear mode rounds the position to 1/32 px,
    which would stall the Gauss-Newton steps below that size, so it only fetches the neighbours."""
    import cv2

    x0 = np.floor(x)
    fx = x - x0
    c = cv2.remap(corners, x0, row0, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    top = c[..., 0] + fx * (c[..., 1] - c[..., 0])
    bot = c[..., 2] + fx * (c[..., 3] - c[..., 2])
    bot -= top
    bot *= fy
    return top + bot


@dataclass(frozen=True)
class SlantedFit:
    """The slanted window's fit: half its side (pixels), Gauss-Newton iterations, and the limits of a
    refined point (see :func:`refine_slanted`)."""

    half: int = 10
    iterations: int = 12
    max_shift_px: float = 1.0
    max_slant: float = 0.5
    tol_px: float = 0.02


def refine_slanted(left: np.ndarray, right: np.ndarray, xy_left: np.ndarray, xy_right: np.ndarray,
                   fit: SlantedFit = SlantedFit()) -> tuple[np.ndarray, np.ndarray]:
    """Right-image pixels of ``xy_left`` refined with a slanted window around the match ``xy_right``.

    Returns ``(xy_right_refined (n, 2) float64, ok (n,) bool)``.  A point is not refined (``ok``
    False, its input position returned) when the window has no texture, the fit does not settle
    within ``fit.tol_px``, it moves more than ``fit.max_shift_px`` from the input, or needs a slant
    beyond ``fit.max_slant`` (pixels of disparity per pixel: the window then straddles a depth edge
    rather than a surface).
    """
    xy_left = np.asarray(xy_left, np.float64).reshape(-1, 2)
    xy_right = np.asarray(xy_right, np.float64).reshape(-1, 2)
    n = len(xy_left)
    if n == 0:
        return xy_right.copy(), np.zeros(0, bool)
    import cv2

    L = np.asarray(left, np.float32)
    R = _corners(right)
    blocks = [slice(i, min(i + BLOCK, n)) for i in range(0, n, BLOCK)]
    def one(b: slice) -> tuple[np.ndarray, np.ndarray]:
        return _refine_block(L, R, xy_left[b], xy_right[b], fit)

    workers = max(1, min(cv2.getNumThreads(), len(blocks)))  # the threads OpenCV may use (a fleet task sets it)
    if workers == 1:
        parts = [one(b) for b in blocks]
    else:  # NumPy and OpenCV release the GIL in the array work; blocks are independent
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(workers) as ex:
            parts = list(ex.map(one, blocks))
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _refine_block(L: np.ndarray, R: np.ndarray, xy_left: np.ndarray, xy_right: np.ndarray, fit: SlantedFit
                  ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`refine_slanted` on one block of points; ``L`` the left image (float32), ``R`` the right
    one's :func:`_corners`."""
    half, iterations, max_shift_px, max_slant, tol_px = fit.half, fit.iterations, fit.max_shift_px, fit.max_slant, fit.tol_px
    n = len(xy_left)
    dy, dx = np.mgrid[-half:half + 1, -half:half + 1]
    dx = dx.ravel().astype(np.float32)
    dy = dy.ravel().astype(np.float32)
    # inverse compositional Gauss-Newton: the Jacobian and its normal matrix come from the template
    T, gx, gy = window_samples(L, xy_left, half)  # (n, m) each
    T -= T.mean(axis=1, keepdims=True)
    t_norm = np.sqrt(np.einsum("nm,nm->n", T, T))
    J = np.stack([gx, gy, gx * dx[None], gx * dy[None]], axis=1)  # d/d(tx, ty, slant x, slant y)
    J -= J.mean(axis=2, keepdims=True)  # the brightness offset is free
    H = np.matmul(J, J.transpose(0, 2, 1)).astype(np.float64)
    det = np.linalg.det(H)
    ok = np.isfinite(det) & (det > 1e-9 * np.trace(H, axis1=1, axis2=2) ** 4) & (t_norm > 0)
    Hinv = np.zeros_like(H)
    Hinv[ok] = np.linalg.inv(H[ok])
    a11, a12 = np.ones(n), np.zeros(n)  # right x = c + a11 dx + a12 dy + tx, right y = c + dy + ty
    t = np.zeros((n, 2))
    step = np.full(n, np.inf)
    act = np.arange(n)  # points still moving (a point without texture has Hinv = 0: it stops at once)
    for _ in range(iterations):
        if len(act) == 0:
            break
        sub = slice(None) if len(act) == n else act  # no copies while every point still moves
        c = xy_right[act] + t[act]
        xr = a11[act].astype(np.float32)[:, None] * dx[None] + a12[act].astype(np.float32)[:, None] * dy[None]
        xr += c[:, :1].astype(np.float32)
        iy = np.floor(c[:, 1:2])  # the window's rows share the point's fractional row
        Iw = _warped(R, xr, (iy.astype(np.float32) + dy[None]), (c[:, 1:2] - iy).astype(np.float32))
        Iw -= Iw.mean(axis=1, keepdims=True)
        i_norm = np.sqrt(np.einsum("nm,nm->n", Iw, Iw))
        e = Iw * (t_norm[act] / np.maximum(i_norm, 1e-6))[:, None].astype(np.float32) - T[sub]  # gain-free
        g = np.matmul(J[sub], e[:, :, None])[:, :, 0].astype(np.float64)
        d = np.einsum("nij,nj->ni", Hinv[sub], g)  # increment of (tx, ty, slant x, slant y) in the template
        # compose with the inverse increment: A <- A M^-1, t <- t - A M^-1 t_d
        sc = 1.0 / np.maximum(1.0 + d[:, 2], 1e-3)
        na11, na12 = a11[act] * sc, a12[act] - a11[act] * d[:, 3] * sc
        t[act, 0] -= na11 * d[:, 0] + na12 * d[:, 1]
        t[act, 1] -= d[:, 1]
        a11[act], a12[act] = na11, na12
        step[act] = np.hypot(d[:, 0], d[:, 1])
        act = act[(step[act] >= tol_px / 2) & (np.abs(t[act]).max(axis=1) < 4 * max_shift_px)]
    ok &= np.isfinite(t).all(axis=1) & (step < tol_px)
    ok &= np.hypot(t[:, 0], t[:, 1]) <= max_shift_px
    ok &= (np.abs(a11 - 1.0) <= max_slant) & (np.abs(a12) <= max_slant)
    out = xy_right.copy()
    out[ok] += t[ok]
    return out, ok
