"""Two-view geometry: relative rotation and translation direction from matched pixels.

Pure compute.  Follows the reference paper's step 2: RANSAC fundamental matrix F
(10,000 trials in the paper), essential matrix ``E = K2^T F K1``, and
``cv2.recoverPose`` for R and the direction of t; optionally refined by
Levenberg-Marquardt on the Sampson error of the inliers.

Convention: ``x_cam2 = R @ x_cam1 + t`` (OpenCV's ``recoverPose``), i.e. ``[R|t]``
is ``T_cam2_cam1``; ``t`` is a unit vector (scale is unobservable).  The motion
of the camera, ``T_cam1_cam2``, is the inverse.  Euler angles for reports use
``R = Rx Ry Rz`` (the paper's Eq. 1).

Degenerate cases are detected and reported in :attr:`TwoViewResult.status`
instead of raising:

* ``too_few_matches`` - fewer usable (finite, distinct) matches than ``min_matches``;
* ``pure_rotation`` - a rotation-only model explains the matches about as well as F
  (no measurable parallax): ``R`` from the rotation fit, ``t = None``;
* ``planar`` - a homography explains about as many matches as F (F is not
  determined by a plane): ``R, t`` from the homography decomposition;
* ``failed`` - the estimators found no consistent model;
* ``ok`` - R and t from F / E.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Literal, Mapping

import cv2
import numpy as np

from stereopath.device.core.config import check_ranges, from_mapping, ranged
from stereopath.device.errors import ConfigError
from stereopath.device.core.geometry import matrix_to_euler_xyz, project_to_so3, skew, so3_exp

log = logging.getLogger(__name__)

__all__ = ["TwoViewConfig", "TwoViewResult", "relative_pose", "rotation_only", "euler_xyz_deg"]

Status = Literal["ok", "too_few_matches", "pure_rotation", "planar", "failed"]


# RANSAC trials of the rotation-only model.
ROTATION_ITERS = 300
# Homography / rotation models are judged by a 2-D transfer error, F by a 1-D epipolar
# distance: compare them at threshold_px * this factor (chi-square 95 % quantiles, 2 vs 1
# degree of freedom: sqrt(5.99 / 3.84) = 1.25).
MODEL_THRESHOLD_FACTOR = 1.25


@dataclass(frozen=True)
class TwoViewConfig:
    """Two-view estimation parameters (build from a mapping with ``stereopath.device.core.config.from_mapping``)."""

    method: Literal["ransac", "magsac", "lmeds"] = "ransac"
    max_iters: int = ranged(10_000, 1, 10_000_000)  # the paper's RANSAC trials
    threshold_px: float = ranged(1.0, 1e-3, 100.0)  # epipolar / reprojection inlier threshold
    confidence: float = ranged(0.999, 0.5, 0.999999)
    min_matches: int = ranged(12, 8, 1_000_000)
    min_inliers: int = ranged(8, 5, 1_000_000)
    rotation_ratio: float = ranged(0.95, 0.0, 1.0)  # pure rotation if rotation-only inliers >= ratio * F inliers
    planar_ratio: float = ranged(0.95, 0.0, 1.0)  # planar if homography inliers >= ratio * F inliers
    check_degenerate: bool = True
    refine: bool = True  # Levenberg-Marquardt on the Sampson error of the inliers
    seed: int = 0

    def __post_init__(self) -> None:
        check_ranges(self)

    @staticmethod
    def from_mapping(mapping: Mapping[str, object]) -> "TwoViewConfig":
        return from_mapping(TwoViewConfig, mapping)


@dataclass(eq=False)
class TwoViewResult:
    """Outcome of a two-view estimate; ``R``/``t`` follow ``x_cam2 = R x_cam1 + t``."""

    status: Status
    R: np.ndarray | None = None  # (3, 3)
    t: np.ndarray | None = None  # (3,) unit vector, None when unobservable
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # (N,) over the input matches
    n_matches: int = 0
    F: np.ndarray | None = None
    E: np.ndarray | None = None
    H: np.ndarray | None = None
    message: str = ""

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @property
    def ok(self) -> bool:
        """A rotation is available (``ok``, ``pure_rotation`` or ``planar``)."""
        return self.R is not None

    @property
    def euler_xyz_deg(self) -> np.ndarray | None:
        return None if self.R is None else euler_xyz_deg(self.R)


def euler_xyz_deg(R: np.ndarray) -> np.ndarray:
    """Angles (deg) ``(a, b, c)`` with ``R = Rx(a) Ry(b) Rz(c)`` (the paper's Eq. 1)."""
    return np.degrees(matrix_to_euler_xyz(R))


# --------------------------------------------------------------------------- helpers


_METHODS = {"ransac": "FM_RANSAC", "magsac": "USAC_MAGSAC", "lmeds": "FM_LMEDS"}


def _as_points(xy: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(xy, dtype=np.float64)
    if a.size == 0:
        return np.zeros((0, 2))
    if a.shape[-1] != 2:
        raise ConfigError(f"{name} must be an (N, 2) array of pixels, got shape {a.shape}")
    return a.reshape(-1, 2)


def _as_K(K: np.ndarray, name: str) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all() or abs(np.linalg.det(K)) < 1e-12:
        raise ConfigError(f"{name} must be a finite, invertible 3x3 camera matrix")
    return K


def _normalize(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels -> normalised image coordinates (x/z, y/z)."""
    Kinv = np.linalg.inv(K)
    h = np.hstack([xy, np.ones((len(xy), 1))]) @ Kinv.T
    return h[:, :2] / h[:, 2:3]


def _bearings(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    n = np.hstack([_normalize(xy, K), np.ones((len(xy), 1))])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _kabsch_batch(a: np.ndarray, b: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Rotations R (batch) minimising sum |b - R a|^2; ``a, b`` are (..., n, 3)."""
    if w is None:
        C = np.einsum("...ni,...nj->...ij", b, a)
    else:
        C = np.einsum("...n,...ni,...nj->...ij", w, b, a)
    U, _, Vt = np.linalg.svd(C)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros(C.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    return U @ D @ Vt


def _rotation_residual_px(R: np.ndarray, b1: np.ndarray, xy2: np.ndarray, K2: np.ndarray) -> np.ndarray:
    """Pixel distance between ``xy2`` and the projection of ``R b1`` (inf behind the camera)."""
    p = b1 @ np.swapaxes(R, -1, -2) @ K2.T  # (..., n, 3)
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = p[..., :2] / z[..., None]
        err = np.linalg.norm(uv - xy2, axis=-1)
    return np.where(z > 1e-9, err, np.inf)


def _unique_count(p1: np.ndarray, p2: np.ndarray) -> int:
    if len(p1) == 0:
        return 0
    key = np.round(np.hstack([p1, p2]) * 100.0)
    return int(len(np.unique(key, axis=0)))


# --------------------------------------------------------------------------- rotation only


def _prepare(xy1, xy2, K1, K2):
    """Validated intrinsics and points, and the indices of the finite matches."""
    K1 = _as_K(K1, "K1")
    K2 = K1 if K2 is None else _as_K(K2, "K2")
    p1 = _as_points(xy1, "xy1")
    p2 = _as_points(xy2, "xy2")
    if len(p1) != len(p2):
        raise ConfigError(f"xy1 and xy2 differ in length: {len(p1)} vs {len(p2)}")
    finite = np.isfinite(p1).all(axis=1) & np.isfinite(p2).all(axis=1)
    return K1, K2, p1, p2, np.nonzero(finite)[0]


def rotation_only(xy1: np.ndarray, xy2: np.ndarray, K1: np.ndarray, K2: np.ndarray | None = None, cfg: TwoViewConfig = TwoViewConfig()) -> TwoViewResult:
    """Rotation-only model ``b2 ~ R b1`` from matched bearings: 2-point RANSAC + Kabsch refinement.

    Usable when the camera only turned (or the scene is far away).  Inliers are
    matches whose reprojection through ``K2 R K1^-1`` lands within
    ``cfg.threshold_px`` of ``xy2``.  ``t`` is always None.
    """
    K1, K2, p1, p2, idx = _prepare(xy1, xy2, K1, K2)
    n_all = len(p1)
    inl_all = np.zeros(n_all, bool)
    if _unique_count(p1[idx], p2[idx]) < 3:
        return TwoViewResult("too_few_matches", inliers=inl_all, n_matches=n_all, message=f"{len(idx)} finite matches, fewer than 3 distinct")
    b1 = _bearings(p1[idx], K1)
    b2 = _bearings(p2[idx], K2)
    q2 = p2[idx]
    n = len(idx)
    rng = np.random.default_rng(cfg.seed)
    iters = ROTATION_ITERS
    s = rng.integers(0, n, size=(iters, 2))
    s[:, 1] = np.where(s[:, 1] == s[:, 0], (s[:, 0] + 1) % n, s[:, 1])
    Rs = _kabsch_batch(b1[s], b2[s])  # (iters, 3, 3)
    # score in chunks to bound memory
    best_count, best_R = -1, np.eye(3)
    for c in range(0, iters, 64):
        err = _rotation_residual_px(Rs[c:c + 64], b1[None], q2[None], K2)
        counts = (err < cfg.threshold_px).sum(axis=1)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_count, best_R = int(counts[k]), Rs[c + k]
    R = best_R
    inl = _rotation_residual_px(R, b1, q2, K2) < cfg.threshold_px
    for _ in range(3):  # refine on the inliers, re-select
        if inl.sum() < 2:
            break
        R = _kabsch_batch(b1[inl], b2[inl])
        new = _rotation_residual_px(R, b1, q2, K2) < cfg.threshold_px
        if np.array_equal(new, inl):
            break
        inl = new
    inl_all[idx[inl]] = True
    if inl.sum() < max(3, min(cfg.min_inliers, n)):
        return TwoViewResult("failed", inliers=inl_all, n_matches=n_all, message=f"rotation model: only {int(inl.sum())} inliers")
    return TwoViewResult("ok", R=project_to_so3(R), t=None, inliers=inl_all, n_matches=n_all)


# --------------------------------------------------------------------------- relative pose


def _sampson(E: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Signed Sampson distances of normalised homogeneous points (N, 3) under E."""
    Ex1 = x1 @ E.T
    Etx2 = x2 @ E
    num = np.einsum("ij,ij->i", x2, Ex1)
    den = np.sqrt(Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2) + 1e-15
    return num / den


def _refine_Rt(R: np.ndarray, t: np.ndarray, x1: np.ndarray, x2: np.ndarray, iters: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on the Sampson error; 5 parameters (rotation 3, direction 2)."""
    t = t / np.linalg.norm(t)

    def basis(t):
        a = np.array([1.0, 0.0, 0.0]) if abs(t[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = np.cross(t, a)
        u /= np.linalg.norm(u)
        return u, np.cross(t, u)

    def apply(R, t, d):
        Rn = so3_exp(d[:3]) @ R
        u, v = basis(t)
        tn = t + d[3] * u + d[4] * v
        return Rn, tn / np.linalg.norm(tn)

    def resid(R, t):
        return _sampson(skew(t) @ R, x1, x2)

    r = resid(R, t)
    cost = float(r @ r)
    lam = 1e-4
    h = 1e-6
    for _ in range(iters):
        J = np.empty((len(r), 5))
        for k in range(5):  # central differences
            d = np.zeros(5)
            d[k] = h
            J[:, k] = (resid(*apply(R, t, d)) - resid(*apply(R, t, -d))) / (2.0 * h)
        A = J.T @ J
        g = J.T @ r
        step = None
        for _ in range(12):
            try:
                cand = -np.linalg.solve(A + lam * (np.diag(np.diag(A)) + 1e-12 * np.eye(5)), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            Rn, tn = apply(R, t, cand)
            rn = resid(Rn, tn)
            cn = float(rn @ rn)
            if cn <= cost:
                R, t, r, cost, step = Rn, tn, rn, cn, cand
                lam = max(lam / 5.0, 1e-12)
                break
            lam *= 5.0
        if step is None or float(np.linalg.norm(step)) < 1e-10:
            break
    return project_to_so3(R), t


def _in_front(R: np.ndarray, t: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Cheirality: the midpoint triangulation of each match lies in front of both cameras."""
    b1 = np.hstack([x1, np.ones((len(x1), 1))])
    b2 = np.hstack([x2, np.ones((len(x2), 1))])
    # depths z1, z2 minimising |z2 b2 - (z1 R b1 + t)|
    a = b1 @ R.T
    # [a, -b2] [z1, z2]^T = -t  (least squares per point)
    aa = np.einsum("ij,ij->i", a, a)
    bb = np.einsum("ij,ij->i", b2, b2)
    ab = np.einsum("ij,ij->i", a, b2)
    at = a @ t
    bt = b2 @ t
    det = aa * bb - ab * ab
    with np.errstate(divide="ignore", invalid="ignore"):
        z1 = (-at * bb + ab * bt) / det
        z2 = (aa * bt - ab * at) / det
    return np.isfinite(z1) & np.isfinite(z2) & (z1 > 0) & (z2 > 0)


def _homography_pose(H: np.ndarray, K1: np.ndarray, K2: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """R, t (unit) from a homography; of the physically valid solutions the one whose plane faces the camera."""
    Hn = np.linalg.inv(K2) @ H @ K1
    try:
        n_sol, Rs, ts, normals = cv2.decomposeHomographyMat(Hn, np.eye(3))
        x1 = _normalize(p1, K1).reshape(-1, 1, 2).astype(np.float32)
        x2 = _normalize(p2, K2).reshape(-1, 1, 2).astype(np.float32)
        keep = cv2.filterHomographyDecompByVisibleRefpoints(Rs, normals, x1, x2)
    except cv2.error as exc:
        log.debug("homography decomposition failed: %s", exc)
        return None, None
    cand = list(range(n_sol)) if keep is None or len(keep) == 0 else [int(k) for k in np.asarray(keep).reshape(-1)]
    best = max(cand, key=lambda k: abs(float(np.asarray(normals[k]).reshape(3)[2])))
    R = project_to_so3(np.asarray(Rs[best]))
    t = np.asarray(ts[best], float).reshape(3)
    nt = np.linalg.norm(t)
    return R, (t / nt if nt > 1e-12 else None)


def _degenerate_model(q1: np.ndarray, q2: np.ndarray, K1: np.ndarray, K2: np.ndarray, cfg: TwoViewConfig, n_F: int,
                      full_mask) -> TwoViewResult | None:
    """A pure rotation or a plane that explains the matches as well as F does, else None."""
    # -- no parallax: a rotation explains the matches as well as F does
    thr2 = cfg.threshold_px * MODEL_THRESHOLD_FACTOR
    rot = rotation_only(q1, q2, K1, K2, replace(cfg, threshold_px=thr2))
    n_rot = rot.n_inliers
    if rot.R is not None and n_rot >= cfg.rotation_ratio * n_F:
        return TwoViewResult("pure_rotation", R=rot.R, t=None, inliers=full_mask(rot.inliers),
                             message=f"rotation-only inliers {n_rot} vs F inliers {n_F}")
    # -- planar scene: a homography explains as much as F
    try:
        H, hmask = cv2.findHomography(q1, q2, cv2.RANSAC, thr2, maxIters=min(cfg.max_iters, 5000), confidence=cfg.confidence)
    except cv2.error:
        H, hmask = None, None
    if H is not None and hmask is not None and np.isfinite(H).all():
        inl_H = hmask.reshape(-1).astype(bool)
        n_H = int(inl_H.sum())
        if n_H >= cfg.planar_ratio * n_F:
            R, t = _homography_pose(H, K1, K2, q1[inl_H], q2[inl_H])
            if R is not None:
                return TwoViewResult("planar", R=R, t=t, inliers=full_mask(inl_H), H=H,
                                     message=f"homography inliers {n_H} vs F inliers {n_F}")
    return None


def _refine_and_reselect(R: np.ndarray, t: np.ndarray, x1: np.ndarray, x2: np.ndarray, inl_F: np.ndarray,
                         good: np.ndarray, thr: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LM on the Sampson error of the inliers, then the inliers re-selected with the refined E (4 rounds)."""
    h1 = np.hstack([x1, np.ones((len(x1), 1))])
    h2 = np.hstack([x2, np.ones((len(x2), 1))])
    sel = inl_F & good if (inl_F & good).sum() >= 8 else inl_F
    for _ in range(4):
        if sel.sum() < 8:
            break
        R, t = _refine_Rt(R, t, h1[sel], h2[sel])
        new = np.abs(_sampson(skew(t) @ R, h1, h2)) < thr
        new &= _in_front(R, t, x1, x2)
        if np.array_equal(new, sel):
            break
        sel = new
    return R, t, sel


def relative_pose(xy1: np.ndarray, xy2: np.ndarray, K1: np.ndarray, K2: np.ndarray | None = None, cfg: TwoViewConfig = TwoViewConfig()) -> TwoViewResult:
    """Relative pose of view 2 w.r.t. view 1 from matched pixels (see module docstring).

    Never raises on degenerate data (empty, NaN, identical points); bad
    argument shapes raise :class:`ConfigError`.
    """
    cv2.setRNGSeed(cfg.seed)  # OpenCV's RANSAC draws do not depend on earlier calls in the process
    K1, K2, p1, p2, idx = _prepare(xy1, xy2, K1, K2)
    n_all = len(p1)
    none = np.zeros(n_all, bool)
    n_unique = _unique_count(p1[idx], p2[idx])
    if n_unique < cfg.min_matches:
        return TwoViewResult("too_few_matches", inliers=none, n_matches=n_all, message=f"{n_unique} distinct finite matches < {cfg.min_matches}")
    q1 = np.ascontiguousarray(p1[idx])
    q2 = np.ascontiguousarray(p2[idx])
    # -- fundamental matrix (the paper's RANSAC step)
    try:
        F, mask = cv2.findFundamentalMat(q1, q2, getattr(cv2, _METHODS[cfg.method]), cfg.threshold_px, cfg.confidence, cfg.max_iters)
    except cv2.error as exc:
        return TwoViewResult("failed", inliers=none, n_matches=n_all, message=f"findFundamentalMat: {exc}")
    if F is None or F.shape[0] < 3 or mask is None or not np.isfinite(F).all():
        return TwoViewResult("failed", inliers=none, n_matches=n_all, message="no fundamental matrix found")
    F = F[:3]
    inl_F = mask.reshape(-1).astype(bool)
    n_F = int(inl_F.sum())
    if n_F < cfg.min_inliers:
        return TwoViewResult("failed", inliers=none, n_matches=n_all, F=F, message=f"F has {n_F} inliers < {cfg.min_inliers}")

    def full_mask(m: np.ndarray) -> np.ndarray:
        out = np.zeros(n_all, bool)
        out[idx[m]] = True
        return out

    if cfg.check_degenerate:
        degenerate = _degenerate_model(q1, q2, K1, K2, cfg, n_F, full_mask)
        if degenerate is not None:
            return replace(degenerate, n_matches=n_all, F=F)
    # -- essential matrix and pose (the paper's E = K^T F K)
    E = K2.T @ F @ K1
    x1 = _normalize(q1, K1)
    x2 = _normalize(q2, K2)
    try:
        n_good, R, t, pmask = cv2.recoverPose(E, x1, x2, np.eye(3), mask=(inl_F.astype(np.uint8) * 255).reshape(-1, 1))[:4]
    except cv2.error as exc:
        return TwoViewResult("failed", inliers=full_mask(inl_F), n_matches=n_all, F=F, E=E, message=f"recoverPose: {exc}")
    good = pmask.reshape(-1) > 0
    if int(n_good) < cfg.min_inliers or not np.isfinite(R).all():
        return TwoViewResult("failed", inliers=full_mask(good), n_matches=n_all, F=F, E=E, message=f"only {int(n_good)} points in front of both cameras")
    R = np.asarray(R, float)
    t = np.asarray(t, float).reshape(3)
    if cfg.refine:
        # LM on the Sampson error of all F inliers, then re-select inliers with the
        # refined essential matrix (E from F alone is poorly conditioned: F has 7
        # degrees of freedom, a calibrated pose 5).
        thr = cfg.threshold_px / (0.5 * (K2[0, 0] + K2[1, 1]))
        R, t, good = _refine_and_reselect(R, t, x1, x2, inl_F, good, thr)
        if int(good.sum()) < cfg.min_inliers:
            return TwoViewResult("failed", inliers=full_mask(good), n_matches=n_all, F=F, E=E, message=f"only {int(good.sum())} inliers after refinement")
    return TwoViewResult("ok", R=project_to_so3(R), t=t / np.linalg.norm(t), inliers=full_mask(good), n_matches=n_all, F=F, E=E)
