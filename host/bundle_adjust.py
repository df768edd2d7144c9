"""Bundle adjustment of keyframe poses and points on the reprojection error in both cameras.

Solver: ``scipy.optimize.least_squares`` (trust-region reflective, a Levenberg-Marquardt-type
method that handles large sparse problems) with a robust soft-L1 loss (a smooth Huber: scipy's
``huber`` stalls in trf on this problem, see tests) and the Jacobian's sparsity
pattern given explicitly, so finite differences cost only about nine residual evaluations per
iteration (columns of different keyframes or different points never share a residual).

Observations are rows ``(keyframe, point_id, cam, u, v)`` in undistorted pixels (cam 0 left,
1 right).  Keyframe 0 is held fixed (gauge); scale comes from the right-camera observations
through the calibrated baseline.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from device.errors import EstimationError
from device.geometry import invert_pose
from device.rig import Rig

log = logging.getLogger(__name__)


@dataclass
class BAResult:
    T_world_cam: np.ndarray  # (K, 4, 4) refined keyframe poses
    points: dict[int, np.ndarray]
    rms_before_px: float
    rms_after_px: float
    n_obs: int
    n_points: int
    iterations: int


def _rotvec_to_R(r: np.ndarray) -> np.ndarray:
    """Batched Rodrigues: (N, 3) -> (N, 3, 3)."""
    theta = np.linalg.norm(r, axis=1)
    small = theta < 1e-10
    k = r / np.where(small, 1.0, theta)[:, None]
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -k[:, 2], k[:, 1]
    K[:, 1, 0], K[:, 1, 2] = k[:, 2], -k[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -k[:, 1], k[:, 0]
    s = np.sin(theta)[:, None, None]
    c = (1 - np.cos(theta))[:, None, None]
    R = np.eye(3)[None] + s * K + c * K @ K
    return np.where(small[:, None, None], np.eye(3)[None], R)


def bundle_adjust(rig: Rig, T_world_cam: np.ndarray, points: dict[int, np.ndarray], observations: np.ndarray,
                  huber_px: float = 1.0, max_nfev: int = 100, loss: str = "soft_l1", min_keyframes_per_point: int = 2) -> BAResult:
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    obs = np.asarray(observations, dtype=float).reshape(-1, 5)
    K_n = len(T_world_cam)
    if K_n < 2 or len(obs) == 0:
        raise EstimationError("bundle adjustment needs at least two keyframes with observations")
    kf = obs[:, 0].astype(int)
    pid = obs[:, 1].astype(np.int64)
    # keep points seen from at least two keyframes and known in ``points``
    known = np.array([p in points for p in pid])
    obs, kf, pid = obs[known], kf[known], pid[known]
    uniq, inv = np.unique(pid, return_inverse=True)
    n_kf_per_pt = np.array([len(np.unique(kf[inv == i])) for i in range(len(uniq))]) if len(uniq) else np.zeros(0)
    good_pts = n_kf_per_pt >= min_keyframes_per_point
    sel = good_pts[inv]
    obs, kf, pid = obs[sel], kf[sel], pid[sel]
    uniq, pidx = np.unique(pid, return_inverse=True)
    if len(uniq) < 10:
        raise EstimationError(f"bundle adjustment: only {len(uniq)} points seen from two keyframes")
    cam = obs[:, 2].astype(int)
    uv = obs[:, 3:5]
    P = len(uniq)
    T_cw = np.array([invert_pose(T) for T in T_world_cam])
    import cv2

    x_pose = np.zeros((K_n, 6))
    for i, T in enumerate(T_cw):
        x_pose[i, :3] = cv2.Rodrigues(T[:3, :3])[0].ravel()
        x_pose[i, 3:] = T[:3, 3]
    x_pts = np.array([points[int(p)] for p in uniq])
    R10, t10 = rig.R, rig.T
    Ks = [rig.cam0.K, rig.cam1.K]
    free = np.arange(1, K_n)  # keyframe 0 fixed

    def unpack(x):
        poses = x_pose.copy()
        poses[1:] = x[: 6 * (K_n - 1)].reshape(-1, 6)
        pts = x[6 * (K_n - 1):].reshape(-1, 3)
        return poses, pts

    fx = np.where(cam == 0, Ks[0][0, 0], Ks[1][0, 0])
    fy = np.where(cam == 0, Ks[0][1, 1], Ks[1][1, 1])
    cx = np.where(cam == 0, Ks[0][0, 2], Ks[1][0, 2])
    cy = np.where(cam == 0, Ks[0][1, 2], Ks[1][1, 2])
    right = cam == 1

    def residuals(x):
        poses, pts = unpack(x)
        R = _rotvec_to_R(poses[:, :3])
        X = pts[pidx]
        Xc = np.einsum("nij,nj->ni", R[kf], X) + poses[kf, 3:]
        Xc[right] = Xc[right] @ R10.T + t10
        z = np.where(np.abs(Xc[:, 2]) < 1e-6, 1e-6, Xc[:, 2])
        u = fx * Xc[:, 0] / z + cx
        v = fy * Xc[:, 1] / z + cy
        return np.column_stack([u - uv[:, 0], v - uv[:, 1]]).ravel()

    n_obs = len(obs)
    A = lil_matrix((2 * n_obs, 6 * (K_n - 1) + 3 * P), dtype=np.int8)
    rows = np.arange(n_obs)
    for d in range(2):
        r = 2 * rows + d
        has_pose = kf > 0
        for j in range(6):
            A[r[has_pose], 6 * (kf[has_pose] - 1) + j] = 1
        for j in range(3):
            A[r, 6 * (K_n - 1) + 3 * pidx + j] = 1
    x0 = np.concatenate([x_pose[1:].ravel(), x_pts.ravel()])
    r0 = residuals(x0)
    rms0 = float(np.sqrt(np.mean(r0**2)))
    res = least_squares(residuals, x0, jac_sparsity=A.tocsr(), loss=loss, f_scale=huber_px, method="trf",
                        x_scale="jac", tr_solver="lsmr", tr_options={"atol": 1e-12, "btol": 1e-12, "maxiter": 2000}, max_nfev=max_nfev, verbose=0)
    rms1 = float(np.sqrt(np.mean(res.fun**2)))
    poses, pts = unpack(res.x)
    R = _rotvec_to_R(poses[:, :3])
    out = np.zeros((K_n, 4, 4))
    for i in range(K_n):
        T = np.eye(4)
        T[:3, :3] = R[i]
        T[:3, 3] = poses[i, 3:]
        out[i] = invert_pose(T)
    log.info("bundle adjustment: %d keyframes, %d points, %d observations, rms %.3f -> %.3f px (%d evaluations)",
             K_n, P, n_obs, rms0, rms1, res.nfev)
    return BAResult(out, {int(p): pts[i] for i, p in enumerate(uniq)}, rms0, rms1, n_obs, P, int(res.nfev))


def propagate_to_frames(T_frames: np.ndarray, frame_kf: np.ndarray, T_kf_old: np.ndarray,
                        T_kf_new: np.ndarray) -> np.ndarray:
    """Move every frame with the correction of its keyframe: ``T_new = T_kf_new inv(T_kf_old) T_old``."""
    out = np.empty_like(T_frames)
    for i, (T, k) in enumerate(zip(T_frames, frame_kf)):
        out[i] = T_kf_new[k] @ invert_pose(T_kf_old[k]) @ T
    return out
