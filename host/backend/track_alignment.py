"""Track observations aligned on one reference view (offline): every keyframe sees the same surface point.

A detector finds a blob on a surface seen at a slant at the centre of its *image*, which perspective
moves from view to view, so a track's independent detections scatter and bundle adjustment averages
that into the path.  :func:`align_tracks` takes each track's middle keyframe as its reference and moves
every other observation to where the reference window lands: an affine warp started from the one the
poses predict, fitted by inverse-compositional Gauss-Newton (:func:`refine_affine`, gain and offset
free); the right-image match moves alike and is refined with the slanted window.  Observations whose fit
does not settle or that move too far are dropped.  Pure computation on the images handed in.
See docs/architecture.md, "Reprocessing" (the ``aligned`` preset).
"""

from __future__ import annotations

from dataclasses import dataclass

import logging

import numpy as np

log = logging.getLogger(__name__)

BLOCK = 1024  # observations per block (a block's windows stay in the CPU caches)


@dataclass(frozen=True)
class AffineFit:
    """The affine window's fit: half its side (pixels), Gauss-Newton iterations, and the last step a
    settled point moved less than (pixels)."""

    half: int = 10
    iterations: int = 10
    tol_px: float = 0.02


def refine_affine(ref_images: list[np.ndarray], ref_img: np.ndarray, xy_ref: np.ndarray, target: np.ndarray,
                  xy: np.ndarray, A0: np.ndarray, fit: AffineFit = AffineFit()
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the window of the grey image ``ref_images[ref_img[i]]`` around ``xy_ref[i]`` lands in the
    grey image ``target``.

    The window's offsets ``x`` map by ``x -> xy + A x``, started at ``xy`` and ``A0`` (n, 2, 2);
    inverse-compositional Gauss-Newton on the six parameters, brightness offset and gain free.  The
    template is sampled exactly; the target with OpenCV's bilinear remap (positions in 1/32 px: an
    affine window's samples have different fractions, so the rounding averages out).
    Returns ``(xy_refined (n, 2), A (n, 2, 2), settled (n,) bool)``: settled when the last step
    moved the point by less than ``fit.tol_px`` and the window had texture (a point stops at half that)."""
    import cv2

    half, iterations, tol_px = fit.half, fit.iterations, fit.tol_px

    from stereopath.host.backend.slanted_stereo import window_samples

    xy_ref = np.asarray(xy_ref, np.float64).reshape(-1, 2)
    n = len(xy_ref)
    c = np.asarray(xy, np.float64).reshape(-1, 2).copy()
    A = np.asarray(A0, np.float64).reshape(-1, 2, 2).copy()
    if n == 0:
        return c, A, np.zeros(0, bool)
    dy, dx = np.mgrid[-half:half + 1, -half:half + 1]
    dx = dx.ravel().astype(np.float32)
    dy = dy.ravel().astype(np.float32)
    m = len(dx)
    T, gx, gy = (np.empty((n, m), np.float32) for _ in range(3))
    for r in np.unique(ref_img):  # the windows of each reference image in one call (exact bilinear)
        sel = np.flatnonzero(ref_img == r)
        T[sel], gx[sel], gy[sel] = window_samples(ref_images[r], xy_ref[sel], half)
    T = T - T.mean(axis=1, keepdims=True)
    t_norm = np.sqrt(np.einsum("nm,nm->n", T, T))
    # d/d(a11, a12, tx, a21, a22, ty) of the template at the identity warp, brightness offset free
    J = np.empty((n, 6, m), np.float32)
    np.multiply(gx, dx, out=J[:, 0])
    np.multiply(gx, dy, out=J[:, 1])
    J[:, 2] = gx
    np.multiply(gy, dx, out=J[:, 3])
    np.multiply(gy, dy, out=J[:, 4])
    J[:, 5] = gy
    J -= J.mean(axis=2, keepdims=True)
    H = np.matmul(J, J.transpose(0, 2, 1)).astype(np.float64)
    ok = (t_norm > 0) & np.all(np.isfinite(H), axis=(1, 2))
    w, _ = np.linalg.eigh(np.where(ok[:, None, None], H, np.eye(6)))
    ok &= w[:, 0] > 1e-6 * np.maximum(w[:, -1], 1e-12)
    Hinv = np.zeros_like(H)
    Hinv[ok] = np.linalg.inv(H[ok])
    step = np.full(n, np.inf)
    act = np.flatnonzero(ok)  # the points still moving; rows of the compacted arrays below
    Jc, Tc, Hc, tn = J[act], T[act], Hinv[act], t_norm[act].astype(np.float32)
    rows = np.arange(len(act))
    for _ in range(iterations):
        if len(act) == 0:
            break
        if len(rows) < len(Jc):  # the settled points leave the arrays (one copy, not one per use)
            Jc, Tc, Hc, tn = Jc[rows], Tc[rows], Hc[rows], tn[rows]
            rows = np.arange(len(act))
        Aa = A[act].astype(np.float32)
        x = c[act, :1].astype(np.float32) + Aa[:, 0, :1] * dx[None] + Aa[:, 0, 1:] * dy[None]
        y = c[act, 1:].astype(np.float32) + Aa[:, 1, :1] * dx[None] + Aa[:, 1, 1:] * dy[None]
        Iw = cv2.remap(target, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
        Iw -= Iw.mean(axis=1, keepdims=True)
        i_norm = np.sqrt(np.einsum("nm,nm->n", Iw, Iw))
        Iw *= (tn / np.maximum(i_norm, 1e-6))[:, None]  # the gain is free
        Iw -= Tc
        g = np.matmul(Jc, Iw[:, :, None])[:, :, 0].astype(np.float64)
        d = np.einsum("nij,nj->ni", Hc, g)
        # compose with the inverse increment: A <- A M^-1, c <- c - A M^-1 t_d
        M = np.empty((len(act), 2, 2))
        M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1] = 1 + d[:, 0], d[:, 1], d[:, 3], 1 + d[:, 4]
        AM = np.matmul(A[act], np.linalg.inv(M))
        dc = np.einsum("nij,nj->ni", AM, d[:, [2, 5]])
        c[act] -= dc
        A[act] = AM
        step[act] = np.hypot(dc[:, 0], dc[:, 1])
        moving = (step[act] >= tol_px / 2) & np.isfinite(c[act]).all(axis=1)
        act, rows = act[moving], rows[moving]
    settled = ok & (step < tol_px) & np.isfinite(c).all(axis=1)
    return c, A, settled


def facing_affine(K: np.ndarray, uv_ref: np.ndarray, X_ref: np.ndarray, T_tgt_ref: np.ndarray) -> np.ndarray:
    """(n, 2, 2) local affine maps of the reference image onto the target image at ``uv_ref``
    (undistorted pixels) for a surface through ``X_ref`` (reference camera) facing the reference
    camera, the target camera at ``T_tgt_ref`` (one (4, 4) or one per point): the starting warp of
    :func:`refine_affine` (the fit finds the surface's own slant)."""
    n = len(uv_ref)
    Kinv = np.linalg.inv(K)
    normal = X_ref / np.maximum(np.linalg.norm(X_ref, axis=1, keepdims=True), 1e-12)
    dist = np.einsum("ij,ij->i", normal, X_ref)
    Trel = np.broadcast_to(np.asarray(T_tgt_ref, float), (n, 4, 4))
    R, t = Trel[:, :3, :3], Trel[:, :3, 3]

    def to_target(uv: np.ndarray) -> np.ndarray:
        ray = np.column_stack([uv, np.ones(n)]) @ Kinv.T
        X = ray * (dist / np.einsum("ij,ij->i", normal, ray))[:, None]
        p = (np.einsum("nij,nj->ni", R, X) + t) @ K.T
        return p[:, :2] / p[:, 2:]

    p0 = to_target(uv_ref)
    A = np.empty((n, 2, 2))
    A[:, :, 0] = to_target(uv_ref + [1.0, 0.0]) - p0
    A[:, :, 1] = to_target(uv_ref + [0.0, 1.0]) - p0
    return A


def _window_inside(c: np.ndarray, A: np.ndarray, half: int, w: int, h: int) -> np.ndarray:
    """Whether the windows ``c + A [-half, half]^2`` lie inside a ``w`` x ``h`` image."""
    corners = np.array([[-half, -half], [half, -half], [-half, half], [half, half]], float)
    p = c[:, None, :] + np.einsum("nij,kj->nki", A, corners)
    return np.all((p[..., 0] >= 0) & (p[..., 0] <= w - 1) & (p[..., 1] >= 0) & (p[..., 1] <= h - 1), axis=1)


def _raw_px(cam, uv: np.ndarray) -> np.ndarray:
    """Undistorted pixels of camera ``cam`` back to its raw (distorted) pixels."""
    import cv2

    if not np.any(cam.dist) or len(uv) == 0:
        return np.asarray(uv, np.float64)
    K = cam.K
    rays = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))])
    return cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, cam.dist)[0].reshape(-1, 2)


def _refine_blocks(templates: list[np.ndarray], targets: list[np.ndarray], args: tuple, half: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`refine_affine` in blocks of at most :data:`BLOCK` observations of one target image, on
    OpenCV's thread count."""
    import cv2

    ref_img, xy_ref, img, xy, A0 = args  # img: the target keyframe of each observation, sorted
    n = len(xy)
    cuts = np.flatnonzero(np.diff(img)) + 1
    blocks = [slice(i, min(i + BLOCK, j)) for a, j in zip(np.r_[0, cuts], np.r_[cuts, n]) for i in range(a, j, BLOCK)]

    def one(b: slice):
        return refine_affine(templates, ref_img[b], xy_ref[b], targets[img[b.start]], xy[b], A0[b], AffineFit(half=half))

    workers = max(1, min(cv2.getNumThreads(), len(blocks)))
    if workers == 1:
        parts = [one(b) for b in blocks]
    else:  # NumPy releases the GIL in the array work; blocks are independent
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(workers) as ex:
            parts = list(ex.map(one, blocks))
    if not parts:
        return np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0, bool)
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))


def align_tracks(rig, lefts: list[np.ndarray], rights: list[np.ndarray], T_world_cam: np.ndarray, cfg,
                 kfs: list, kf_of: np.ndarray, track: np.ndarray) -> tuple[list, np.ndarray]:
    """Every track's observations moved onto the surface point of its reference observation (see the
    module doc).  ``kfs``: the keyframes' :class:`~stereopath.host.backend.tracks.KeyframeFeatures`
    (grey images ``lefts``/``rights``, poses ``T_world_cam``); ``kf_of``, ``track``: each keypoint's
    keyframe and track (-1: in none), over the keyframes' keypoints in order.  Returns the keyframes
    with the moved keypoints (left pixel, stereo match, 3D point) and the mask of the keypoints kept."""
    from stereopath.device.core.features import Features, gray
    from stereopath.device.core.geometry import invert_pose
    from stereopath.host.backend.tracks import ALIGN_MAX_MOVE_PX, KeyframeFeatures, stereo_points

    keep = np.ones(len(track), bool)
    glob = np.flatnonzero(track >= 0)
    if len(glob) == 0:
        return kfs, keep
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in kfs])]).astype(np.int64)
    xy = np.concatenate([k.feats.xy for k in kfs]).astype(np.float64)
    uv0 = np.concatenate([k.uv0 for k in kfs])
    X = np.concatenate([k.X_cam for k in kfs])
    glob = glob[np.lexsort((kf_of[glob], track[glob]))]
    _, start, count = np.unique(track[glob], return_index=True, return_counts=True)
    ref = np.repeat(glob[start + (count - 1) // 2], count)  # the track's middle keyframe
    tgt_mask = ref != glob
    tgt, ref = glob[tgt_mask], ref[tgt_mask]
    kt, kr = kf_of[tgt], kf_of[ref]
    T = np.asarray(T_world_cam, float)
    T_cw = np.array([invert_pose(x) for x in T])
    A0 = facing_affine(rig.cam0.K, uv0[ref], X[ref], np.matmul(T_cw[kt], T[kr]))
    grey = [gray(im) for im in lefts]
    order = np.lexsort((kr, kt))  # by target image, then reference image
    new_xy = np.empty((len(tgt), 2))
    settled = np.empty(len(tgt), bool)
    args = (kr[order], xy[ref[order]], kt[order], xy[tgt[order]], A0[order])
    half = cfg.align_window // 2
    A = np.empty((len(tgt), 2, 2))
    new_xy[order], A[order], settled[order] = _refine_blocks([g.astype(np.float32) for g in grey], grey, args, half)
    moved = np.linalg.norm(new_xy - xy[tgt], axis=1)
    h, w = grey[0].shape[:2]
    # both windows on real pixels (a border replicated into a window would pull the fit)
    inside = _window_inside(xy[ref], np.repeat(np.eye(2)[None], len(ref), 0), half, w, h)
    inside &= _window_inside(new_xy, A, half, w, h)
    ok = settled & inside & (moved <= ALIGN_MAX_MOVE_PX)
    out = []
    for k, kf in enumerate(kfs):
        m = (kt == k)
        sel = np.flatnonzero(m)
        if len(sel) == 0:
            out.append(kf)
            continue
        local = tgt[sel] - offsets[k]
        good = ok[sel]
        # the moved pixel matched in the right image as at keyframes, from the old match moved alike
        xy_k = new_xy[sel[good]]
        guess = _raw_px(rig.cam1, kf.uv1[local[good]]) + (xy_k - xy[tgt[sel[good]]])
        u1, v1, X1, ok1 = stereo_points(rig, gray(lefts[k]), gray(rights[k]), xy_k.astype(np.float32), cfg,
                                        guess_right=guess)
        fx = kf.feats.xy.copy()
        a_uv0, a_uv1, a_X = kf.uv0.copy(), kf.uv1.copy(), kf.X_cam.copy()
        idx = local[good][ok1]
        fx[idx] = xy_k[ok1]
        a_uv0[idx], a_uv1[idx], a_X[idx] = u1[ok1], v1[ok1], X1[ok1]
        f = kf.feats
        out.append(KeyframeFeatures(Features(fx, f.desc, f.size, f.angle, f.response, f.view), a_uv0, a_uv1, a_X))
        dropped = np.concatenate([local[~good], local[good][~ok1]])
        keep[offsets[k] + dropped] = False
    log.info("track alignment: %d of %d observations moved onto their track's reference (median %.3f px), %d dropped",
             int((~np.isin(tgt, np.flatnonzero(~keep))).sum()), len(tgt), float(np.median(moved[ok])) if ok.any() else 0.0,
             int((~keep).sum()))
    return out, keep
