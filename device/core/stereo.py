"""Stereo triangulation, projection and Levenberg-Marquardt pose refinement in both cameras.

Pixel coordinates handed to these functions are *undistorted* (ideal pinhole
with the camera's own K).  Poses: ``T_cam_world`` maps world points into the
left camera; the right camera is ``T_cam1_cam0 @ T_cam_world``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from stereopath.device.core.geometry import skew, so3_exp
from stereopath.device.core.rig import Rig


def undistort_px(xy: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Distorted pixel coordinates -> ideal pinhole pixels with the same K."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(xy) == 0 or not np.any(dist):
        return xy.copy()
    return cv2.undistortPoints(xy.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)


def project(K: np.ndarray, X_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection; returns pixels (N,2) and depths (N,)."""
    z = X_cam[:, 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    u = K[0, 0] * X_cam[:, 0] / zs + K[0, 2]
    v = K[1, 1] * X_cam[:, 1] / zs + K[1, 2]
    return np.stack([u, v], axis=1), z


def triangulate(rig: Rig, uv0: np.ndarray, uv1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate undistorted left/right pixel pairs; returns X in cam0 (N,3) and max reprojection error."""
    if len(uv0) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    P0 = rig.cam0.K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = rig.cam1.K @ np.hstack([rig.R, rig.T.reshape(3, 1)])
    Xh = cv2.triangulatePoints(P0, P1, uv0.T.astype(np.float64), uv1.T.astype(np.float64))
    w = Xh[3]
    w = np.where(np.abs(w) < 1e-12, 1e-12, w)
    X = (Xh[:3] / w).T
    p0, z0 = project(rig.cam0.K, X)
    p1, z1 = project(rig.cam1.K, X @ rig.R.T + rig.T)
    err = np.maximum(np.linalg.norm(p0 - uv0, axis=1), np.linalg.norm(p1 - uv1, axis=1))
    err = np.where((z0 > 0) & (z1 > 0), err, np.inf)
    return X, err


@dataclass(frozen=True, eq=False)
class PointObservations:
    """World points and where one camera saw them (undistorted pixels), row for row."""

    X_world: np.ndarray  # (N, 3)
    uv: np.ndarray       # (N, 2)


@dataclass(frozen=True)
class LMOptions:
    """Robust Levenberg-Marquardt settings of :func:`refine_pose_lm`: Huber loss at ``huber_px``;
    residuals of ``cutoff_px`` (default ``10 * outlier_px``) or more weigh nothing; the inliers
    returned are those under ``outlier_px``."""

    huber_px: float = 1.0
    max_iter: int = 15
    outlier_px: float = 3.0
    cutoff_px: float | None = None


@dataclass(frozen=True, eq=False)
class RotationPrior:
    """A prior on ``R_cam_world`` (e.g. gyro-integrated): ``weight * log(R prior^T)`` residuals
    (radians scaled to pixels by the weight)."""

    R: np.ndarray
    weight: float


@dataclass
class RefineResult:
    T_cam_world: np.ndarray
    inliers_left: np.ndarray
    inliers_right: np.ndarray
    rms_px: float
    iterations: int


def _residuals(T: np.ndarray, X: np.ndarray, uv: np.ndarray, K: np.ndarray, T_extra: np.ndarray | None):
    Xc = X @ T[:3, :3].T + T[:3, 3]
    Xk = Xc if T_extra is None else Xc @ T_extra[:3, :3].T + T_extra[:3, 3]
    p, z = project(K, Xk)
    return p - uv, Xc, Xk, z


def _camera_system(T: np.ndarray, X: np.ndarray, uv: np.ndarray, K: np.ndarray, Te: np.ndarray | None,
                   huber_px: float, cutoff_px: float) -> tuple[float, np.ndarray, np.ndarray]:
    """One camera's Huber-weighted cost and normal equations (H, g) for the left perturbation of ``T``
    (residuals of ``cutoff_px`` or more weigh nothing)."""
    r, Xc, Xk, z = _residuals(T, X, uv, K, Te)
    valid = z > 1e-6
    e = np.sqrt(r[:, 0] ** 2 + r[:, 1] ** 2)
    w = np.where(e <= huber_px, 1.0, huber_px / np.maximum(e, 1e-12))
    w = np.where(valid & (e < cutoff_px), w, 0.0)
    cost = float(np.sum(w * e * e))
    iz = 1.0 / np.where(valid, Xk[:, 2], 1.0)
    # rows a = d(u)/d(Xk) and d(v)/d(Xk), then through Xk = R_e Xc + t_e to d/d(Xc)
    n = len(z)
    a = np.zeros((2, n, 3))
    a[0, :, 0] = K[0, 0] * iz
    a[0, :, 2] = -K[0, 0] * Xk[:, 0] * iz * iz
    a[1, :, 1] = K[1, 1] * iz
    a[1, :, 2] = -K[1, 1] * Xk[:, 1] * iz * iz
    if Te is not None:
        a = a @ Te[:3, :3]
    # d(Xc)/d(dt, dtheta) = [I, -[Xc]x], and a (-[Xc]x) = Xc x a for a row vector a
    J = np.empty((2, n, 6))
    J[:, :, :3] = a
    x, y, zc = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    J[:, :, 3] = y * a[:, :, 2] - zc * a[:, :, 1]
    J[:, :, 4] = zc * a[:, :, 0] - x * a[:, :, 2]
    J[:, :, 5] = x * a[:, :, 1] - y * a[:, :, 0]
    J = J.reshape(2 * n, 6)
    Jw = J * np.concatenate([w, w])[:, None]
    return cost, Jw.T @ J, Jw.T @ r.T.reshape(-1)


def _inlier_errors(T: np.ndarray, X: np.ndarray, uv: np.ndarray, K: np.ndarray, Te: np.ndarray | None,
                   outlier_px: float) -> tuple[np.ndarray, np.ndarray]:
    r, *_ = _residuals(T, X, uv, K, Te)
    e = np.linalg.norm(r, axis=1)
    inl = e < outlier_px
    return inl, e[inl]


def refine_pose_lm(rig: Rig, T_cam_world: np.ndarray, left: PointObservations, right: PointObservations | None = None,
                   options: LMOptions = LMOptions(), prior: RotationPrior | None = None) -> RefineResult:
    """Levenberg-Marquardt on the reprojection error in both cameras (Huber loss, IRLS).

    The update is a left perturbation ``T <- [exp(dtheta) | dt] @ T``; see :class:`LMOptions`
    and :class:`RotationPrior`.
    """
    X_world, uv_left = left.X_world, left.uv
    X_world_r, uv_right = (None, None) if right is None else (right.X_world, right.uv)
    huber_px, max_iter, outlier_px = options.huber_px, options.max_iter, options.outlier_px
    prior_R, prior_weight = (None, 0.0) if prior is None else (prior.R, prior.weight)
    T = T_cam_world.copy()
    cutoff = 10 * outlier_px if options.cutoff_px is None else options.cutoff_px
    K0, K1 = rig.cam0.K, rig.cam1.K
    T10 = rig.T_cam1_cam0
    has_r = X_world_r is not None and uv_right is not None and len(uv_right) > 0
    blocks = [(X_world, uv_left, K0, None)] + ([(X_world_r, uv_right, K1, T10)] if has_r else [])
    lam = 1e-3
    n_iter = 0

    def cost_and_system(T: np.ndarray):
        H = np.zeros((6, 6))
        g = np.zeros(6)
        cost = 0.0
        for X, uv, K, Te in blocks:
            c, Hc, gc = _camera_system(T, X, uv, K, Te, huber_px, cutoff)
            cost, H, g = cost + c, H + Hc, g + gc
        if prior_R is not None and prior_weight > 0:
            from stereopath.device.core.geometry import so3_log

            rr = so3_log(T[:3, :3] @ prior_R.T) * prior_weight
            cost += float(rr @ rr)
            Jr = np.zeros((3, 6))
            Jr[:, 3:] = np.eye(3) * prior_weight
            H += Jr.T @ Jr
            g += Jr.T @ rr
        return cost, H, g

    cost, H, g = cost_and_system(T)
    for n_iter in range(1, max_iter + 1):
        A = H + lam * np.diag(np.maximum(np.diag(H), 1e-9))
        try:
            delta = -np.linalg.solve(A, g)
        except np.linalg.LinAlgError:
            break
        Tn = np.eye(4)
        Tn[:3, :3] = so3_exp(delta[3:])
        Tn[:3, 3] = delta[:3]
        T_new = Tn @ T
        new_cost, H_new, g_new = cost_and_system(T_new)
        if new_cost < cost:
            # converged: the step no longer lowers the cost noticeably (relative 1e-6)
            converged = cost - new_cost <= 1e-6 * cost or np.linalg.norm(delta) < 1e-10
            T, cost, H, g = T_new, new_cost, H_new, g_new
            lam = max(lam / 10, 1e-7)
            if converged:
                break
        else:
            lam *= 10
            if lam > 1e6:
                break
    inl, el = _inlier_errors(T, X_world, uv_left, K0, None, outlier_px)
    errs = [el]
    inr = np.zeros(0, bool)
    if has_r:
        inr, er = _inlier_errors(T, X_world_r, uv_right, K1, T10, outlier_px)
        errs.append(er)
    allerr = np.concatenate(errs)
    rms = float(np.sqrt(np.mean(allerr**2))) if len(allerr) else float("inf")
    return RefineResult(T, inl, inr, rms, n_iter)


class KltStereoParams(Protocol):
    """What :func:`stereo_right` reads from a configuration (StereoConfig, TrackConfig, ...)."""

    klt_window: int
    klt_levels: int
    fb_max_px: float
    epipolar_max_dy_px: float


KLT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 0.005)


def stereo_right(rig: Rig, left: np.ndarray, right: np.ndarray, xy_left: np.ndarray, guess_right: np.ndarray,
                 cfg: KltStereoParams, fb_check: bool = True, levels: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Locate left-image points in the right image; returns right pixels (float32) and the accepted mask.

    Pyramidal KLT from left to right seeded by ``guess_right`` (e.g. a projection at an expected
    depth).  A point is accepted when KLT converged, the rectified rows agree within
    ``cfg.epipolar_max_dy_px``, the disparity is positive and the point lies inside the right
    image; ``fb_check`` adds the right-to-left track back (within ``cfg.fb_max_px``), which new
    points need and known inliers (refinement) can skip.  ``levels`` overrides ``cfg.klt_levels``
    (a guess from a known 3D point needs no coarse levels).  Images are grey, as captured (the
    rectified-row test undistorts and rectifies the two point sets, not the images).
    """
    if len(xy_left) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    lk = _stereo_lk(cfg, levels)
    p0 = np.asarray(xy_left, np.float32).reshape(-1, 1, 2)
    g = np.asarray(guess_right, np.float32).reshape(-1, 1, 2)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(left, right, p0, g.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    ok = st.ravel() == 1
    p1 = p1.reshape(-1, 2)
    r = rig.rectification()
    rl = cv2.undistortPoints(p0, rig.cam0.K, rig.cam0.dist, R=r.R0, P=r.P0).reshape(-1, 2)
    rr = cv2.undistortPoints(p1.reshape(-1, 1, 2), rig.cam1.K, rig.cam1.dist, R=r.R1, P=r.P1).reshape(-1, 2)
    w, h = rig.cam1.size
    ok &= np.abs(rl[:, 1] - rr[:, 1]) <= cfg.epipolar_max_dy_px
    ok &= rl[:, 0] - rr[:, 0] > 0
    ok &= (p1[:, 0] >= 0) & (p1[:, 0] < w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] < h - 1)
    if fb_check:
        ok &= tracks_back(left, right, xy_left, p1, cfg, levels, where=ok)
    return p1.astype(np.float32), ok


def _stereo_lk(cfg: KltStereoParams, levels: int | None) -> dict:
    return dict(winSize=(cfg.klt_window, cfg.klt_window), maxLevel=cfg.klt_levels if levels is None else levels,
                criteria=KLT_CRITERIA)


def tracks_back(left: np.ndarray, right: np.ndarray, xy_left: np.ndarray, xy_right: np.ndarray, cfg: KltStereoParams,
                levels: int | None = None, where: np.ndarray | None = None) -> np.ndarray:
    """The forward-backward check of left-right matches: whether KLT from each right pixel back into the left
    image (seeded at its left pixel, the pyramid of :func:`stereo_right`) converges within ``cfg.fb_max_px``
    of it.  Only the matches set in ``where`` are tracked (the others are False): each point's track is
    independent of the others', so checking the survivors of cheaper tests last gives the same answer."""
    n = len(xy_left)
    out = np.zeros(n, bool)
    idx = np.arange(n) if where is None else np.flatnonzero(where)
    if len(idx) == 0:
        return out
    p0 = np.asarray(xy_left, np.float32).reshape(-1, 2)[idx].reshape(-1, 1, 2)
    p1 = np.asarray(xy_right, np.float32).reshape(-1, 2)[idx].reshape(-1, 1, 2)
    pb, stb, _ = cv2.calcOpticalFlowPyrLK(right, left, p1, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                          **_stereo_lk(cfg, levels))
    out[idx] = (stb.ravel() == 1) & (np.linalg.norm((pb - p0).reshape(-1, 2), axis=1) < cfg.fb_max_px)
    return out


def pose_to_rvec_tvec(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    return rvec.reshape(3, 1), T[:3, 3].reshape(3, 1).copy()


def rvec_tvec_to_pose(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(tvec, dtype=np.float64).reshape(3)
    return T


__all__ = ["undistort_px", "project", "triangulate", "refine_pose_lm", "PointObservations", "LMOptions", "RotationPrior", "RefineResult", "stereo_right", "tracks_back", "KltStereoParams",
           "pose_to_rvec_tvec", "rvec_tvec_to_pose", "skew"]
