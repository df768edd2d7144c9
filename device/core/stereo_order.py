"""Check that the left and right images of a sequence are not exchanged (disparity sign).

With cam0 on the left, a scene point appears further right in the left image than in the right
one after rectification: disparity ``x_left - x_right`` is positive.  Image folders swapped
(cam0 <-> cam1) make almost every disparity negative.  :func:`check_stereo_order` matches ORB
features between the images of a few frames and refuses the pair when most matched disparities
are clearly negative.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

import numpy as np

from stereopath.device.core.rig import Rig
from stereopath.device.errors import DatasetError

log = logging.getLogger(__name__)

MIN_MATCHES = 20          # fewer row-aligned matches than this: no verdict
SWAPPED_FRACTION = 0.75   # this share of the fitting matches only fit exchanged -> swapped
EPIPOLAR_TOL_PX = 3.0  # Sampson distance of a usable match


def _consistent(rig: Rig, p0: np.ndarray, p1: np.ndarray) -> int:
    """How many matches (pixels ``p0`` in cam0, ``p1`` in cam1) fit the rig: near the epipolar line
    (Sampson distance) and triangulated in front of both cameras (positive disparity)."""
    import cv2

    n0 = cv2.undistortPoints(p0.reshape(-1, 1, 2), rig.cam0.K, rig.cam0.dist).reshape(-1, 2)
    n1 = cv2.undistortPoints(p1.reshape(-1, 1, 2), rig.cam1.K, rig.cam1.dist).reshape(-1, 2)
    R, T = np.asarray(rig.R, float), np.asarray(rig.T, float).reshape(3)
    tx = np.array([[0, -T[2], T[1]], [T[2], 0, -T[0]], [-T[1], T[0], 0]])
    E = tx @ R
    x0 = np.column_stack([n0, np.ones(len(n0))])
    x1 = np.column_stack([n1, np.ones(len(n1))])
    Ex0, Etx1 = x0 @ E.T, x1 @ E
    num = np.sum(x1 * Ex0, axis=1) ** 2
    den = Ex0[:, 0] ** 2 + Ex0[:, 1] ** 2 + Etx1[:, 0] ** 2 + Etx1[:, 1] ** 2
    keep = np.sqrt(num / np.maximum(den, 1e-18)) * rig.cam0.fx <= EPIPOLAR_TOL_PX
    if not np.any(keep):
        return 0
    P0 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = np.hstack([R, T.reshape(3, 1)])
    X = cv2.triangulatePoints(P0, P1, n0[keep].T, n1[keep].T)
    w = X[3]
    ok = np.abs(w) > 1e-12
    Xc = X[:3, ok] / w[ok]
    Z1 = (R @ Xc + T.reshape(3, 1))[2]
    return int(np.sum((Xc[2] > 0) & (Z1 > 0)))


def disparity_signs(rig: Rig, left: np.ndarray, right: np.ndarray) -> tuple[int, int]:
    """(matches that fit the rig as given, matches that fit it with the two images exchanged).

    ORB features are matched on the raw images.  A match fits an ordering when it lies near the
    rig's epipolar line and triangulates in front of both cameras (a positive disparity).  For a
    rig with no rotation both orderings share the epipolar lines and only the disparity sign
    tells them apart; for a rotated rig the exchanged ordering also leaves the epipolar lines.
    """
    import cv2

    orb = cv2.ORB_create(nfeatures=800)
    kl, dl = orb.detectAndCompute(left, None)
    kr, dr = orb.detectAndCompute(right, None)
    if dl is None or dr is None or len(kl) < 2 or len(kr) < 2:
        return 0, 0
    matches = [m for m in cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr) if m.distance <= 50]
    if not matches:
        return 0, 0
    pl = np.array([kl[m.queryIdx].pt for m in matches], np.float64)
    pr = np.array([kr[m.trainIdx].pt for m in matches], np.float64)
    return _consistent(rig, pl, pr), _consistent(rig, pr, pl)


def check_stereo_order(rig: Rig, pairs: Iterable[tuple[np.ndarray, np.ndarray]], source: str = "") -> None:
    """Raise :class:`DatasetError` when the pairs' disparities say left and right are exchanged."""
    pos = neg = 0
    for left, right in pairs:
        p, n = disparity_signs(rig, left, right)
        pos, neg = pos + p, neg + n
    total = pos + neg
    if total < MIN_MATCHES:
        log.debug("%s: %d informative stereo matches; stereo order not checked", source, total)
        return
    if neg >= SWAPPED_FRACTION * total:
        raise DatasetError(
            f"{source + ': ' if source else ''}left and right images look swapped: {neg} stereo matches fit the "
            f"rig with the images exchanged, {pos} as given (the given order gives them negative disparities); "
            f"the left image must come from cam0, the left camera: exchange the cam0 and cam1 (or image_0 "
            f"and image_1) folders")
    log.debug("%s: stereo order ok (%d matches fit as given, %d exchanged)", source, pos, neg)


def check_sequence_order(seq, frames: int = 2) -> None:
    """:func:`check_stereo_order` on the first readable frames of a sequence (``rig``, ``frame(i)``)."""
    pairs = []
    for i in range(min(len(seq), frames + 3)):
        if len(pairs) >= frames:
            break
        try:
            fr = seq.frame(i)
        except DatasetError:
            continue
        pairs.append((fr.left, fr.right))
    check_stereo_order(seq.rig, pairs, getattr(seq, "name", "") or "")
