"""On-line estimate of a constant stereo disparity offset from two or more keyframes (pure compute).

An offset ``d0`` (``d_measured = d_true + d0``: a yaw or principal-point error of the calibration) is
invisible in one stereo pair, but a point seen in stereo at two keyframes must move rigidly with the
camera, and an offset bends near and far points differently.  :func:`offset_from_two_keyframes` is a
small bundle adjustment in the rectified frame (relative pose, ``d0``, points; pixel residuals, Huber,
points eliminated by the Schur complement); :func:`offset_from_keyframes` the same over a window.
:class:`OffsetFilter` fuses the estimates slowly and bounded, and ignores those whose *variance
inflation* (the offset's variance with the motion free over that with it known) says the motion could
absorb the offset.  Design and reasons: docs/architecture.md, "Disparity offset".
"""

from __future__ import annotations

import logging

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from stereopath.device.core.geometry import invert_pose, project_to_se3, rotation_angle_deg, so3_exp

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PairEstimate:
    d0: float  # px, in the convention d_measured = d_true + d0
    sigma: float  # px, formal standard deviation scaled by the residuals
    n_points: int
    coupling: float = 0.0  # |correlation| of d0 with the translation along its best-correlated direction
    inflation: float = 1.0  # variance of d0 with the motion free over that with the motion known (>= 1)


def _residuals(R, t, d0, P, A, B, f, cx, cy, fb):
    """(n, 6) residuals: (u, v, d) at A and at B of points ``P`` = (x/z, y/z, 1/z) in A's frame."""
    XA = np.column_stack([P[:, 0], P[:, 1], np.ones(len(P))]) / P[:, 2:3]
    XB = XA @ R.T + t
    z = np.maximum(XB[:, 2], 1e-9)
    r = np.column_stack([f * P[:, 0] + cx - A[:, 0], f * P[:, 1] + cy - A[:, 1], fb * P[:, 2] + d0 - A[:, 2],
                         f * XB[:, 0] / z + cx - B[:, 0], f * XB[:, 1] / z + cy - B[:, 1], fb / z + d0 - B[:, 2]])
    return r, XA, XB, z


def _jacobians(R, P, XA, XB, z, f, fb):
    """Residual derivatives: global (n, 6, 7) over (dt, dtheta, d0), per point (n, 6, 3) over P."""
    n = len(z)
    dproj, dX = _projection_and_motion_jacobians(XB, XA @ R.T, z, f, fb)
    Jg = np.zeros((n, 6, 7))
    Jg[:, 3:, :6] = np.einsum("nij,njk->nik", dproj, dX)
    Jg[:, 2, 6] = 1.0
    Jg[:, 5, 6] = 1.0
    rho = P[:, 2]
    dXA = np.zeros((n, 3, 3))  # d(XA)/d(P)
    dXA[:, 0, 0] = dXA[:, 1, 1] = 1.0 / rho
    dXA[:, 0, 2] = -P[:, 0] / rho**2
    dXA[:, 1, 2] = -P[:, 1] / rho**2
    dXA[:, 2, 2] = -1.0 / rho**2
    Jp = np.zeros((n, 6, 3))
    Jp[:, 0, 0] = Jp[:, 1, 1] = f
    Jp[:, 2, 2] = fb
    Jp[:, 3:] = np.einsum("nij,jk,nkl->nil", dproj, R, dXA)
    return Jg, Jp


def _projection_and_motion_jacobians(X, RX, z, f, fb):
    """``d(u, v, d)/dX`` (n, 3, 3) of rectified points ``X`` (depth ``z``), and ``dX/d(dt, dtheta)`` (n, 3, 6)
    for ``X = exp(dtheta) R x + t + dt`` with ``RX = R x`` (``d(exp(w) R x)/dw = -[R x]x``)."""
    n = len(z)
    dproj = np.zeros((n, 3, 3))
    dproj[:, 0, 0] = f / z
    dproj[:, 0, 2] = -f * X[:, 0] / z**2
    dproj[:, 1, 1] = f / z
    dproj[:, 1, 2] = -f * X[:, 1] / z**2
    dproj[:, 2, 2] = -fb / z**2
    dX = np.zeros((n, 3, 6))
    dX[:, :, :3] = np.eye(3)
    dX[:, :, 3:] = -_skew_rows(RX)
    return dproj, dX


def _skew_rows(v: np.ndarray) -> np.ndarray:
    """``[v]x`` for each row of ``v``: (n, 3) -> (n, 3, 3)."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -v[:, 2], v[:, 1]
    S[:, 1, 0], S[:, 1, 2] = v[:, 2], -v[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -v[:, 1], v[:, 0]
    return S


def _weights(r: np.ndarray, z: np.ndarray, huber_px: float) -> np.ndarray:
    e = np.abs(r)
    w = np.where(e < huber_px, 1.0, huber_px / np.maximum(e, 1e-12))
    w[(z < 1e-6) | (e.max(1) > 20 * huber_px)] = 0.0
    return w


def _gauss_newton_step(R, t, d0, P, A, B, f, cx, cy, fb, huber_px, fix_pose=False, fix_offset=False):
    """One Gauss-Newton step of the two-keyframe problem, the points eliminated (Schur complement):
    ``(dg, dp, S)`` with ``dg`` over (dt, dtheta, d0), ``dp`` per point and ``S`` the reduced system;
    None when singular.  ``fix_pose`` / ``fix_offset`` hold those unknowns."""
    r, XA, XB, z = _residuals(R, t, d0, P, A, B, f, cx, cy, fb)
    w = _weights(r, z, huber_px)
    Jg, Jp = _jacobians(R, P, XA, XB, z, f, fb)
    if fix_pose:
        Jg[:, :, :6] = 0.0
    if fix_offset:
        Jg[:, :, 6] = 0.0
    Hgg = np.einsum("nki,nk,nkj->ij", Jg, w, Jg)
    Hgp = np.einsum("nki,nk,nkj->nij", Jg, w, Jp)  # (n, 7, 3)
    Hpp = np.einsum("nki,nk,nkj->nij", Jp, w, Jp) + 1e-9 * np.eye(3)
    bg = np.einsum("nki,nk,nk->i", Jg, w, r)
    bp = np.einsum("nki,nk,nk->ni", Jp, w, r)
    try:
        Hpp_inv = np.linalg.inv(Hpp)
        W = np.einsum("nij,njk->nik", Hgp, Hpp_inv)  # (n, 7, 3)
        S = Hgg - np.einsum("nij,nkj->ik", W, Hgp)
        s = bg - np.einsum("nij,nj->i", W, bp)
        S = S + (1.0 if fix_pose else 1e-9) * np.diag([1.0] * 6 + [1e-9]) + np.diag([0.0] * 6 + [float(fix_offset)])
        dg = -np.linalg.solve(S, s)
    except np.linalg.LinAlgError:
        return None
    dp = -np.einsum("nij,nj->ni", Hpp_inv, bp + np.einsum("nji,j->ni", Hgp, dg))
    return dg, dp, S


def _apply_step(R, t, d0, P, dg, dp):
    P = P + dp
    P[:, 2] = np.maximum(P[:, 2], 1e-9)
    return so3_exp(dg[3:6]) @ R, t + dg[:3], d0 + float(dg[6]), P


def motion_with_offset(A: np.ndarray, B: np.ndarray, R_BA: np.ndarray, t_BA: np.ndarray, d0: float, f: float,
                       cx: float, cy: float, baseline_m: float, huber_px: float = 0.5, min_points: int = 30,
                       iterations: int = 10) -> tuple[np.ndarray, np.ndarray] | None:
    """The motion ``(R_BA, t_BA)`` between two keyframes that their stereo observations give under a
    known disparity offset ``d0`` (rows and frames as in :func:`offset_from_two_keyframes`), or None."""
    A = np.asarray(A, float)
    B = np.asarray(B, float)
    ok = np.isfinite(A).all(1) & np.isfinite(B).all(1) & (A[:, 2] - d0 > 0) & (B[:, 2] - d0 > 0)
    A, B = A[ok], B[ok]
    if len(A) < min_points:
        return None
    fb = f * baseline_m
    P = np.column_stack([(A[:, 0] - cx) / f, (A[:, 1] - cy) / f, (A[:, 2] - d0) / fb])
    R, t = np.asarray(R_BA, float).copy(), np.asarray(t_BA, float).reshape(3).copy()
    for _ in range(iterations):
        step = _gauss_newton_step(R, t, d0, P, A, B, f, cx, cy, fb, huber_px, fix_offset=True)
        if step is None:
            return None
        dg, dp, _ = step
        R, t, _, P = _apply_step(R, t, d0, P, dg, dp)
        if np.abs(dg).max() < 1e-8:
            break
    return R, t


def offset_from_two_keyframes(A: np.ndarray, B: np.ndarray, R_BA: np.ndarray, t_BA: np.ndarray, f: float,
                              cx: float, cy: float, baseline_m: float, huber_px: float = 0.5,
                              min_points: int = 30, iterations: int = 10, fix_pose: bool = False,
                              max_inflation: float | None = None) -> PairEstimate | None:
    """The disparity offset from points observed in stereo at two keyframes (rectified pixels).

    ``A`` and ``B`` are (n, 3) rows ``(u, v, disparity)`` of the same points in the rectified
    left image of keyframes A and B; ``R_BA``, ``t_BA`` the initial motion (``x_B = R x_A + t``,
    rectified camera frames).  Every point is a free 3D point (all its measurements are
    residuals: fixing its ray at A would dilute the estimate towards zero).  Returns None when
    there are too few points or the system is singular (no translation: no parallax).  With
    ``max_inflation``, a pair whose variance inflation at the initial motion exceeds it is not
    solved: the estimate returned has ``d0 = nan`` and that inflation (the filter ignores it)."""
    A = np.asarray(A, float)
    B = np.asarray(B, float)
    ok = np.isfinite(A).all(1) & np.isfinite(B).all(1) & (A[:, 2] > 0) & (B[:, 2] > 0)
    A, B = A[ok], B[ok]
    if len(A) < min_points:
        return None
    fb = f * baseline_m
    P = np.column_stack([(A[:, 0] - cx) / f, (A[:, 1] - cy) / f, A[:, 2] / fb])
    R, t, d0 = np.asarray(R_BA, float).copy(), np.asarray(t_BA, float).reshape(3).copy(), 0.0
    S = None
    for it in range(iterations):
        step = _gauss_newton_step(R, t, d0, P, A, B, f, cx, cy, fb, huber_px, fix_pose=fix_pose)
        if step is None:
            return None
        dg, dp, S = step
        if it == 0 and max_inflation is not None and not fix_pose:
            try:
                inflation = float(np.linalg.inv(S)[6, 6] * S[6, 6])
            except np.linalg.LinAlgError:
                return None
            if inflation > max_inflation:
                return PairEstimate(float("nan"), float("inf"), len(A), 0.0, inflation)
        R, t, d0, P = _apply_step(R, t, d0, P, dg, dp)
        if np.abs(dg).max() < 1e-8:
            break
    r, *_ = _residuals(R, t, d0, P, A, B, f, cx, cy, fb)
    inl = np.abs(r).max(1) < 3 * huber_px
    n_inl = int(inl.sum())
    if n_inl < min_points or S is None:
        return None
    try:
        cov = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return None
    # residual scale over the inliers (6 residuals and 3 unknowns per point, 7 shared)
    dof = max(3 * n_inl - 7, 1)
    s2 = float(np.sum(r[inl] ** 2) / dof)
    var = cov[6, 6] * max(s2, 1e-6)
    if not np.isfinite(var) or var <= 0:
        return None
    # how much of d0 a change of the translation could explain (multiple correlation with t)
    Ctt, Ctd = cov[:3, :3], cov[:3, 6]
    try:
        coupling = float(np.sqrt(max(Ctd @ np.linalg.solve(Ctt, Ctd) / cov[6, 6], 0.0))) if not fix_pose else 0.0
    except np.linalg.LinAlgError:
        coupling = 1.0
    # S is the offset's information after the points were eliminated (motion known: S[6, 6])
    inflation = 1.0 if fix_pose else float(max(cov[6, 6] * S[6, 6], 1.0))
    return PairEstimate(float(d0), float(np.sqrt(var)), n_inl, min(coupling, 1.0), inflation)


def offset_between_keyframes(rect, A: np.ndarray, B: np.ndarray, T_world_a: np.ndarray, T_world_b: np.ndarray,
                             max_inflation: float | None = None) -> PairEstimate | None:
    """:func:`offset_from_two_keyframes` for keyframes at poses ``T_world_a``, ``T_world_b`` (camera 1 to
    world) of a rig with rectification ``rect`` (``R0``, ``P0``, ``f``, ``baseline_m``)."""
    R_ba, t_ba = _rectified_motion(rect, T_world_a, T_world_b)
    return offset_from_two_keyframes(A, B, R_ba, t_ba, rect.f, rect.P0[0, 2], rect.P0[1, 2], rect.baseline_m,
                                     max_inflation=max_inflation)


def _rectified_motion(rect, T_world_a: np.ndarray, T_world_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe A -> keyframe B (``x_B = R x_A + t``) in the rectified frames of camera 1."""
    T_ba = invert_pose(T_world_b) @ T_world_a
    return rect.R0 @ T_ba[:3, :3] @ rect.R0.T, rect.R0 @ T_ba[:3, 3]


def offset_correction_of_motion(rect, A: np.ndarray, B: np.ndarray, T_world_a: np.ndarray, T_world_b: np.ndarray,
                                d0_used: float, d0_new: float) -> np.ndarray | None:
    """How learning the offset changes the motion between two keyframes: ``D`` (4x4, in B's camera
    frame) such that ``D @ T_ba`` is the motion ``T_ba = inv(T_world_b) @ T_world_a`` measured with
    ``d0_new`` instead of ``d0_used``.  Both motions come from the same two-keyframe solve, so
    ``D`` holds the offset's effect only; None when either solve fails."""
    R_ba, t_ba = _rectified_motion(rect, T_world_a, T_world_b)
    args = (rect.f, rect.P0[0, 2], rect.P0[1, 2], rect.baseline_m)
    used = motion_with_offset(A, B, R_ba, t_ba, d0_used, *args)
    new = motion_with_offset(A, B, R_ba, t_ba, d0_new, *args)
    if used is None or new is None:
        return None
    M = []
    for R, t in (used, new):  # back from the rectified frames to the cameras'
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = rect.R0.T @ R @ rect.R0, rect.R0.T @ t
        M.append(T)
    return M[1] @ invert_pose(M[0])


@dataclass
class OffsetFilter:
    """Slow, bounded fusion of per-pair offset estimates (information-weighted, prior at ``prior``)."""

    prior: float = 0.0
    prior_sigma: float = 0.15  # px: without evidence the offset stays near the prior
    floor_sigma: float = 0.1  # px: no single pair is trusted more than this
    max_sigma: float = 0.2  # px: poorer estimates are ignored
    # estimates whose motion could absorb > 6/7 of the offset's information are ignored: driving forward
    # stays below, orbits and slides past a scene lie far above
    max_inflation: float = 7.0
    gate_sigma: float = 3.0  # estimates farther than this many sigmas (combined) from the value are ignored
    bound: float = 1.0  # px: |offset - prior| never exceeds this
    min_pairs: int = 3  # estimates fused before the offset is used

    def __post_init__(self) -> None:
        self._info = 1.0 / self.prior_sigma**2
        self._sum = self.prior * self._info
        self.n = 0
        self.rejected = 0
        self.unidentified = 0

    @property
    def value(self) -> float:
        v = self._sum / self._info
        return float(np.clip(v, self.prior - self.bound, self.prior + self.bound))

    @property
    def sigma(self) -> float:
        return float(1.0 / np.sqrt(self._info))

    @property
    def ready(self) -> bool:
        return self.n >= self.min_pairs

    def update(self, est: PairEstimate | None) -> bool:
        """Fuse one estimate; returns whether it was used."""
        if est is not None and est.inflation > self.max_inflation:
            self.unidentified += 1
            return False
        if est is None or not np.isfinite(est.d0) or est.sigma > self.max_sigma:
            return False
        sig = max(est.sigma, self.floor_sigma)
        if self.n >= self.min_pairs and abs(est.d0 - self.value) > self.gate_sigma * np.hypot(sig, self.sigma):
            self.rejected += 1
            return False
        info = 1.0 / sig**2
        self._info += info
        self._sum += info * est.d0
        self.n += 1
        return True


@dataclass
class PriorPath:
    """The keyframe pairs measured with the prior offset (the last ``max_pairs`` of one unbroken chain),
    and the one correction that re-measures them once the offset is learned (pure compute).

    ``correction`` re-solves each pair with the learned offset (:func:`offset_correction_of_motion`),
    chains the differences and returns the rigid motion of the live state (world frame) that moves the
    current keyframe where the re-measured chain puts it, and forgets the pairs; None when the chain does
    not end at that keyframe, or the correction is implausible (over ``max_fraction`` of the chain's length or
    ``max_deg``).  A pair whose solve fails keeps its tracked motion."""

    max_pairs: int = 32
    max_fraction: float = 0.05  # a learned offset re-measures depths by a few per cent at most
    pairs: deque = field(init=False)

    def __post_init__(self) -> None:
        self.pairs = deque(maxlen=self.max_pairs)

    def add(self, kf: int, A: np.ndarray, B: np.ndarray, T_world_a: np.ndarray, T_world_b: np.ndarray) -> None:
        """Keyframe ``kf``'s pair with keyframe ``kf - 1``; a gap in the keyframes restarts the chain."""
        if self.pairs and self.pairs[-1][0] != kf - 1:
            self.pairs.clear()
        self.pairs.append((kf, A.copy(), B.copy(), T_world_a.copy(), T_world_b.copy()))

    def correction(self, rect, kf: int, T_world_cam: np.ndarray, d0_used: float, d0_new: float,
                   max_deg: float) -> np.ndarray | None:
        pairs, self.pairs = self.pairs, deque(maxlen=self.max_pairs)  # used once
        if not pairs or pairs[-1][0] != kf:
            return None
        E = np.eye(4)  # the re-measured current camera in the tracked one's frame
        length = 0.0
        for _, A, B, T_a, T_b in pairs:
            T_ba = invert_pose(T_b) @ T_a
            D = offset_correction_of_motion(rect, A, B, T_a, T_b, d0_used, d0_new)
            E = T_ba @ E @ invert_pose(T_ba) @ (np.eye(4) if D is None else invert_pose(D))
            length += float(np.linalg.norm(T_ba[:3, 3]))
        shift, ang = float(np.linalg.norm(E[:3, 3])), rotation_angle_deg(E[:3, :3])
        if shift > self.max_fraction * length or ang > max_deg:
            log.info("offset %.3f px: path correction of %.4f m / %.2f deg over %.2f m rejected", d0_new, shift, ang,
                     length)
            return None
        log.info("offset %.3f px learned: the path since %d keyframes back moves %.4f m, %.3f deg", d0_new,
                 len(pairs), shift, ang)
        return project_to_se3(T_world_cam @ E @ invert_pose(T_world_cam))


def offset_from_keyframes(views: list, motions: list, f: float, cx: float, cy: float, baseline_m: float,
                          huber_px: float = 0.5, min_points: int = 30, iterations: int = 10,
                          max_inflation: float | None = None) -> PairEstimate | None:
    """The disparity offset from points observed in stereo at several keyframes (a window).

    ``views[j]`` is ``(ids, obs)``: point ids and (n, 3) rectified ``(u, v, disparity)`` rows at keyframe
    ``j``; ``motions[j]`` the initial ``(R, t)`` from keyframe 0 to keyframe ``j`` (``x_j = R x_0 + t``,
    rectified frames; ``motions[0]`` is the identity and stays fixed).  Every point seen at two keyframes
    or more is a free 3D point; every other motion and the offset are free (as
    :func:`offset_from_two_keyframes`, of which this is the generalisation)."""
    fb = f * baseline_m
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
    for it in range(iterations):
        r, Jg, Jp, z = _window_system(R, t, d0, P, M, kf_of, pt_of, f, cx, cy, fb, ng)
        w = _weights(r, z, huber_px)
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
        # converged: the offset moves by less than 1e-4 px and the motions by micrometres / microradians
        if abs(dg[-1]) < 1e-4 and np.abs(dg[:-1]).max(initial=0.0) < 1e-6:
            break
    r, _, _, z = _window_system(R, t, d0, P, M, kf_of, pt_of, f, cx, cy, fb, ng, jacobians=False)
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


def _window_system(R, t, d0, P, M, kf_of, pt_of, f, cx, cy, fb, ng, jacobians=True):
    """Residuals (o, 3) of every observation, and their Jacobians over (motions, d0) (o, 3, ng) and the point (o, 3, 3)."""
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
    dproj, dX = _projection_and_motion_jacobians(Xj, RX, z, f, fb)
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


def offset_over_keyframes(rect, views: list, max_inflation: float | None = None) -> PairEstimate | None:
    """:func:`offset_from_keyframes` for keyframe views ``(ids, rectified rows, T_world_cam)`` of a rig with
    rectification ``rect``; the motions start from the poses."""
    T0 = views[0][2]
    motions = [_rectified_motion(rect, T0, T) for _, _, T in views]
    motions[0] = (np.eye(3), np.zeros(3))
    return offset_from_keyframes([(ids, obs) for ids, obs, _ in views], motions, rect.f, rect.P0[0, 2],
                                 rect.P0[1, 2], rect.baseline_m, max_inflation=max_inflation)
