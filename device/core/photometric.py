"""The brightness relation between the two cameras of a rig, measured on stereo matches (pure compute).

KLT assumes a point is as bright in both images; two cameras with their own exposure control break that.
The relation is an affine map of grey levels, ``left ~ gain * right + offset``, fitted on the mean
intensities of small patches around points already matched in stereo, so it measures the cameras and
not what only one of them sees.  :func:`fit_gain_offset` fits it robustly (a symmetric line, outliers
dropped), :func:`measure_relation` measures a pair with no earlier fit in two passes,
:func:`relation_matters` says whether it changes the matched texture by more than a tolerance (4 grey
levels by default), and :func:`correct_right` applies it with a lookup table.
See docs/architecture.md, "Two cameras, two exposures".
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class GainOffset:
    """``left ~ gain * right + offset`` in grey levels; ``n`` matches supported the fit (0: identity),
    ``change`` is the median grey-level change the relation makes to their right patches."""

    gain: float = 1.0
    offset: float = 0.0
    n: int = 0
    change: float = 0.0

    def apply_levels(self, levels: np.ndarray) -> np.ndarray:
        return self.gain * np.asarray(levels, np.float64) + self.offset


def _patch_means(image: np.ndarray, xy: np.ndarray, patch: int) -> np.ndarray:
    """Mean grey level of the ``patch`` x ``patch`` square of whole pixels around each point (clipped at the border)."""
    h, w = image.shape[:2]
    r = patch // 2
    x0 = np.clip(np.floor(xy[:, 0]).astype(np.int64) - r, 0, w - 1)
    y0 = np.clip(np.floor(xy[:, 1]).astype(np.int64) - r, 0, h - 1)
    x1 = np.clip(x0 + patch, 0, w)
    y1 = np.clip(y0 + patch, 0, h)
    ii = cv2.integral(image)  # (h+1, w+1), float64 sums
    s = ii[y1, x1] - ii[y0, x1] - ii[y1, x0] + ii[y0, x0]
    area = np.maximum((x1 - x0) * (y1 - y0), 1)
    return s / area


def fit_gain_offset(left: np.ndarray, right: np.ndarray, xy_left: np.ndarray, xy_right: np.ndarray,
                    patch: int = 9, min_points: int = 30, min_spread: float = 8.0,
                    min_correlation: float = 0.9) -> GainOffset | None:
    """The affine grey-level relation of the right camera to the left from matched pixels.

    The line through the patch means' centroid with the ratio of their spreads as slope (symmetric:
    both cameras' patch means carry the same noise, which would shrink a least-squares gain), then
    again without the matches whose residual exceeds three robust standard deviations (a match on an
    occlusion edge, a specular spot).  ``None`` when it is not identifiable: fewer than
    ``min_points`` matches, right-image patch means spread less than ``min_spread`` grey levels (a
    uniform scene fixes an offset, not a gain), patch means correlated less than
    ``min_correlation`` (not one affine relation), or a gain outside 0.25-4."""
    xy_left = np.asarray(xy_left, np.float64).reshape(-1, 2)
    xy_right = np.asarray(xy_right, np.float64).reshape(-1, 2)
    if len(xy_left) < min_points or len(xy_left) != len(xy_right):
        return None
    a = _patch_means(left, xy_left, patch)
    b = _patch_means(right, xy_right, patch)
    if float(np.std(b)) < min_spread:
        return None
    keep = np.ones(len(a), bool)
    g = o = 0.0
    for _ in range(2):
        # both sides are measured with the same noise: the symmetric (geometric-mean) line, not least
        # squares of one on the other, whose gain the noise of the regressor shrinks towards 0
        ak, bk = a[keep], b[keep]
        if np.corrcoef(ak, bk)[0, 1] < min_correlation:
            return None
        g = float(np.std(ak) / np.std(bk))
        o = float(np.mean(ak) - g * np.mean(bk))
        res = a - (g * b + o)
        mad = float(np.median(np.abs(res[keep] - np.median(res[keep]))))
        keep = np.abs(res) <= max(3.0 * 1.4826 * mad, 1.0)
        if keep.sum() < min_points:
            return None
    if not 0.25 <= g <= 4.0:
        return None
    change = float(np.median(np.abs((g - 1.0) * b[keep] + o)))
    return GainOffset(float(g), float(o), int(keep.sum()), change)


def relation_matters(rel: GainOffset | None, tolerance: float = 4.0) -> bool:
    """Whether ``rel`` changes the matched texture's grey levels by more than ``tolerance`` (median)."""
    return rel is not None and rel.change > tolerance


def correct_right(right: np.ndarray, rel: GainOffset) -> np.ndarray:
    """The right image in the left camera's grey levels (``uint8``, saturated at 0 and 255)."""
    lut = np.clip(np.rint(rel.apply_levels(np.arange(256))), 0, 255).astype(np.uint8)
    return cv2.LUT(right, lut)


def measure_relation(left: np.ndarray, right: np.ndarray, xy_left: np.ndarray,
                     search: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
                     refine_above: float = 1.0) -> GainOffset | None:
    """The relation of a pair with no earlier measurement: ``search(right image)`` locates the left
    pixels ``xy_left`` in a right image (returns right pixels and a mask), then :func:`fit_gain_offset`.

    Cameras far apart match few points as captured (a right camera at 0.75x gain: 40-50 of 300
    corners), so when that first fit changes the texture by more than ``refine_above`` grey levels the
    points are searched again in the right image corrected by it, and the relation is fitted anew on
    those matches (five to six times as many) against the right image as captured."""
    xy_left = np.asarray(xy_left, np.float64).reshape(-1, 2)
    xr, ok = search(right)
    rel = fit_gain_offset(left, right, xy_left[ok], xr[ok])
    if rel is None or rel.change <= refine_above:
        return rel
    xr, ok = search(correct_right(right, rel))
    return fit_gain_offset(left, right, xy_left[ok], xr[ok]) or rel


__all__ = ["GainOffset", "fit_gain_offset", "relation_matters", "correct_right", "measure_relation"]
