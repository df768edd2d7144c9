"""On-line estimate of a constant stereo disparity offset from two or more keyframes (pure compute).

An offset ``d0`` (``d_measured = d_true + d0``: a yaw or principal-point error of the calibration) is
invisible in one stereo pair, but a point seen in stereo at two keyframes must move rigidly with the
camera, and an offset bends near and far points differently.  :func:`offset_from_two_keyframes` is a
small bundle adjustment in the rectified frame (relative pose, ``d0``, points; pixel residuals, Huber,
points eliminated by the Schur complement);
:func:`~stereopath.device.estimation.offset_window.offset_from_keyframes` the same over a window.
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
from stereopath.device.core.rig import Rectification

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RectifiedCamera:
    """The rectified left camera of a stereo rig: focal length and principal point (px), baseline (m)."""

    f: float
    cx: float
    cy: float
    baseline_m: float

    @property
    def fb(self) -> float:
        return self.f * self.baseline_m

    @staticmethod
    def of(rect: Rectification) -> RectifiedCamera:
        return RectifiedCamera(rect.f, rect.P0[0, 2], rect.P0[1, 2], rect.baseline_m)


@dataclass(frozen=True)
class KeyframePair:
    """The same points observed in stereo at keyframes A and B: (n, 3) rows ``(u, v, disparity)`` in the
    rectified left image of each, and the initial motion ``x_B = R_BA x_A + t_BA`` (rectified frames)."""

    A: np.ndarray
    B: np.ndarray
    R_BA: np.ndarray
    t_BA: np.ndarray


@dataclass(frozen=True)
class KeyframeObservations:
    """The same points observed in stereo at keyframes A and B (rectified ``(u, v, disparity)`` rows, as
    :class:`KeyframePair`) and the keyframes' poses (camera 1 to world) the frame loop gave them."""

    A: np.ndarray
    B: np.ndarray
    T_world_a: np.ndarray
    T_world_b: np.ndarray

    def copy(self) -> KeyframeObservations:
        return KeyframeObservations(self.A.copy(), self.B.copy(), self.T_world_a.copy(), self.T_world_b.copy())


@dataclass(frozen=True)
class SolveOptions:
    """How an offset or motion solve runs: Huber width (px), the fewest points it accepts, Gauss-Newton
    iterations, (offset solves) the variance inflation above which it gives up at once, and (the window's
    solve) the offset step below which it has converged: 1 % of the offset filter's floor
    (:attr:`OffsetFilter.floor_sigma`), which trusts no estimate more than that."""

    huber_px: float = 0.5
    min_points: int = 30
    iterations: int = 10
    max_inflation: float | None = None
    offset_step_px: float = 1e-3


@dataclass(frozen=True)
class _PairUnknowns:
    """The two-keyframe problem's unknowns: the motion, the offset, points (x/z, y/z, 1/z) in A's frame."""

    R: np.ndarray
    t: np.ndarray
    d0: float
    P: np.ndarray


@dataclass(frozen=True)
class PairEstimate:
    d0: float  # px, in the convention d_measured = d_true + d0
    sigma: float  # px, formal standard deviation scaled by the residuals
    n_points: int
    coupling: float = 0.0  # |correlation| of d0 with the translation along its best-correlated direction
    inflation: float = 1.0  # variance of d0 with the motion free over that with the motion known (>= 1)


def _residuals(x: _PairUnknowns, A: np.ndarray, B: np.ndarray,
               cam: RectifiedCamera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(n, 6) residuals: (u, v, d) at A and at B of points ``P`` = (x/z, y/z, 1/z) in A's frame."""
    R, t, d0, P = x.R, x.t, x.d0, x.P
    f, cx, cy, fb = cam.f, cam.cx, cam.cy, cam.fb
    XA = np.column_stack([P[:, 0], P[:, 1], np.ones(len(P))]) / P[:, 2:3]
    XB = XA @ R.T + t
    z = np.maximum(XB[:, 2], 1e-9)
    r = np.column_stack([f * P[:, 0] + cx - A[:, 0], f * P[:, 1] + cy - A[:, 1], fb * P[:, 2] + d0 - A[:, 2],
                         f * XB[:, 0] / z + cx - B[:, 0], f * XB[:, 1] / z + cy - B[:, 1], fb / z + d0 - B[:, 2]])
    return r, XA, XB, z


def _jacobians(R: np.ndarray, P: np.ndarray, XA: np.ndarray, XB: np.ndarray, z: np.ndarray, f: float,
               fb: float) -> tuple[np.ndarray, np.ndarray]:
    """Residual derivatives: global (n, 6, 7) over (dt, dtheta, d0), per point (n, 6, 3) over P."""
    n = len(z)
    dproj, dX = projection_and_motion_jacobians(XB, XA @ R.T, z, f, fb)
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


def projection_and_motion_jacobians(X: np.ndarray, RX: np.ndarray, z: np.ndarray, f: float,
                                     fb: float) -> tuple[np.ndarray, np.ndarray]:
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


def huber_weights(r: np.ndarray, z: np.ndarray, huber_px: float) -> np.ndarray:
    e = np.abs(r)
    w = np.where(e < huber_px, 1.0, huber_px / np.maximum(e, 1e-12))
    w[(z < 1e-6) | (e.max(1) > 20 * huber_px)] = 0.0
    return w


def _gauss_newton_step(x: _PairUnknowns, A: np.ndarray, B: np.ndarray, cam: RectifiedCamera, huber_px: float,
                       fix_pose: bool = False,
                       fix_offset: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """One Gauss-Newton step of the two-keyframe problem, the points eliminated (Schur complement):
    ``(dg, dp, S)`` with ``dg`` over (dt, dtheta, d0), ``dp`` per point and ``S`` the reduced system;
    None when singular.  ``fix_pose`` / ``fix_offset`` hold those unknowns."""
    r, XA, XB, z = _residuals(x, A, B, cam)
    w = huber_weights(r, z, huber_px)
    Jg, Jp = _jacobians(x.R, x.P, XA, XB, z, cam.f, cam.fb)
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


def _apply_step(x: _PairUnknowns, dg: np.ndarray, dp: np.ndarray) -> _PairUnknowns:
    P = x.P + dp
    P[:, 2] = np.maximum(P[:, 2], 1e-9)
    return _PairUnknowns(so3_exp(dg[3:6]) @ x.R, x.t + dg[:3], x.d0 + float(dg[6]), P)


def motion_with_offset(pair: KeyframePair, d0: float, cam: RectifiedCamera,
                       options: SolveOptions = SolveOptions()) -> tuple[np.ndarray, np.ndarray] | None:
    """The motion ``(R_BA, t_BA)`` between two keyframes that their stereo observations give under a
    known disparity offset ``d0`` (rows and frames as in :func:`offset_from_two_keyframes`), or None."""
    A = np.asarray(pair.A, float)
    B = np.asarray(pair.B, float)
    ok = np.isfinite(A).all(1) & np.isfinite(B).all(1) & (A[:, 2] - d0 > 0) & (B[:, 2] - d0 > 0)
    A, B = A[ok], B[ok]
    if len(A) < options.min_points:
        return None
    f, cx, cy, fb = cam.f, cam.cx, cam.cy, cam.fb
    P = np.column_stack([(A[:, 0] - cx) / f, (A[:, 1] - cy) / f, (A[:, 2] - d0) / fb])
    x = _PairUnknowns(np.asarray(pair.R_BA, float).copy(), np.asarray(pair.t_BA, float).reshape(3).copy(), d0, P)
    for _ in range(options.iterations):
        step = _gauss_newton_step(x, A, B, cam, options.huber_px, fix_offset=True)
        if step is None:
            return None
        dg, dp, _ = step
        moved = _apply_step(x, dg, dp)
        x = _PairUnknowns(moved.R, moved.t, d0, moved.P)  # the offset stays as given
        if np.abs(dg).max() < 1e-8:
            break
    return x.R, x.t


def offset_from_two_keyframes(pair: KeyframePair, cam: RectifiedCamera, options: SolveOptions = SolveOptions(),
                              fix_pose: bool = False) -> PairEstimate | None:
    """The disparity offset from points observed in stereo at two keyframes (rectified pixels).

    ``pair.A`` and ``pair.B`` are (n, 3) rows ``(u, v, disparity)`` of the same points in the rectified
    left image of keyframes A and B; ``pair.R_BA``, ``pair.t_BA`` the initial motion (``x_B = R x_A + t``,
    rectified camera frames).  Every point is a free 3D point (all its measurements are
    residuals: fixing its ray at A would dilute the estimate towards zero).  Returns None when
    there are too few points or the system is singular (no translation: no parallax).  With
    ``options.max_inflation``, a pair whose variance inflation at the initial motion exceeds it is not
    solved: the estimate returned has ``d0 = nan`` and that inflation (the filter ignores it)."""
    A = np.asarray(pair.A, float)
    B = np.asarray(pair.B, float)
    ok = np.isfinite(A).all(1) & np.isfinite(B).all(1) & (A[:, 2] > 0) & (B[:, 2] > 0)
    A, B = A[ok], B[ok]
    min_points, huber_px, max_inflation = options.min_points, options.huber_px, options.max_inflation
    if len(A) < min_points:
        return None
    f, cx, cy, fb = cam.f, cam.cx, cam.cy, cam.fb
    P = np.column_stack([(A[:, 0] - cx) / f, (A[:, 1] - cy) / f, A[:, 2] / fb])
    x = _PairUnknowns(np.asarray(pair.R_BA, float).copy(), np.asarray(pair.t_BA, float).reshape(3).copy(), 0.0, P)
    S = None
    for it in range(options.iterations):
        step = _gauss_newton_step(x, A, B, cam, huber_px, fix_pose=fix_pose)
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
        x = _apply_step(x, dg, dp)
        if np.abs(dg).max() < 1e-8:
            break
    d0 = x.d0
    r, *_ = _residuals(x, A, B, cam)
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


def offset_between_keyframes(rect: Rectification, pair: KeyframeObservations,
                             max_inflation: float | None = None) -> PairEstimate | None:
    """:func:`offset_from_two_keyframes` for keyframes at poses ``pair.T_world_a``, ``pair.T_world_b`` of a
    rig with rectification ``rect`` (``R0``, ``P0``, ``f``, ``baseline_m``)."""
    R_ba, t_ba = rectified_motion(rect, pair.T_world_a, pair.T_world_b)
    return offset_from_two_keyframes(KeyframePair(pair.A, pair.B, R_ba, t_ba), RectifiedCamera.of(rect),
                                     SolveOptions(max_inflation=max_inflation))


def rectified_motion(rect: Rectification, T_world_a: np.ndarray, T_world_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe A -> keyframe B (``x_B = R x_A + t``) in the rectified frames of camera 1."""
    T_ba = invert_pose(T_world_b) @ T_world_a
    return rect.R0 @ T_ba[:3, :3] @ rect.R0.T, rect.R0 @ T_ba[:3, 3]


def offset_correction_of_motion(rect: Rectification, pair: KeyframeObservations, d0_used: float,
                                d0_new: float) -> np.ndarray | None:
    """How learning the offset changes the motion between two keyframes: ``D`` (4x4, in B's camera
    frame) such that ``D @ T_ba`` is the motion ``T_ba = inv(T_world_b) @ T_world_a`` measured with
    ``d0_new`` instead of ``d0_used``.  Both motions come from the same two-keyframe solve, so
    ``D`` holds the offset's effect only; None when either solve fails."""
    R_ba, t_ba = rectified_motion(rect, pair.T_world_a, pair.T_world_b)
    cam = RectifiedCamera.of(rect)
    used = motion_with_offset(KeyframePair(pair.A, pair.B, R_ba, t_ba), d0_used, cam)
    new = motion_with_offset(KeyframePair(pair.A, pair.B, R_ba, t_ba), d0_new, cam)
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
    pairs: deque[tuple[int, KeyframeObservations]] = field(init=False)

    def __post_init__(self) -> None:
        self.pairs = deque(maxlen=self.max_pairs)

    def add(self, kf: int, pair: KeyframeObservations) -> None:
        """Keyframe ``kf``'s pair with keyframe ``kf - 1``; a gap in the keyframes restarts the chain."""
        if self.pairs and self.pairs[-1][0] != kf - 1:
            self.pairs.clear()
        self.pairs.append((kf, pair.copy()))

    def correction(self, rect: Rectification, kf: int, T_world_cam: np.ndarray, d0_used: float, d0_new: float,
                   max_deg: float) -> np.ndarray | None:
        pairs, self.pairs = self.pairs, deque(maxlen=self.max_pairs)  # used once
        if not pairs or pairs[-1][0] != kf:
            return None
        E = np.eye(4)  # the re-measured current camera in the tracked one's frame
        length = 0.0
        for _, pair in pairs:
            T_ba = invert_pose(pair.T_world_b) @ pair.T_world_a
            D = offset_correction_of_motion(rect, pair, d0_used, d0_new)
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
