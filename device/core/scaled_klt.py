"""Frame-to-frame KLT with the previous image resampled at the scale each point is predicted to take.

Pyramidal KLT compares windows that are only shifted; when the camera moves along its axis a near
point's surroundings scale by ``Z_prev / Z_next`` between frames, which pulls the tracked position off
the point (``tests/device/test_scaled_klt.py``).  :func:`track_scaled` groups the points by predicted scale in
rungs of ``(1 + step) ** k`` and tracks each group whose scale is not 1 from the previous image's region
resampled at that scale (placed by the group's median offset), against the same region of the next
image.  The group at scale 1, points predicted outside the next image and points that move unlike their
group are tracked exactly as :func:`cv2.calcOpticalFlowPyrLK` would.  Pure compute: images in,
positions out.  See docs/architecture.md, "The on-board estimator".
"""

from __future__ import annotations

import math

import cv2
import numpy as np


def scale_groups(scale: np.ndarray, step: float) -> np.ndarray:
    """Each point's rung on the ladder ``(1 + step) ** k`` nearest its predicted ``scale`` (0: scale 1).

    Scales that are not finite and positive count as 1 (no prediction); ``step <= 0`` puts every point on 0."""
    s = np.asarray(scale, float)
    k = np.zeros(len(s), np.int64)
    if step <= 0 or len(s) == 0:
        return k
    ok = np.isfinite(s) & (s > 0)
    k[ok] = np.round(np.log(np.clip(s[ok], 0.25, 4.0)) / math.log1p(step)).astype(np.int64)
    return k


def forward_backward(prev, cur, p0, guess, klt: dict, fb_levels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """KLT ``prev`` -> ``cur`` from ``guess``, then back from the result to ``prev`` seeded at ``p0`` (a
    true track converges there at once; ``fb_levels`` caps the backward pyramid): (positions in
    ``cur``, both statuses set, backward disagreement in px).  Also the offline tracks' keyframe ->
    frame step (``host/backend/tracks.py``)."""
    p0 = p0.reshape(-1, 1, 2).astype(np.float32)
    g = guess.reshape(-1, 1, 2).astype(np.float32)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, g.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **klt)
    pb, stb, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                          **dict(klt, maxLevel=min(klt.get("maxLevel", 3), fb_levels)))
    fb = np.linalg.norm((pb - p0).reshape(-1, 2), axis=1)
    return p1.reshape(-1, 2), (st.ravel() == 1) & (stb.ravel() == 1), fb


def _crop(img: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """``img[y0:y1, x0:x1]``, the part outside the image filled by replicating its border."""
    h, w = img.shape[:2]
    if 0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h:
        return np.ascontiguousarray(img[y0:y1, x0:x1])
    cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if cx0 < cx1 and cy0 < cy1:  # the part inside the image, its border replicated outward (no resampling)
        return cv2.copyMakeBorder(img[cy0:cy1, cx0:cx1], cy0 - y0, y1 - cy1, cx0 - x0, x1 - cx1, cv2.BORDER_REPLICATE)
    return cv2.warpAffine(img, np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0]]), (x1 - x0, y1 - y0),
                          flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)


def track_scaled(prev: np.ndarray, cur: np.ndarray, p0: np.ndarray, guess: np.ndarray, scale: np.ndarray,
                 step: float, klt: dict, fb_levels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Track points ``p0`` of ``prev`` into ``cur`` from ``guess`` (both (n, 2) pixels), the window of
    each compared at its predicted ``scale`` (rungs of ``step``, see :func:`scale_groups`).

    ``klt``: :func:`cv2.calcOpticalFlowPyrLK`'s ``winSize``, ``maxLevel`` and ``criteria``;
    ``fb_levels``: the pyramid of the backward track (it starts at the known answer).  Returns the
    positions in ``cur`` (float32), whether both tracks converged, and the backward track's
    disagreement in pixels of ``prev``."""
    p0 = np.asarray(p0, np.float32).reshape(-1, 2)
    guess = np.asarray(guess, np.float32).reshape(-1, 2)
    n = len(p0)
    p1, ok, fb = np.zeros((n, 2), np.float32), np.zeros(n, bool), np.full(n, np.inf)
    if n == 0:
        return p1, ok, fb
    rung = scale_groups(scale, step)
    win = int(klt.get("winSize", (21, 21))[0])
    margin = (win // 2 + 2) * 2 ** int(klt.get("maxLevel", 3)) + 2  # what the coarsest level reads around a point
    h, w = cur.shape[:2]
    # a point predicted outside the next image has nothing there to compare at any scale: plain KLT
    rung[~((guess >= 0) & (guess < (w, h))).all(1)] = 0
    plans = []
    for k in np.unique(rung[rung != 0]):
        idx = np.flatnonzero(rung == k)
        s = (1.0 + step) ** int(k)
        # prev scaled by s and shifted by the group's median offset to its guesses (the canvas of both images)
        shift = np.median(guess[idx] - s * p0[idx], axis=0)
        q = s * p0[idx] + shift
        pts = np.vstack([guess[idx], q])
        x0 = int(math.floor(max(pts[:, 0].min() - margin, -margin)))
        y0 = int(math.floor(max(pts[:, 1].min() - margin, -margin)))
        x1 = int(math.ceil(min(pts[:, 0].max() + margin, w + margin)))
        y1 = int(math.ceil(min(pts[:, 1].max() + margin, h + margin)))
        # a point whose shifted position falls off the region moves unlike its group: plain KLT
        inside = (q[:, 0] >= x0) & (q[:, 0] < x1 - 1) & (q[:, 1] >= y0) & (q[:, 1] < y1 - 1)
        rung[idx[~inside]] = 0
        if inside.any():
            plans.append((idx[inside], s, shift, (x0, y0, x1, y1)))
    idx = np.flatnonzero(rung == 0)
    if len(idx):
        p1[idx], ok[idx], fb[idx] = forward_backward(prev, cur, p0[idx], guess[idx], klt, fb_levels)
    for idx, s, shift, (x0, y0, x1, y1) in plans:
        M = np.array([[s, 0.0, shift[0] - x0], [0.0, s, shift[1] - y0]])
        prev_s = cv2.warpAffine(prev, M, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        cur_c = _crop(cur, x0, y0, x1, y1)
        q1, good, back = forward_backward(prev_s, cur_c, p0[idx] @ M[:, :2].T + M[:, 2], guess[idx] - (x0, y0), klt,
                                           fb_levels)
        p1[idx] = q1 + (x0, y0)
        ok[idx] = good
        fb[idx] = back / s  # the resampled image has s of its pixels to one of the previous image's
    return p1, ok, fb
