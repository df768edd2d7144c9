"""Stereo correspondences refined with a slanted window (offline, sub-pixel, unbiased on slanted surfaces).

A translational window (KLT) assumes the disparity is constant over the window.  On a surface
seen at a slant the disparity is an affine function of the pixel, ``d(x) = d0 + a dx + b dy``, and
the translational least-squares estimate is the disparity at the window's *gradient-energy
centroid*, not at its centre.  Perspective compresses the texture of a receding surface, so the
far side of a window holds more gradient energy than the near side and the centroid leans to the
far side: the disparity comes out systematically too small (on the simulated table scan about
+0.015 px in the right image at 0.5-1.2 m, i.e. a path 4e-4 too long after bundle adjustment, the
same order as the table top's share of near points).

:func:`refine_slanted` starts from the translational match and fits, per point, the right-image
position as an affine function of the window offset in x (the slant ``a, b``) plus a vertical
shift and a gain and offset of the brightness (Gauss-Newton on the window's pixels), and returns
the right-image position of the window's centre under that model.  The vertical mapping stays a
shift: the two cameras' rows differ only by the small rectifying rotation.  Pure NumPy; the images
are grey ``(h, w)`` arrays, the pixels ``(n, 2)``.
"""

from __future__ import annotations

import numpy as np


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear samples of ``img`` at ``(x, y)`` with their x and y derivatives (of the bilinear
    surface itself, so that Gauss-Newton sees the function it minimises)."""
    h, w = img.shape
    x = np.clip(x, 0.0, w - 1.001)
    y = np.clip(y, 0.0, h - 1.001)
    x0 = x.astype(np.int32)
    y0 = y.astype(np.int32)
    fx = (x - x0).astype(np.float32)
    fy = (y - y0).astype(np.float32)
    i = y0 * w + x0
    flat = img.ravel()
    a = flat[i]
    b = flat[i + 1]
    c = flat[i + w]
    d = flat[i + w + 1]
    top = a + fx * (b - a)
    bot = c + fx * (d - c)
    val = top + fy * (bot - top)
    gx = (b - a) + fy * ((d - c) - (b - a))
    gy = bot - top
    return val, gx, gy


def refine_slanted(left: np.ndarray, right: np.ndarray, xy_left: np.ndarray, xy_right: np.ndarray,
                   half: int = 10, iterations: int = 8, max_shift_px: float = 1.0,
                   max_slant: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Right-image pixels of ``xy_left`` refined with a slanted window around the match ``xy_right``.

    Returns ``(xy_right_refined (n, 2) float64, ok (n,) bool)``.  A point is not refined (``ok``
    False, its input position returned) when the fit is singular, does not settle, moves more than
    ``max_shift_px`` from the input, or needs a slant beyond ``max_slant`` (pixels of disparity per
    pixel: the window then straddles a depth edge rather than a surface).
    """
    xy_left = np.asarray(xy_left, np.float64).reshape(-1, 2)
    xy_right = np.asarray(xy_right, np.float64).reshape(-1, 2)
    n = len(xy_left)
    if n == 0:
        return xy_right.copy(), np.zeros(0, bool)
    L = np.asarray(left, np.float32)
    R = np.asarray(right, np.float32)
    dy, dx = np.mgrid[-half:half + 1, -half:half + 1]
    dx = dx.ravel().astype(np.float32)
    dy = dy.ravel().astype(np.float32)
    T, _, _ = _bilinear(L, xy_left[:, :1] + dx[None], xy_left[:, 1:2] + dy[None])  # (n, m) template
    p = np.zeros((n, 6))  # x shift, y shift, slant along x, slant along y, gain - 1, offset
    ok = np.ones(n, bool)
    step = np.full(n, np.inf)
    for _ in range(iterations):
        xr = (xy_right[:, :1] + p[:, :1] + (1.0 + p[:, 2:3]) * dx[None] + p[:, 3:4] * dy[None]).astype(np.float32)
        yr = (xy_right[:, 1:2] + p[:, 1:2] + dy[None]).astype(np.float32)
        val, gx, gy = _bilinear(R, xr, yr)
        res = val - (1.0 + p[:, 4:5]) * T - p[:, 5:6]
        J = np.stack([gx, gy, gx * dx[None], gx * dy[None], -T, -np.ones_like(T)], axis=1)  # (n, 6, m)
        A = np.matmul(J, J.transpose(0, 2, 1)).astype(np.float64)
        g = np.matmul(J, res[:, :, None])[:, :, 0].astype(np.float64)
        A += 1e-6 * np.trace(A, axis1=1, axis2=2)[:, None, None] * np.eye(6)
        good = ok & (np.linalg.cond(A) < 1e12)
        delta = np.zeros_like(p)
        delta[good] = -np.linalg.solve(A[good], g[good][..., None])[..., 0]
        ok &= good
        delta[~ok] = 0.0
        p += delta
        step = np.abs(delta[:, 0]) + np.abs(delta[:, 1])
    ok &= np.all(np.isfinite(p), axis=1) & (step < 1e-2)
    ok &= np.hypot(p[:, 0], p[:, 1]) <= max_shift_px
    ok &= (np.abs(p[:, 2]) <= max_slant) & (np.abs(p[:, 3]) <= max_slant)
    out = xy_right.copy()
    out[ok] += p[ok, :2]
    return out, ok
