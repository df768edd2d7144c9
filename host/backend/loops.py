"""Loop closure between keyframes: candidates, geometric verification, loop constraints.

A loop is a pair of keyframes ``(i, j)``, ``j - i > min_separation``, that see the same part of the
scene: camera centres within ``max_distance_m`` and viewing directions within ``max_angle_deg`` on the
estimated path, at least ``min_matches`` descriptor matches, then PnP RANSAC of keyframe i's stereo
points on keyframe j's pixels with enough inliers, a consistent scale between the two keyframes' stereo
points, and a relative pose within the drift the path could have accumulated (a repeated texture
elsewhere fails this).  The matches are first searched only near where keyframe i's stereo points fall
in keyframe j on the estimated path (:func:`guided_matches`, within ``guided_radius_px``), and in the
whole of keyframe j when those do not verify (the path drifted further, or too few matched).  A
keyframe's candidates are tried nearest first, and the first ``candidates_per_keyframe`` accepted are
kept.  Each accepted loop is a relative-pose constraint ``T_ci_cj`` with a deviation from the PnP
residuals (:class:`Loop`).  Pure computation on arrays.  See docs/architecture.md, "Reprocessing".
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from stereopath.device.core.config import check_ranges, ranged
from stereopath.device.core.geometry import invert_pose, rotation_angle_deg
from stereopath.device.core.rig import Rig

if TYPE_CHECKING:
    from stereopath.device.core.matching import MatchConfig
    from stereopath.host.backend.tracks import KeyframeFeatures, KeyframeList

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoopCheck:
    """The geometric verification of a loop candidate: PnP RANSAC, the stereo scale, and how far the
    measured relative pose may disagree with the estimated path."""

    ransac_px: float = ranged(2.0, 0.1, 100.0)
    min_inliers: int = ranged(40, 6, 100_000)
    min_inlier_ratio: float = ranged(0.3, 0.0, 1.0)
    scale_tolerance: float = ranged(0.03, 0.0, 1.0)
    max_3d_error: float = ranged(0.02, 0.0, 10.0)  # median |X_j - T X_i| / depth of the inliers
    drift_per_m: float = ranged(0.02, 0.0, 10.0)  # accepted disagreement with the estimated path per metre travelled
    min_drift_m: float = ranged(0.02, 0.0, 100.0)
    max_rotation_deg: float = ranged(5.0, 0.0, 180.0)

    def __post_init__(self) -> None:
        check_ranges(self, "loops.check.")


@dataclass(frozen=True)
class LoopConfig:
    enabled: bool = True
    min_separation: int = ranged(25, 0, 1_000_000)  # keyframes (more than the track window)
    max_distance_m: float = ranged(0.3, 0.0, 1000.0)
    max_angle_deg: float = ranged(35.0, 0.0, 180.0)
    min_matches: int = ranged(40, 1, 100_000)
    candidates_per_keyframe: int = ranged(1, 1, 1000)  # loops kept per keyframe (the live closer keeps one) ...
    nearest_checked: int = ranged(3, 1, 1000)  # ... of its spatially nearest candidates, tried nearest first
    guided_radius_px: float = ranged(16.0, 0.0, 500.0)  # first try: matches this near the estimated path's prediction (0: none)
    check: LoopCheck = field(default_factory=LoopCheck)

    def __post_init__(self) -> None:
        check_ranges(self, "loops.")


@dataclass(frozen=True)
class LoopCandidate:
    """Two keyframes ``i < j`` that may see the same place: their keypoints (``a``, ``b``:
    :class:`~stereopath.host.backend.tracks.KeyframeFeatures`), estimated poses, the path travelled
    between them, and their descriptor matches (None: computed when verified)."""

    a: KeyframeFeatures
    b: KeyframeFeatures
    T_wi: np.ndarray
    T_wj: np.ndarray
    path_m: float
    i: int = 0
    j: int = 1
    matches: np.ndarray | None = None


@dataclass(frozen=True)
class Loop:
    i: int  # keyframe indices, i < j
    j: int
    T_ci_cj: np.ndarray  # (4, 4) measured relative pose (camera j in camera i)
    inliers: int
    matches: int
    sigma_rot_rad: float
    sigma_trans_m: float
    correction_m: float  # |translation of T_ci_cj - estimated relative translation|

    def as_dict(self) -> dict:
        return {"kf_i": self.i, "kf_j": self.j, "inliers": self.inliers, "matches": self.matches,
                "correction_mm": round(1000 * self.correction_m, 3),
                "sigma_rot_deg": float(np.degrees(self.sigma_rot_rad)), "sigma_trans_mm": 1000 * self.sigma_trans_m}


def candidate_pairs(T_world_cam: np.ndarray, cfg: LoopConfig) -> list[tuple[int, int]]:
    """Keyframe pairs far apart in the sequence but close in space and viewing direction (for each
    keyframe its ``nearest_checked`` nearest, nearest first)."""
    C = T_world_cam[:, :3, 3]
    z = T_world_cam[:, :3, 2]
    out = []
    cos_max = np.cos(np.radians(cfg.max_angle_deg))
    for i in range(len(C)):
        j = np.arange(i + cfg.min_separation + 1, len(C))
        if not len(j):
            break
        d = np.linalg.norm(C[j] - C[i], axis=1)
        near = np.flatnonzero((d < cfg.max_distance_m) & (z[j] @ z[i] > cos_max))
        near = near[np.argsort(d[near], kind="stable")][:cfg.nearest_checked]
        out += [(i, int(k)) for k in j[near]]
    return out


def _match_config() -> MatchConfig:
    """How two keyframes' keypoints are matched for a loop, guided or in full."""
    from stereopath.device.core.matching import MatchConfig

    return MatchConfig(ratio=0.8, mutual=True, per_view=False)


def descriptor_matches(a: KeyframeFeatures, b: KeyframeFeatures) -> np.ndarray:
    from stereopath.device.core.matching import match

    return match(a.feats, b.feats, _match_config()).idx


MIN_DEPTH_M = 1e-3  # a point predicted nearer than this (or behind) is not searched for


def guided_matches(rig: Rig, cand: LoopCandidate, radius_px: float) -> np.ndarray:
    """(M, 2) matches of keyframe i's keypoints with keyframe j's within ``radius_px`` of where i's stereo
    points fall in j on the estimated path (``T_wi``, ``T_wj``): cheaper than the full match, and the same
    loop whenever the path's drift between the two moves the points less than the radius.  A keypoint
    alone within the radius passes the ratio test by position: the geometric checks decide then."""
    from stereopath.host.backend.tracks import match_projected

    if len(cand.a) == 0 or len(cand.b) == 0:
        return np.zeros((0, 2), np.int64)
    T_ji = invert_pose(cand.T_wj) @ cand.T_wi
    return match_projected(rig, cand.a, cand.b, T_ji, radius_px, _match_config(), MIN_DEPTH_M)[0]


def _pnp(rig: Rig, X_i: np.ndarray, uv_j: np.ndarray, cfg: LoopCheck
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """T_cj_ci from 3D points in camera i and pixels in camera j, with the inlier indices (or None)."""
    import cv2

    K = rig.cam0.K
    ok, rvec, tvec, inl = cv2.solvePnPRansac(X_i.astype(np.float64), uv_j.astype(np.float64), K, None,
                                             reprojectionError=cfg.ransac_px, confidence=0.999, iterationsCount=500,
                                             flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None or len(inl) < cfg.min_inliers:
        return None
    inl = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(X_i[inl].astype(np.float64), uv_j[inl].astype(np.float64), K, None, rvec, tvec)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    proj = (X_i @ T[:3, :3].T + T[:3, 3])
    z = np.maximum(proj[:, 2], 1e-9)
    px = proj[:, :2] / z[:, None] * [K[0, 0], K[1, 1]] + K[:2, 2]
    err = np.linalg.norm(px - uv_j, axis=1)
    inl = np.flatnonzero((err < cfg.ransac_px) & (proj[:, 2] > 0))
    return T, inl, err


def verify_pair(rig: Rig, cand: LoopCandidate, cfg: LoopConfig) -> tuple[Loop | None, str]:
    """Geometric verification of a loop candidate; (the loop or None, the reason).  Its descriptor
    matches when not given: the guided ones first (``cfg.guided_radius_px``), the full match of the two
    keyframes when those do not verify."""
    if cand.matches is not None:
        return _verify(rig, cand, cand.matches, cfg)
    if cfg.guided_radius_px > 0:
        loop, why = _verify(rig, cand, guided_matches(rig, cand, cfg.guided_radius_px), cfg)
        if loop is not None:
            return loop, why + " (guided)"
        log.debug("loop candidate %d-%d, guided: %s; the full match", cand.i, cand.j, why)
    return _verify(rig, cand, descriptor_matches(cand.a, cand.b), cfg)


def _verify(rig: Rig, cand: LoopCandidate, m: np.ndarray, cfg: LoopConfig) -> tuple[Loop | None, str]:
    """:func:`verify_pair` on the matches ``m``."""
    a, b, i, j = cand.a, cand.b, cand.i, cand.j
    chk = cfg.check
    if len(m) < cfg.min_matches:
        return None, f"{len(m)} matches"
    X_i, uv_j, X_j = a.X_cam[m[:, 0]], b.uv0[m[:, 1]], b.X_cam[m[:, 1]]
    res = _pnp(rig, X_i, uv_j, chk)
    if res is None:
        return None, "PnP failed"
    T_ji, inl, err = res
    if len(inl) < chk.min_inliers or len(inl) < chk.min_inlier_ratio * len(m):
        return None, f"{len(inl)} inliers of {len(m)}"
    Xi_in_j = X_i[inl] @ T_ji[:3, :3].T + T_ji[:3, 3]
    scale = np.median(np.linalg.norm(X_j[inl], axis=1) / np.maximum(np.linalg.norm(Xi_in_j, axis=1), 1e-9))
    err3d = np.median(np.linalg.norm(X_j[inl] - Xi_in_j, axis=1) / np.maximum(X_j[inl, 2], 1e-9))
    if abs(scale - 1) > chk.scale_tolerance or err3d > chk.max_3d_error:
        return None, f"inconsistent scale {scale:.3f} / 3D error {err3d:.3f}"
    T_ij = invert_pose(T_ji)
    T_ij_est = invert_pose(cand.T_wi) @ cand.T_wj
    corr = float(np.linalg.norm(T_ij[:3, 3] - T_ij_est[:3, 3]))
    rot = rotation_angle_deg(T_ij[:3, :3].T @ T_ij_est[:3, :3])
    if corr > max(chk.min_drift_m, chk.drift_per_m * cand.path_m) or rot > chk.max_rotation_deg:
        return None, f"disagrees with the path by {1000 * corr:.1f} mm / {rot:.2f} deg"
    s_rot, s_t = relative_pose_sigmas(rig.cam0.K[0, 0], float(np.sqrt(np.mean(err[inl] ** 2))), len(inl),
                                      float(np.median(X_i[inl, 2])))
    return Loop(i, j, T_ij, int(len(inl)), int(len(m)), s_rot, s_t, corr), "accepted"


MIN_RELATIVE_PIXEL_SIGMA = 0.3  # px: a relative pose is not trusted beyond this pixel noise


def relative_pose_sigmas(f_px: float, rms_px: float, n_points: int, depth_m: float) -> tuple[float, float]:
    """The standard deviations (rad, m) given to a relative pose measured from ``n_points`` points at a
    median depth ``depth_m``, fitted to ``rms_px`` (at least :data:`MIN_RELATIVE_PIXEL_SIGMA`): the
    rotation twice ``px / f / sqrt(n)``, the translation that angle at the points' depth.  A loop and two
    consecutive keyframes of an adjusted path are weighted by this one model."""
    px = max(rms_px, MIN_RELATIVE_PIXEL_SIGMA)
    s_rot = px / f_px / np.sqrt(n_points) * 2.0
    return float(s_rot), float(s_rot * depth_m)


def path_lengths(T_world_cam: np.ndarray) -> np.ndarray:
    """The distance travelled along the poses' camera centres up to each pose."""
    C = np.asarray(T_world_cam, float)[:, :3, 3]
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(C, axis=0), axis=1))])


def verified_in_order(rig: Rig, kfs: KeyframeList, T_world_cam: np.ndarray, along: np.ndarray,
                      pairs: list[tuple[int, int]], cfg: LoopConfig, limit: int) -> list[Loop]:
    """The candidate ``pairs`` matched and verified in their order until ``limit`` are accepted (the
    accepted loops).  A full descriptor match of two keyframes is the costly part, so the pairs after
    the last accepted one are not matched at all; callers give them nearest first."""
    loops: list[Loop] = []
    for i, j in pairs:
        cand = LoopCandidate(kfs[i], kfs[j], T_world_cam[i], T_world_cam[j], float(along[j] - along[i]), i, j)
        loop, why = verify_pair(rig, cand, cfg)
        log.debug("loop candidate %d-%d: %s", i, j, why)
        if loop is not None:
            loops.append(loop)
            if len(loops) >= limit:
                break
    return loops


def detect_loops(rig: Rig, kfs: KeyframeList, T_world_cam: np.ndarray, cfg: LoopConfig = LoopConfig()) -> list[Loop]:
    """Verified loops among the keyframes ``kfs`` (:class:`~stereopath.host.backend.tracks.KeyframeFeatures`):
    each keyframe's candidates (:func:`candidate_pairs`, nearest first) until ``candidates_per_keyframe``
    are accepted."""
    if not cfg.enabled or len(kfs) < 2:
        return []
    T_world_cam = np.asarray(T_world_cam, float)
    along = path_lengths(T_world_cam)
    by_i: dict[int, list[int]] = {}
    for i, j in candidate_pairs(T_world_cam, cfg):
        by_i.setdefault(i, []).append(j)
    loops = []
    for i, js in by_i.items():
        loops += verified_in_order(rig, kfs, T_world_cam, along, [(i, j) for j in js], cfg,
                                   cfg.candidates_per_keyframe)
    log.info("loop closure: %d candidate pairs, %d loops accepted", sum(map(len, by_i.values())), len(loops))
    return loops


_COLS = 7  # i, j, inliers, matches, sigma_rot, sigma_trans, correction; then T_ci_cj (16)


def loops_to_array(loops: list[Loop]) -> np.ndarray:
    """(L, 23) rows for a stage file."""
    if not loops:
        return np.zeros((0, _COLS + 16))
    return np.array([[lp.i, lp.j, lp.inliers, lp.matches, lp.sigma_rot_rad, lp.sigma_trans_m, lp.correction_m,
                      *np.asarray(lp.T_ci_cj, float).ravel()] for lp in loops])


def loops_from_array(a: np.ndarray) -> list[Loop]:
    a = np.asarray(a, float).reshape(-1, _COLS + 16)
    return [Loop(int(r[0]), int(r[1]), r[_COLS:].reshape(4, 4), int(r[2]), int(r[3]), float(r[4]), float(r[5]),
                 float(r[6])) for r in a]
