"""The reference paper's estimator (steps 1-5 of docs/architecture.md, "The reference paper's method"), as written.

Per camera and consecutive pair (P-1, P): SIFT (original view) of P-1 against
modified-ASIFT features of P, RANSAC fundamental matrix (10,000 iterations in
the ``paper`` preset), E = K^T F K, ``recoverPose`` -> relative rotation.
Rotations are chained per camera (Eq. 2).  Camera 2's chain is expressed in
camera 1's frame through the rig extrinsics and the two are averaged (Eq. 3)
as a chordal L2 mean projected back onto SO(3) - the element-wise mean of
the paper is not a rotation.  Translation (Eq. 4-5): world points matched in
the stereo pairs at P-1 and P are triangulated on the rectified images
(Z = f B / d) and ``T_P = median(X_{P-1} - X_P)`` (several points with a
robust median rather than one); as in the paper this ignores the rotation
between P-1 and P.  ``T_F(P) = T_F(P-1) + R_F(P-1) T_P``: the increment,
measured in camera P-1's axes, is rotated into the world frame by the chained
rotation so that positions add up in one frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from stereopath.device.core.config import check_ranges, ranged
from stereopath.device.estimation.base import PoseEstimate, WorldFrame
from stereopath.device.core.features import gray
from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.core.geometry import chordal_mean, make_pose
from stereopath.device.core.rig import Rig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PaperConfig:
    feature_preset: str = "paper"
    ransac_iterations: int = ranged(10_000, 10, 1_000_000)
    frame_step: int = ranged(4, 1, 1000)  # a "position" every N video frames (consecutive 20 Hz frames barely move)
    ransac_threshold_px: float = 1.0
    epipolar_max_dy_px: float = 1.0
    min_matches: int = ranged(15, 8, 100000)
    min_disparity_px: float = 1.0
    # Eq. 4 as written ignores the rotation between P-1 and P; True removes it (T_P from
    # X_{P-1} - R_P X_P), which is not the paper's method but shows what the rotation costs.
    rotation_compensated: bool = False

    def __post_init__(self) -> None:
        check_ranges(self)


def match_indices(m) -> np.ndarray:
    """Index pairs (M, 2) of a :mod:`stereopath.device.core.matching` result."""
    for name in ("idx", "indices", "pairs"):
        if hasattr(m, name):
            return np.asarray(getattr(m, name)).reshape(-1, 2)
    return np.asarray(m).reshape(-1, 2)


class PaperEstimator:
    name = "paper"

    def __init__(self, rig: Rig, config: PaperConfig | None = None) -> None:
        from stereopath.device.core.features import get_preset

        self.rig = rig
        self.cfg = config or PaperConfig()
        self._fcfg = get_preset(self.cfg.feature_preset)
        self.world_frame: WorldFrame = "first_camera"
        self._rect = rig.rectification()
        self._prev = None  # (feats_left, feats_right)
        self._R_F = [np.eye(3), np.eye(3)]  # chained rotation per camera (camera 2 in camera 1 axes)
        self._T_F = np.zeros(3)
        self._count = 0
        self.counters = {"rotation_failures": 0, "translation_failures": 0}

    def stats(self) -> dict:
        return dict(self.counters)

    def _rectified(self, xy: np.ndarray, cam: int) -> np.ndarray:
        c = self.rig.cam0 if cam == 0 else self.rig.cam1
        R, P = (self._rect.R0, self._rect.P0) if cam == 0 else (self._rect.R1, self._rect.P1)
        if len(xy) == 0:
            return np.zeros((0, 2))
        return cv2.undistortPoints(xy.reshape(-1, 1, 2).astype(np.float64), c.K, c.dist, R=R, P=P).reshape(-1, 2)

    def _stereo_points(self, fl, fr) -> tuple[np.ndarray, np.ndarray]:
        """Indices into ``fl`` and their 3D points (cam0 frame) from rectified stereo matching."""
        from stereopath.device.core.matching import match_epipolar_rectified

        rl, rr = self._rectified(fl.xy, 0), self._rectified(fr.xy, 1)
        m = match_epipolar_rectified(rl, rr, fl.desc, fr.desc, max_dy=self.cfg.epipolar_max_dy_px,
                                     min_disp=self.cfg.min_disparity_px)
        idx = match_indices(m)
        if len(idx) == 0:
            return np.zeros(0, int), np.zeros((0, 3))
        r = self._rect
        d = rl[idx[:, 0], 0] - rr[idx[:, 1], 0]
        Z = r.f * r.baseline_m / d
        X = (rl[idx[:, 0], 0] - r.cx) * Z / r.f
        Y = (rl[idx[:, 0], 1] - r.cy) * Z / r.f
        X_rect = np.stack([X, Y, Z], axis=1)
        return idx[:, 0], X_rect @ r.R0  # rectified -> cam0 axes (R0 maps cam0 -> rectified)

    def _relative_rotation(self, prev, cur, cam: int) -> np.ndarray | None:
        from stereopath.device.core.matching import MatchConfig, match
        from stereopath.device.core.twoview import TwoViewConfig, relative_pose

        m = match(prev.original_view(), cur, MatchConfig())
        idx = match_indices(m)
        if len(idx) < self.cfg.min_matches:
            return None
        p0 = prev.original_view()
        K = (self.rig.cam0 if cam == 0 else self.rig.cam1).K
        res = relative_pose(p0.xy[idx[:, 0]], cur.xy[idx[:, 1]], K, K,
                            TwoViewConfig(max_iters=self.cfg.ransac_iterations,
                                          threshold_px=self.cfg.ransac_threshold_px))
        if res.R is None:
            return None
        # recoverPose gives x_P = R x_{P-1} + t; the camera's own rotation P-1 -> P is R^T
        return res.R.T

    def process(self, frame: StereoFrame, imu: ImuSamples | None) -> PoseEstimate | None:
        from stereopath.device.core.features import detect

        self._count += 1
        if (self._count - 1) % self.cfg.frame_step:
            return None
        left, right = gray(frame.left), gray(frame.right)
        fl, fr = detect(left, self._fcfg), detect(right, self._fcfg)
        if self._prev is None:
            self._prev = (fl, fr)
            return PoseEstimate(frame.seq, frame.t_ns, np.eye(4), "ok", keyframe=True)
        pl, pr = self._prev
        R_prev_world = chordal_mean(self._R_F)
        Rl = self._relative_rotation(pl, fl, 0)
        Rr = self._relative_rotation(pr, fr, 1)
        status, note = "ok", ""
        if Rr is not None:
            Rr = self.rig.R.T @ Rr @ self.rig.R  # camera 2's rotation in camera 1 axes
        if Rl is None and Rr is None:
            self.counters["rotation_failures"] += 1
            status, note = "lost", "rotation_failed"
        else:
            Rl = Rl if Rl is not None else Rr
            Rr = Rr if Rr is not None else Rl
            self._R_F = [self._R_F[0] @ Rl, self._R_F[1] @ Rr]
        # stereo translation by fixed world points seen at P-1 and P
        inl_prev, X_prev = self._stereo_points(pl.original_view(), pr.original_view())
        inl_cur, X_cur = self._stereo_points(fl, fr)
        T_P = None
        if len(inl_prev) and len(inl_cur):
            from stereopath.device.core.matching import MatchConfig, match

            a = pl.original_view().subset(inl_prev)
            b = fl.subset(inl_cur)
            idx = match_indices(match(a, b, MatchConfig()))
            if len(idx) >= 3:
                Xc = X_cur[idx[:, 1]]
                if self.cfg.rotation_compensated and Rl is not None:
                    Xc = Xc @ Rl.T  # the current points in camera P-1's axes
                T_P = np.median(X_prev[idx[:, 0]] - Xc, axis=0)
        if T_P is None:
            self.counters["translation_failures"] += 1
            status, note = ("lost", note or "translation_failed")
            T_P = np.zeros(3)
        self._T_F = self._T_F + R_prev_world @ T_P
        self._prev = (fl, fr)
        R = chordal_mean(self._R_F)
        return PoseEstimate(frame.seq, frame.t_ns, make_pose(R, self._T_F), status, note=note)
