"""The disparity offset over a window of keyframes (pure compute): every point seen in stereo at two of
the last keyframes or more is a free 3D point, every motion but the first's and the offset are free.
The generalisation of :func:`~stereopath.device.estimation.disparity_offset.offset_from_two_keyframes`;
design and reasons: docs/architecture.md, "Disparity offset".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereopath.device.core.geometry import so3_exp
from stereopath.device.core.rig import Rectification
from stereopath.device.estimation.disparity_offset import (PairEstimate, RectifiedCamera, SolveOptions, huber_weights,
                                                          projection_and_motion_jacobians, rectified_motion)


def offset_from_keyframes(views: list[tuple[np.ndarray, np.ndarray]], motions: list[tuple[np.ndarray, np.ndarray]],
                          cam: RectifiedCamera, options: SolveOptions = SolveOptions()) -> PairEstimate | None:
    """The disparity offset from points observed in stereo at several keyframes (a window).

    ``views[j]`` is ``(ids, obs)``: point ids and (n, 3) rectified ``(u, v, disparity)`` rows at keyframe
    ``j``; ``motions[j]`` the initial ``(R, t)`` from keyframe 0 to keyframe ``j`` (``x_j = R x_0 + t``,
    rectified frames; ``motions[0]`` is the identity and stays fixed).  Every point seen at two keyframes
    or more is a free 3D point; every other motion and the offset are free (as
    :func:`offset_from_two_keyframes`, of which this is the generalisation)."""
    f, cx, cy, fb = cam.f, cam.cx, cam.cy, cam.fb
    huber_px, min_points, max_inflation = options.huber_px, options.min_points, options.max_inflation
    K = len(views)
    if K < 2:
        return None
    kf_of, id_of, M = [], [], []
    for j, (ids, obs) in enumerate(views):
        obs = np.asarray(obs, float).reshape(-1, 3)
        ok = np.isfinite(obs).all(1) & (obs[:, 2] > 0)
        kf_of.append(np.full(int(ok.sum()), j))
        id_of.append(np.asarray(ids, np.int64)[ok])
        M.append(obs[ok])
    kf_of, id_of, M = np.concatenate(kf_of), np.concatenate(id_of), np.concatenate(M)
    uniq, counts = np.unique(id_of, return_counts=True)
    keep = uniq[counts >= 2]  # points measured at two keyframes or more
    if len(keep) < min_points:
        return None
    sel = np.isin(id_of, keep)
    kf_of, pt_of, M = kf_of[sel], np.searchsorted(keep, id_of[sel]), M[sel]
    n_pts = len(keep)
    R = [np.asarray(m[0], float).copy() for m in motions]
    t = [np.asarray(m[1], float).reshape(3).copy() for m in motions]
    ng = 6 * (K - 1) + 1
    # observations grouped by point (sums per point by reduceat)
    order = np.argsort(pt_of, kind="stable")
    kf_of, pt_of, M = kf_of[order], pt_of[order], M[order]
    starts = np.flatnonzero(np.r_[True, pt_of[1:] != pt_of[:-1]])
    # points (x/z, y/z, 1/z) in keyframe 0's frame, from their first observation (the stable sort keeps
    # each point's observations in keyframe order)
    u, v, d = M[starts].T
    zc = fb / np.maximum(d, 0.5)
    Xc = np.column_stack([(u - cx) / f * zc, (v - cy) / f * zc, zc])
    j0 = kf_of[starts]
    Rs, ts = np.stack(R), np.stack(t)
    X0 = np.einsum("nji,nj->ni", Rs[j0], Xc - ts[j0])  # R^T (Xc - t)
    P = np.column_stack([X0[:, 0] / X0[:, 2], X0[:, 1] / X0[:, 2], 1.0 / np.maximum(X0[:, 2], 1e-6)])
    d0 = 0.0
    S = None
    seen = _WindowObservations(M, kf_of, pt_of)
    for it in range(options.iterations):
        r, Jg, Jp, z = _window_system(_WindowUnknowns(R, t, d0, P), seen, cam)
        w = huber_weights(r, z, huber_px)
        Jgw = Jg * w[:, :, None]
        Jpw = Jp * w[:, :, None]
        Hgg = Jgw.reshape(-1, ng).T @ Jg.reshape(-1, ng)
        bg = Jgw.reshape(-1, ng).T @ r.reshape(-1)
        Hgp = np.add.reduceat(np.matmul(Jgw.transpose(0, 2, 1), Jp), starts, axis=0)  # (points, ng, 3)
        Hpp = np.add.reduceat(np.matmul(Jpw.transpose(0, 2, 1), Jp), starts, axis=0) + 1e-9 * np.eye(3)
        bp = np.add.reduceat(np.matmul(Jpw.transpose(0, 2, 1), r[:, :, None])[:, :, 0], starts, axis=0)
        try:
            Hpp_inv = np.linalg.inv(Hpp)
            W = np.matmul(Hgp, Hpp_inv)
            S = Hgg - W.transpose(1, 0, 2).reshape(ng, -1) @ Hgp.transpose(1, 0, 2).reshape(ng, -1).T \
                + 1e-9 * np.eye(ng)
            s = bg - W.transpose(1, 0, 2).reshape(ng, -1) @ bp.reshape(-1)
            if it == 0 and max_inflation is not None:
                inflation = float(np.linalg.inv(S)[-1, -1] * S[-1, -1])
                if inflation > max_inflation:
                    return PairEstimate(float("nan"), float("inf"), n_pts, 0.0, inflation)
            dg = -np.linalg.solve(S, s)
        except np.linalg.LinAlgError:
            return None
        dp = -np.matmul(Hpp_inv, (bp + np.matmul(Hgp.transpose(0, 2, 1), dg))[:, :, None])[:, :, 0]
        for j in range(1, K):
            o = 6 * (j - 1)
            R[j] = so3_exp(dg[o + 3:o + 6]) @ R[j]
            t[j] = t[j] + dg[o:o + 3]
        d0 += float(dg[-1])
        P = P + dp
        P[:, 2] = np.maximum(P[:, 2], 1e-9)
        # converged: the offset, the one unknown the window is solved for, moves by less than its step
        # (the motions and points are nuisance unknowns: their last micrometres do not move the offset)
        if abs(dg[-1]) < options.offset_step_px:
            break
    r, _, _, z = _window_system(_WindowUnknowns(R, t, d0, P), seen, cam, jacobians=False)
    # inlier points: every residual of every observation under 3 Huber widths (as the pair counts them)
    point_ok = np.minimum.reduceat((np.abs(r).max(1) < 3 * huber_px).astype(np.int8), starts) > 0
    inl = point_ok[pt_of]
    n_pts_inl = int(point_ok.sum())
    if S is None or n_pts_inl < min_points:
        return None
    try:
        cov = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return None
    dof = max(3 * int(inl.sum()) - 3 * n_pts_inl - ng, 1)
    s2 = float(np.sum(r[inl] ** 2) / dof)
    var = cov[-1, -1] * max(s2, 1e-6)
    if not np.isfinite(var) or var <= 0:
        return None
    inflation = float(max(cov[-1, -1] * S[-1, -1], 1.0))
    return PairEstimate(float(d0), float(np.sqrt(var)), n_pts_inl, 0.0, inflation)


@dataclass(frozen=True)
class _WindowUnknowns:
    """The window's unknowns: motions from keyframe 0 (the first fixed), the offset, the points (x/z, y/z, 1/z)."""

    R: list[np.ndarray]
    t: list[np.ndarray]
    d0: float
    P: np.ndarray


@dataclass(frozen=True)
class _WindowObservations:
    """Every observation of the window: (o, 3) rectified rows, and each one's keyframe and point index."""

    M: np.ndarray
    kf_of: np.ndarray
    pt_of: np.ndarray


def _window_system(x: _WindowUnknowns, seen: _WindowObservations, cam: RectifiedCamera,
                   jacobians: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray]:
    """Residuals (o, 3) of every observation, and their Jacobians over (motions, d0) (o, 3, ng) and the point (o, 3, 3)."""
    R, t, d0, P = x.R, x.t, x.d0, x.P
    M, kf_of, pt_of = seen.M, seen.kf_of, seen.pt_of
    f, cx, cy, fb = cam.f, cam.cx, cam.cy, cam.fb
    ng = 6 * (len(R) - 1) + 1
    Ra = np.stack(R)[kf_of]
    ta = np.stack(t)[kf_of]
    Pp = P[pt_of]
    X0 = np.column_stack([Pp[:, 0], Pp[:, 1], np.ones(len(Pp))]) / Pp[:, 2:3]
    RX = np.matmul(Ra, X0[:, :, None])[:, :, 0]
    Xj = RX + ta
    z = np.maximum(Xj[:, 2], 1e-9)
    r = np.column_stack([f * Xj[:, 0] / z + cx - M[:, 0], f * Xj[:, 1] / z + cy - M[:, 1], fb / z + d0 - M[:, 2]])
    if not jacobians:
        return r, None, None, z
    n = len(z)
    dproj, dX = projection_and_motion_jacobians(Xj, RX, z, f, fb)
    Jpose = np.matmul(dproj, dX)
    Jg = np.zeros((n, 3, ng))
    moving = kf_of > 0
    cols = 6 * (kf_of[moving] - 1)
    for c in range(6):
        Jg[np.flatnonzero(moving), :, cols + c] = Jpose[moving, :, c]
    Jg[:, 2, -1] = 1.0
    rho = Pp[:, 2]
    dXA = np.zeros((n, 3, 3))
    dXA[:, 0, 0] = dXA[:, 1, 1] = 1.0 / rho
    dXA[:, 0, 2] = -Pp[:, 0] / rho**2
    dXA[:, 1, 2] = -Pp[:, 1] / rho**2
    dXA[:, 2, 2] = -1.0 / rho**2
    Jp = np.matmul(np.matmul(dproj, Ra), dXA)
    return r, Jg, Jp, z


def offset_over_keyframes(rect: Rectification, views: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                          max_inflation: float | None = None) -> PairEstimate | None:
    """:func:`offset_from_keyframes` for keyframe views ``(ids, rectified rows, T_world_cam)`` of a rig with
    rectification ``rect``; the motions start from the poses."""
    T0 = views[0][2]
    motions = [rectified_motion(rect, T0, T) for _, _, T in views]
    motions[0] = (np.eye(3), np.zeros(3))
    return offset_from_keyframes([(ids, obs) for ids, obs, _ in views], motions, RectifiedCamera.of(rect),
                                 SolveOptions(max_inflation=max_inflation))
