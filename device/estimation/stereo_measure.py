"""Stereo measurements of the ``stereo`` estimator: right-image search, triangulation, two-camera pose.

One object per estimator holds the rig, its rectification and the configuration; the
frame loop and the keyframe worker both measure through it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from stereopath.device.core.geometry import invert_pose
from stereopath.device.core.rig import Rig
from stereopath.device.core.stereo_config import StereoConfig
from stereopath.device.core.stereo import (
    LMOptions,
    PointObservations,
    pose_to_rvec_tvec,
    refine_pose_lm,
    rvec_tvec_to_pose,
    stereo_right,
    tracks_back,
    triangulate,
    undistort_px,
)
from stereopath.device.estimation.gyro_prior import GyroRotation, pixel_sigma


@dataclass(frozen=True, eq=False)
class PoseGuess:
    """Where a pose solve starts: a pose (camera 1 to world), whether PnP RANSAC starts from it (else it
    only places the right-image search), and the gyro's orientation as a prior of the refinement."""

    T_world_cam: np.ndarray
    trusted: bool = True
    gyro: GyroRotation | None = None


@dataclass(frozen=True)
class RightMatches:
    """The right-image matches a pose solve measured: ``index`` of each point among the solve's, its left and
    right pixels (distorted, as in the images)."""

    index: np.ndarray
    left: np.ndarray
    right: np.ndarray

    def per_point(self, n: int) -> np.ndarray:
        """(n, 2) right pixels of the solve's ``n`` points, NaN where there is no match."""
        out = np.full((n, 2), np.nan, np.float32)
        out[self.index] = self.right
        return out


class StereoMeasure:
    """Right-image correspondences, stereo points and poses for one rig: the estimator's stereo geometry and
    KLT settings, and the disparity offset in use (its prior until the estimator learns it)."""

    def __init__(self, rig: Rig, cfg: StereoConfig) -> None:
        self.rig = rig
        self.geometry = geo = cfg.geometry
        self.klt = cfg.klt
        self.rect = rig.rectification()
        self.disparity_offset_px = float(cfg.disparity_offset.prior_px)
        fb = self.rect.f * self.rect.baseline_m
        self.max_depth = min(geo.max_depth_m, fb / geo.min_disparity_px) if geo.min_disparity_px > 0 else geo.max_depth_m

    def right_guess(self, X_cam0: np.ndarray) -> np.ndarray:
        """Where points given in camera 1's frame appear in the right image (distorted pixels)."""
        if len(X_cam0) == 0:
            return np.zeros((0, 2))
        Xr = X_cam0 @ self.rig.R.T + self.rig.T
        Xr[:, 2] = np.maximum(Xr[:, 2], 1e-3)
        return cv2.projectPoints(Xr.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.rig.cam1.K,
                                 self.rig.cam1.dist)[0].reshape(-1, 2)

    def rays(self, xy: np.ndarray) -> np.ndarray:
        """Camera-1 rays (z = 1) of distorted left pixels."""
        c = self.rig.cam0
        uvu = undistort_px(xy, c.K, c.dist)
        return np.column_stack([(uvu[:, 0] - c.cx) / c.fx, (uvu[:, 1] - c.cy) / c.fy, np.ones(len(uvu))])

    def right_ideal(self, uv_right: np.ndarray) -> np.ndarray:
        """Right pixels -> ideal (undistorted, K of camera 2) pixels with the disparity offset removed.

        Removing an offset ``d0`` from the rectified disparity is moving the right point by ``+d0``
        along its rectified row (done through the rectification, so it holds for distorted images)."""
        offset = self.disparity_offset_px
        if offset == 0.0 or len(uv_right) == 0:
            return undistort_px(uv_right, self.rig.cam1.K, self.rig.cam1.dist)
        r = self.rect
        rr = cv2.undistortPoints(np.asarray(uv_right, np.float64).reshape(-1, 1, 2), self.rig.cam1.K,
                                 self.rig.cam1.dist, R=r.R1, P=r.P1).reshape(-1, 2)
        rr[:, 0] += offset
        # back from the rectified right image to ideal pixels of camera 2 (K1, no distortion)
        rays = np.column_stack([rr, np.ones(len(rr))]) @ np.linalg.inv(r.P1[:, :3]).T
        rays = rays @ r.R1  # R1^T applied to each row
        return ((rays / rays[:, 2:3]) @ self.rig.cam1.K.T)[:, :2]

    def rectified_observations(self, uv_left: np.ndarray, uv_right: np.ndarray) -> np.ndarray:
        """(n, 3) rows ``(u, v, disparity)`` in the rectified left image, as measured (no offset removed)."""
        r = self.rect
        rl = cv2.undistortPoints(np.asarray(uv_left, np.float64).reshape(-1, 1, 2), self.rig.cam0.K,
                                 self.rig.cam0.dist, R=r.R0, P=r.P0).reshape(-1, 2)
        rr = cv2.undistortPoints(np.asarray(uv_right, np.float64).reshape(-1, 1, 2), self.rig.cam1.K,
                                 self.rig.cam1.dist, R=r.R1, P=r.P1).reshape(-1, 2)
        return np.column_stack([rl, rl[:, 0] - rr[:, 0]])

    def triangulate(self, uv_left: np.ndarray, uv_right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stereo points (camera 1 frame) and their reprojection error, the disparity offset removed."""
        uvl = undistort_px(uv_left, self.rig.cam0.K, self.rig.cam0.dist)
        return triangulate(self.rig, uvl, self.right_ideal(uv_right))

    def good_points(self, Xc: np.ndarray, err: np.ndarray) -> np.ndarray:
        """Triangulations that are consistent and inside the mapped depth range."""
        geo = self.geometry
        return (err < geo.triangulation_max_px) & (Xc[:, 2] > geo.min_depth_m) & (Xc[:, 2] < self.max_depth)

    def stereo_points(self, left: np.ndarray, right: np.ndarray, xy: np.ndarray, z0: float,
                      fb_check: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """New stereo points at left pixels ``xy``: (right pixels, camera-1 points, good mask).

        The right-image search starts from each pixel's ray at depth ``z0``; ``fb_check`` as in
        :func:`~stereopath.device.core.stereo.stereo_right`."""
        uvr, ok = stereo_right(self.rig, left, right, xy, self.right_guess(self.rays(xy) * z0), self.klt, False)
        Xc, err = self.triangulate(xy, uvr)
        ok &= self.good_points(Xc, err)
        if fb_check:  # last: the backward track is the dearest test
            ok &= tracks_back(left, right, xy, uvr, self.klt, where=ok)
        return uvr, Xc, ok

    def solve_pose(self, left: np.ndarray, right: np.ndarray, X: np.ndarray, uv: np.ndarray, guess: PoseGuess,
                   seed: int, stereo_out: list[RightMatches] | None = None
                   ) -> tuple[np.ndarray | None, int, np.ndarray | None]:
        """PnP RANSAC (from the guess when it is trusted), then LM in both cameras over every point in
        front (nothing beyond twice the inlier threshold weighs; the guess's gyro orientation as a prior,
        weighed against the consensus's pixel noise), inliers classified at the refined pose.
        Returns (T_world_cam, n_inliers, mask).  ``stereo_out``: a list that receives the right-image
        matches the refinement used (:class:`RightMatches`)."""
        geo = self.geometry
        K0, d0 = self.rig.cam0.K, self.rig.cam0.dist
        uv_u = undistort_px(uv, K0, d0)
        use_guess = guess.trusted
        T_cw = invert_pose(guess.T_world_cam)
        rvec, tvec = pose_to_rvec_tvec(T_cw)
        # RANSAC draws do not depend on what ran before (OpenCV's RNG is per thread)
        cv2.setRNGSeed(seed)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X.reshape(-1, 1, 3), uv_u.reshape(-1, 1, 2), K0, None, rvec, tvec, useExtrinsicGuess=use_guess,
            iterationsCount=200 if use_guess else 500, reprojectionError=geo.pnp_reproj_px, confidence=0.999,
            flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok or inl is None or len(inl) < geo.min_pnp_inliers:
            return None, 0, None
        T_cw = rvec_tvec_to_pose(rvec, tvec)
        # The consensus only seeds the refinement: a minimal-sample hypothesis a little off leaves
        # good points just outside the threshold, and the caller drops outliers for good (a tracked
        # map loses them, and the pose jumps with the subset).  So every point in front of the camera
        # enters the robust two-camera refinement, with its right-image observation, and the inliers
        # are classified at the refined pose.  Residuals over twice the threshold weigh nothing: a
        # block of consistently wrong matches (repeated texture) cannot pull the pose.
        Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
        idx = np.flatnonzero(Xc[:, 2] > geo.min_depth_m)
        uvr, okr = stereo_right(self.rig, left, right, uv[idx], self.right_guess(Xc[idx]), self.klt, fb_check=False,
                                levels=self.klt.seeded_stereo_levels)
        ridx = idx[okr]
        if stereo_out is not None:
            stereo_out.append(RightMatches(ridx, np.asarray(uv)[ridx], uvr[okr]))
        uvr_u = self.right_ideal(uvr[okr])
        prior = None
        if guess.gyro is not None:
            fx, fy, cx, cy = K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2]
            Xi = Xc[idx]
            err = np.hypot(fx * Xi[:, 0] / Xi[:, 2] + cx - uv_u[idx, 0], fy * Xi[:, 1] / Xi[:, 2] + cy - uv_u[idx, 1])
            prior = guess.gyro.prior(pixel_sigma(err, geo.pnp_reproj_px, geo.huber_px))
        res = refine_pose_lm(self.rig, T_cw, PointObservations(X[idx], uv_u[idx]), PointObservations(X[ridx], uvr_u),
                             LMOptions(huber_px=geo.huber_px, outlier_px=geo.pnp_reproj_px, cutoff_px=2 * geo.pnp_reproj_px),
                             prior)
        final = np.zeros(len(X), bool)
        final[idx[res.inliers_left]] = True
        if final.sum() < geo.min_pnp_inliers:
            return None, 0, None
        return invert_pose(res.T_cam_world), int(final.sum()), final
