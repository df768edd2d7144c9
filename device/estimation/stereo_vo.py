"""The default ``stereo`` estimator: metric stereo visual-inertial odometry.

Per frame (see docs/architecture.md, "Estimators"):

1. gyro integration since the previous frame gives the rotation prior (and the
   fallback when vision fails: the frame is flagged ``imu_only``);
2. map points (3D, world frame, triangulated from a stereo pair) are tracked
   into the new left image by pyramidal KLT seeded with the predicted pose,
   checked forward-backward, and located in the new right image the same way;
3. PnP RANSAC on the 2D-3D matches, then Levenberg-Marquardt on the
   reprojection error in both cameras;
4. at keyframes (chosen by tracked-point count, parallax and age) the new left
   image gets modified-ASIFT features that are matched against the previous
   keyframe's SIFT (original-view) features with known 3D: these matches join
   the tracked points in the keyframe's PnP, so keyframe poses come from the
   (modified-)ASIFT matching.  New map points are added where the image has
   none: left/right correspondence by KLT, accepted only when the rectified
   rows agree (|dy| <= 1 px) and the disparity is positive, then triangulated.

Works without an IMU (KITTI): the prior is then a constant-velocity model.
At start-up a still IMU block before the first frame gives the gyro bias and
gravity; the world frame is then gravity aligned (z up), else camera 1 at the
first frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from stereopath.device.core.config import check_range
from stereopath.device.errors import ConfigError
from stereopath.device.estimation.base import PoseEstimate, WorldFrame
from stereopath.device.estimation.inertial import GyroIntegrator, estimate_still, gravity_aligned_rotation
from stereopath.device.core.stereo import (
    pose_to_rvec_tvec,
    refine_pose_lm,
    rvec_tvec_to_pose,
    triangulate,
    undistort_px,
)
from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.core.geometry import invert_pose, make_pose, rotation_angle_deg, so3_exp, so3_log
from stereopath.device.core.rig import Rig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StereoConfig:
    feature_preset: str = "onboard"  # modified-ASIFT preset used at keyframes
    use_asift_keyframes: bool = True
    max_points: int = 500  # map points kept for tracking
    new_corner_spacing_px: int = 14
    min_tracked: int = 120  # fewer tracked inliers -> keyframe
    kf_parallax_px: float = 45.0  # median flow since the keyframe -> keyframe
    kf_max_frames: int = 20
    klt_window: int = 21
    klt_levels: int = 3
    fb_max_px: float = 0.6  # forward-backward KLT disagreement
    epipolar_max_dy_px: float = 1.0
    triangulation_max_px: float = 1.0
    min_depth_m: float = 0.1
    max_depth_m: float = 20.0
    pnp_reproj_px: float = 2.0
    min_pnp_inliers: int = 12
    use_imu: bool = True
    huber_px: float = 1.0
    max_failures_keep_map: int = 10  # failed frames in a row before the map restarts
    background_keyframes: bool = True  # affine views of a keyframe computed off the frame loop
    record_observations: bool = False  # keep a keyframe observation log (memory grows with the session)
    guided_radius_px: float = 24.0  # keyframe matching around the predicted positions (0 = global)
    refine_points: bool = True  # average each tracked point's stereo triangulations at keyframes
    kf_library_max: int = 6000  # keypoints (all views) kept with 3D per keyframe for the next match

    def __post_init__(self) -> None:
        check_range("max_points", self.max_points, 20, 20000)
        check_range("min_tracked", self.min_tracked, 8, self.max_points)
        check_range("kf_max_frames", self.kf_max_frames, 1, 1000)
        check_range("klt_window", self.klt_window, 5, 61)
        check_range("klt_levels", self.klt_levels, 0, 6)
        check_range("epipolar_max_dy_px", self.epipolar_max_dy_px, 0.1, 5.0)
        check_range("min_depth_m", self.min_depth_m, 0.01, self.max_depth_m)
        check_range("min_pnp_inliers", self.min_pnp_inliers, 6, 10000)


@dataclass
class _Map:
    X: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # world points
    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))  # left pixels, last frame
    uv_kf: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))  # at keyframe
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # stable point ids
    nobs: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float64))  # stereo observations averaged

    def keep(self, mask: np.ndarray) -> None:
        self.X, self.uv, self.uv_kf, self.ids = self.X[mask], self.uv[mask], self.uv_kf[mask], self.ids[mask]
        self.nobs = self.nobs[mask]

    def __len__(self) -> int:
        return len(self.X)


def _gray(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return img


class StereoEstimator:
    name = "stereo"

    def __init__(self, rig: Rig, config: StereoConfig | None = None) -> None:
        self.rig = rig
        self.cfg = config or StereoConfig()
        self.world_frame: WorldFrame = "first_camera"
        self._rect = rig.rectification()
        self._T_world_cam: np.ndarray | None = None
        self._T_prev_prev: np.ndarray | None = None
        self._t_prev: int | None = None
        self._dt_prev: float | None = None
        self._prev_left: np.ndarray | None = None
        self._map = _Map()
        # the last keyframe's all-view features with 3D points: a Future while the background
        # thread computes them (or the plain result when run synchronously)
        self._kf_future = None
        self._executor = None
        if self.cfg.use_asift_keyframes and self.cfg.background_keyframes:
            from concurrent.futures import ThreadPoolExecutor

            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="keyframe-features")
        self._since_kf = 0
        self._failures = 0
        self._pending_feats = None
        self._gyro: GyroIntegrator | None = None
        self._R_body_cam = None if rig.T_body_cam0 is None else rig.T_body_cam0[:3, :3]
        self._klt = dict(winSize=(self.cfg.klt_window, self.cfg.klt_window), maxLevel=self.cfg.klt_levels,
                         criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))
        self._feature_cfg = None
        self._match_cfg = None
        # keyframe log for offline bundle adjustment: poses, observations (kf, point id, cam, u, v)
        self.record_observations = self.cfg.record_observations
        self.keyframe_poses: list[tuple[int, np.ndarray]] = []
        self.observations: list[np.ndarray] = []
        self.landmarks: dict[int, np.ndarray] = {}
        self._next_id = 0
        self._cur_seq = 0
        self.counters = {"keyframes": 0, "imu_only": 0, "lost": 0, "asift_matches": 0}

    # ------------------------------------------------------------------ public

    def stats(self) -> dict:
        return dict(self.counters)

    def close(self) -> None:
        """Stop the background keyframe worker (idempotent)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None

    def __del__(self) -> None:  # the worker thread must not outlive the estimator
        try:
            self.close()
        except Exception:
            pass

    def process(self, frame: StereoFrame, imu: ImuSamples | None) -> PoseEstimate:
        left, right = _gray(frame.left), _gray(frame.right)
        self._cur_seq = frame.seq
        if self._T_world_cam is None:
            return self._initialise(frame, left, right, imu)

        dt = (frame.t_ns - self._t_prev) * 1e-9
        T_pred, have_rot_prior = self._predict(frame.t_ns, dt, imu)
        est = self._track(frame, left, right, T_pred, have_rot_prior)
        self._T_prev_prev = self._T_world_cam
        self._T_world_cam = est.T_world_cam
        self._t_prev = frame.t_ns
        self._dt_prev = dt
        return est

    # ------------------------------------------------------------------ stages

    def _initialise(self, frame: StereoFrame, left, right, imu: ImuSamples | None) -> PoseEstimate:
        R_world_cam = np.eye(3)
        if self.cfg.use_imu and imu is not None and len(imu) and self._R_body_cam is not None:
            still = estimate_still(imu)
            if still is not None:
                self._gyro = GyroIntegrator(still.gyro_bias_rad_s)
                R_world_body = gravity_aligned_rotation(still.accel_mean_m_s2)
                R_world_cam = R_world_body @ self._R_body_cam
                self.world_frame = "gravity_aligned"
                log.info("IMU still at start: gyro bias %s rad/s, |g| = %.3f m/s^2; world frame gravity aligned",
                         np.round(still.gyro_bias_rad_s, 5), still.gravity_norm_m_s2)
            else:
                self._gyro = GyroIntegrator(None)
                log.warning("IMU not still before the first frame: no gyro bias, world frame = first camera")
            self._gyro.feed_and_integrate(imu, frame.t_ns, frame.t_ns)
        T = make_pose(R_world_cam, np.zeros(3))
        self._T_world_cam = T
        self._t_prev = frame.t_ns
        self._prev_left = left
        n = self._new_keyframe(left, right, T, tracked=None)
        status = "ok" if n >= self.cfg.min_pnp_inliers else "lost"
        return PoseEstimate(frame.seq, frame.t_ns, T.copy(), status, inliers=n, keyframe=True,
                            note="" if status == "ok" else "no_stereo_points")

    def _predict(self, t_ns: int, dt: float, imu: ImuSamples | None) -> tuple[np.ndarray, bool]:
        T_prev = self._T_world_cam
        # constant velocity (translation and rotation) from the last two poses
        if self._T_prev_prev is not None and self._dt_prev:
            T_rel = invert_pose(self._T_prev_prev) @ T_prev  # motion in the previous camera frame
            scale = dt / self._dt_prev
            R_rel = so3_exp(so3_log(T_rel[:3, :3]) * scale)
            t_rel = T_rel[:3, 3] * scale
        else:
            R_rel, t_rel = np.eye(3), np.zeros(3)
        have_rot = False
        if self._gyro is not None and self._R_body_cam is not None:
            R_b = self._gyro.feed_and_integrate(imu, self._t_prev, t_ns)
            if R_b is not None:
                Rbc = self._R_body_cam
                R_rel = Rbc.T @ R_b @ Rbc
                have_rot = True
        return T_prev @ make_pose(R_rel, t_rel), have_rot

    def _track(self, frame: StereoFrame, left, right, T_pred: np.ndarray, have_rot: bool) -> PoseEstimate:
        cfg = self.cfg
        m = self._map
        T_est = None
        n_inl = 0
        note = ""
        if len(m) >= cfg.min_pnp_inliers and self._prev_left is not None:
            uv_new, good = self._klt_track(left, T_pred)
            if good.sum() >= cfg.min_pnp_inliers:
                T_est, n_inl, inl = self._solve_pose(left, right, m.X[good], uv_new[good], T_pred)
                if T_est is not None:
                    m.uv = uv_new.astype(np.float32)
                    m.keep(good)
                    m.keep(inl)
                else:
                    note = "pose_failed"
            else:
                note = "too_few_tracked"
        else:
            note = "no_map"
        self._since_kf += 1
        if T_est is not None:
            self._failures = 0
            self._prev_left = left
            is_kf = False
            parallax = float(np.median(np.linalg.norm(m.uv - m.uv_kf, axis=1))) if len(m) else 0.0
            if n_inl < cfg.min_tracked or parallax > cfg.kf_parallax_px or self._since_kf >= cfg.kf_max_frames:
                T_est, n_inl = self._keyframe_pose(left, right, T_est, n_inl)
                self._new_keyframe(left, right, T_est, tracked=True)
                is_kf = True
            return PoseEstimate(frame.seq, frame.t_ns, T_est, "ok", inliers=n_inl, keyframe=is_kf)
        # Vision failed (black frame, lens cap, no overlap, blur): fall back to the IMU rotation (or
        # constant velocity).  The map and the last good image are kept so the next good frame can
        # be tracked against them; after several failures in a row the map restarts here.
        status = "imu_only" if have_rot else "lost"
        self.counters[status] += 1
        self._failures += 1
        is_kf = False
        if self._failures > cfg.max_failures_keep_map or len(m) < cfg.min_pnp_inliers:
            self._map = _Map()
            n = self._new_keyframe(left, right, T_pred, tracked=None)
            if n >= cfg.min_pnp_inliers:
                self._prev_left = left
                is_kf = True
        return PoseEstimate(frame.seq, frame.t_ns, T_pred, status, inliers=0, keyframe=is_kf, note=note)

    def _klt_track(self, left: np.ndarray, T_pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Track the map into ``left``; returns new pixels and the good mask (the map is not changed)."""
        m = self._map
        T_cw = invert_pose(T_pred)
        Xc = m.X @ T_cw[:3, :3].T + T_cw[:3, 3]
        guess = m.uv.copy()
        front = Xc[:, 2] > 1e-3
        if np.any(front):
            pts = cv2.projectPoints(Xc[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                    self.rig.cam0.K, self.rig.cam0.dist)[0].reshape(-1, 2)
            guess[front] = pts
        p0 = m.uv.reshape(-1, 1, 2).astype(np.float32)
        g = guess.reshape(-1, 1, 2).astype(np.float32)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(self._prev_left, left, p0, g.copy(),
                                             flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._klt)
        pb, stb, _ = cv2.calcOpticalFlowPyrLK(left, self._prev_left, p1, p0.copy(),
                                              flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._klt)
        fb = np.linalg.norm((pb - p0).reshape(-1, 2), axis=1)
        w, h = self.rig.cam0.size
        p1 = p1.reshape(-1, 2)
        good = (st.ravel() == 1) & (stb.ravel() == 1) & (fb < self.cfg.fb_max_px)
        good &= (p1[:, 0] >= 0) & (p1[:, 0] < w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] < h - 1)
        return p1.astype(np.float32), good

    def _stereo_right(self, left: np.ndarray, right: np.ndarray, uv_left: np.ndarray,
                      guess_right: np.ndarray, fb_check: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Locate left points in the right image (KLT seeded by ``guess_right``), checked on rectified rows.

        ``fb_check`` adds the right-to-left track back (new points); the rectified-row check
        alone is enough where the points are already known inliers (refinement)."""
        if len(uv_left) == 0:
            return np.zeros((0, 2), np.float32), np.zeros(0, bool)
        p0 = uv_left.reshape(-1, 1, 2).astype(np.float32)
        g = guess_right.reshape(-1, 1, 2).astype(np.float32)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(left, right, p0, g.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                             **self._klt)
        if fb_check:
            pb, stb, _ = cv2.calcOpticalFlowPyrLK(right, left, p1, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                                  **self._klt)
            fb = np.linalg.norm((pb - p0).reshape(-1, 2), axis=1)
        else:
            stb, fb = st, np.zeros(len(p0))
        p1 = p1.reshape(-1, 2)
        r = self._rect
        rl = cv2.undistortPoints(p0, self.rig.cam0.K, self.rig.cam0.dist, R=r.R0, P=r.P0).reshape(-1, 2)
        rr = cv2.undistortPoints(p1.reshape(-1, 1, 2), self.rig.cam1.K, self.rig.cam1.dist, R=r.R1,
                                 P=r.P1).reshape(-1, 2)
        disp = rl[:, 0] - rr[:, 0]
        w, h = self.rig.cam1.size
        ok = (st.ravel() == 1) & (stb.ravel() == 1) & (fb < self.cfg.fb_max_px)
        ok &= np.abs(rl[:, 1] - rr[:, 1]) <= self.cfg.epipolar_max_dy_px
        ok &= disp > 0
        ok &= (p1[:, 0] >= 0) & (p1[:, 0] < w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] < h - 1)
        return p1.astype(np.float32), ok

    def _right_guess(self, X_cam0: np.ndarray) -> np.ndarray:
        Xr = X_cam0 @ self.rig.R.T + self.rig.T
        Xr[:, 2] = np.maximum(Xr[:, 2], 1e-3)
        return cv2.projectPoints(Xr.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.rig.cam1.K,
                                 self.rig.cam1.dist)[0].reshape(-1, 2)

    def _solve_pose(self, left, right, X: np.ndarray, uv: np.ndarray, T_guess: np.ndarray):
        """PnP RANSAC from the guess, then LM in both cameras.  Returns (T_world_cam, n_inliers, mask)."""
        cfg = self.cfg
        K0, d0 = self.rig.cam0.K, self.rig.cam0.dist
        uv_u = undistort_px(uv, K0, d0)
        T_cw = invert_pose(T_guess)
        rvec, tvec = pose_to_rvec_tvec(T_cw)
        cv2.setRNGSeed(self._cur_seq)  # RANSAC draws do not depend on what ran before in the process
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X.reshape(-1, 1, 3), uv_u.reshape(-1, 1, 2), K0, None, rvec, tvec, useExtrinsicGuess=True,
            iterationsCount=200, reprojectionError=cfg.pnp_reproj_px, confidence=0.999,
            flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok or inl is None or len(inl) < cfg.min_pnp_inliers:
            return None, 0, None
        mask = np.zeros(len(X), bool)
        mask[inl.ravel()] = True
        T_cw = rvec_tvec_to_pose(rvec, tvec)
        # right-image observations of the inliers for the two-camera refinement
        Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
        idx = np.flatnonzero(mask & (Xc[:, 2] > cfg.min_depth_m))
        uvr, okr = self._stereo_right(left, right, uv[idx], self._right_guess(Xc[idx]), fb_check=False)
        ridx = idx[okr]
        uvr_u = undistort_px(uvr[okr], self.rig.cam1.K, self.rig.cam1.dist)
        res = refine_pose_lm(self.rig, T_cw, X[mask], uv_u[mask], X[ridx], uvr_u, huber_px=cfg.huber_px,
                             outlier_px=cfg.pnp_reproj_px)
        final = np.zeros(len(X), bool)
        final[np.flatnonzero(mask)[res.inliers_left]] = True
        if final.sum() < cfg.min_pnp_inliers:
            return None, 0, None
        return invert_pose(res.T_cam_world), int(final.sum()), final

    # ------------------------------------------------------------------ keyframes

    def _features(self, img: np.ndarray, views: list[int] | None = None):
        from stereopath.device.core.features import PRESETS, detect

        if self._feature_cfg is None:
            if self.cfg.feature_preset not in PRESETS:
                raise ConfigError(f"feature_preset = {self.cfg.feature_preset!r}; known: {sorted(PRESETS)}")
            self._feature_cfg = PRESETS[self.cfg.feature_preset]
        return detect(img, self._feature_cfg, views=views)

    def _keyframe_pose(self, left, right, T_est: np.ndarray, n_inl: int) -> tuple[np.ndarray, int]:
        """Add modified-ASIFT matches against the previous keyframe's 3D features to the pose solve.

        The new keyframe's original-view SIFT features are matched against the previous
        keyframe's features from all affine views (computed in the background since that
        keyframe was created, each with a stereo 3D point).
        """
        self._pending_feats = None
        if not self.cfg.use_asift_keyframes:
            return T_est, n_inl
        from stereopath.device.core.matching import MatchConfig, match, match_guided

        feats0 = self._features(left, views=[0])
        self._pending_feats = feats0
        prev = self._kf_result()
        if prev is None:
            return T_est, n_inl
        prev_feats, prev_X = prev
        if self.cfg.guided_radius_px > 0:
            # the previous keyframe's 3D features projected with the tracked pose: match only nearby
            T_cw = invert_pose(T_est)
            Xc = prev_X @ T_cw[:3, :3].T + T_cw[:3, 3]
            pred = np.full((len(Xc), 2), np.nan)
            front = Xc[:, 2] > self.cfg.min_depth_m
            if np.any(front):
                pred[front] = cv2.projectPoints(Xc[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                                self.rig.cam0.K, self.rig.cam0.dist)[0].reshape(-1, 2)
            mt = match_guided(prev_feats, feats0, pred, self.cfg.guided_radius_px, self._match_cfg or MatchConfig())
            idx = np.asarray(mt.idx).reshape(-1, 2)[:, ::-1]  # (current, previous)
        else:
            mt = match(feats0, prev_feats, self._match_cfg or MatchConfig())
            idx = np.asarray(mt.idx).reshape(-1, 2)
        if len(idx) < self.cfg.min_pnp_inliers:
            return T_est, n_inl
        X = np.vstack([prev_X[idx[:, 1]], self._map.X])
        uv = np.vstack([feats0.xy[idx[:, 0]].astype(np.float64), self._map.uv])
        T_new, n_new, mask = self._solve_pose(left, right, X, uv, T_est)
        if T_new is None:
            return T_est, n_inl
        self.counters["asift_matches"] += int(mask[: len(idx)].sum())
        self._map.keep(mask[len(idx):])
        return T_new, n_new

    def _kf_result(self):
        """The previous keyframe's (features, world points), waiting for the background job if needed."""
        fut = self._kf_future
        if fut is None:
            return None
        return fut.result() if hasattr(fut, "result") else fut

    def _keyframe_features(self, left, right, feats0, T_world_cam: np.ndarray, z0: float):
        """All-view features of a keyframe with stereo 3D points (runs in the background thread)."""
        from stereopath.device.core.features import Features

        n_views = len(self._feature_cfg.views) if getattr(self._feature_cfg, "views", None) else 1
        parts = [feats0]
        if n_views > 1 and getattr(self._feature_cfg, "backend", "ours") != "cv2_affine":
            parts.append(self._features(left, views=list(range(1, n_views))))
        feats = Features.concat(parts) if len(parts) > 1 else feats0
        if len(feats) == 0:
            return None
        if len(feats) > self.cfg.kf_library_max:  # the strongest keypoints of all views
            keep = np.argsort(-feats.response, kind="stable")[: self.cfg.kf_library_max]
            feats = feats.subset(np.sort(keep))
        xy = feats.xy.astype(np.float32)
        uvu = undistort_px(xy, self.rig.cam0.K, self.rig.cam0.dist)
        rays = np.column_stack([(uvu[:, 0] - self.rig.cam0.cx) / self.rig.cam0.fx,
                                (uvu[:, 1] - self.rig.cam0.cy) / self.rig.cam0.fy, np.ones(len(uvu))])
        uvr, ok = self._stereo_right(left, right, xy, self._right_guess(rays * z0))
        Xc, err = triangulate(self.rig, uvu, undistort_px(uvr, self.rig.cam1.K, self.rig.cam1.dist))
        ok &= (err < self.cfg.triangulation_max_px) & (Xc[:, 2] > self.cfg.min_depth_m) & (Xc[:, 2] < self.cfg.max_depth_m)
        if ok.sum() < self.cfg.min_pnp_inliers:
            return None
        Xw = Xc[ok] @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
        return feats.subset(ok), Xw

    def _new_keyframe(self, left, right, T_world_cam: np.ndarray, tracked) -> int:
        """Top up the map with new stereo points; start this keyframe's affine-view features in the background."""
        cfg = self.cfg
        m = self._map
        feats0 = self._pending_feats if tracked else None
        self._pending_feats = None
        T_cw = invert_pose(T_world_cam)
        # right-image guess from the median depth of the current map (or a middle depth)
        z0 = self._default_depth()
        if len(m):
            Xc_m = m.X @ T_cw[:3, :3].T + T_cw[:3, 3]
            if np.any(Xc_m[:, 2] > 0):
                z0 = float(np.median(Xc_m[Xc_m[:, 2] > 0, 2]))
        if cfg.use_asift_keyframes:
            if feats0 is None:
                feats0 = self._features(left, views=[0])
            args = (left, right, feats0, T_world_cam.copy(), z0)
            if self._executor is not None:
                self._kf_future = self._executor.submit(self._keyframe_features, *args)
            else:
                self._kf_future = self._keyframe_features(*args)
        # candidate new map points: corners away from the existing tracks
        need = cfg.max_points - len(m)
        mask = np.full(left.shape[:2], 255, np.uint8)
        for u, v in m.uv.astype(int):
            cv2.circle(mask, (int(u), int(v)), cfg.new_corner_spacing_px, 0, -1)
        cands_all = np.zeros((0, 2), np.float32)
        if need > 0:
            c = cv2.goodFeaturesToTrack(left, maxCorners=need, qualityLevel=0.005,
                                        minDistance=cfg.new_corner_spacing_px, mask=mask, blockSize=5)
            if c is not None:
                cands_all = c.reshape(-1, 2).astype(np.float32)
        if len(cands_all) == 0:
            self._since_kf = 0
            return len(m)
        uvu = undistort_px(cands_all, self.rig.cam0.K, self.rig.cam0.dist)
        rays = np.column_stack([(uvu[:, 0] - self.rig.cam0.cx) / self.rig.cam0.fx,
                                (uvu[:, 1] - self.rig.cam0.cy) / self.rig.cam0.fy, np.ones(len(uvu))])
        uvr, ok = self._stereo_right(left, right, cands_all, self._right_guess(rays * z0))
        uvr_u = undistort_px(uvr, self.rig.cam1.K, self.rig.cam1.dist)
        Xc, err = triangulate(self.rig, uvu, uvr_u)
        ok &= (err < cfg.triangulation_max_px) & (Xc[:, 2] > cfg.min_depth_m) & (Xc[:, 2] < cfg.max_depth_m)
        Xw = Xc @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
        # corners (not SIFT keypoints) become tracked map points, up to max_points
        sel = np.flatnonzero(ok)
        sel = sel[: max(0, need)]
        # observations of the existing points at this keyframe (for offline bundle adjustment)
        k = len(self.keyframe_poses)
        if self.record_observations:
            self.keyframe_poses.append((self._cur_seq, T_world_cam.copy()))
        if (self.record_observations or cfg.refine_points) and len(m):
            Xc_old = m.X @ T_cw[:3, :3].T + T_cw[:3, 3]
            uvr_old, ok_old = self._stereo_right(left, right, m.uv, self._right_guess(Xc_old), fb_check=False)
            if self.record_observations:
                self._record(k, m.ids, m.uv, uvr_old, ok_old)
            if cfg.refine_points and ok_old.any():
                # running mean of each tracked point over its stereo observations at keyframes
                Xc_new, err_new = triangulate(self.rig, undistort_px(m.uv[ok_old], self.rig.cam0.K, self.rig.cam0.dist),
                                              undistort_px(uvr_old[ok_old], self.rig.cam1.K, self.rig.cam1.dist))
                good = (err_new < cfg.triangulation_max_px) & (Xc_new[:, 2] > cfg.min_depth_m) & \
                    (Xc_new[:, 2] < cfg.max_depth_m)
                idx = np.flatnonzero(ok_old)[good]
                Xw_new = Xc_new[good] @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
                n = m.nobs[idx][:, None]
                m.X[idx] = (m.X[idx] * n + Xw_new) / (n + 1)
                m.nobs[idx] += 1
        new_ids = np.arange(self._next_id, self._next_id + len(sel), dtype=np.int64)
        self._next_id += len(sel)
        if self.record_observations and len(sel):
            self._record(k, new_ids, cands_all[sel], uvr[sel], np.ones(len(sel), bool))
            self.landmarks.update({int(i): x for i, x in zip(new_ids, Xw[sel])})
        m.X = np.vstack([m.X, Xw[sel]])
        m.uv = np.vstack([m.uv, cands_all[sel]]).astype(np.float32)
        m.ids = np.concatenate([m.ids, new_ids])
        m.nobs = np.concatenate([m.nobs, np.ones(len(sel))])
        m.uv_kf = m.uv.copy()
        self._since_kf = 0
        self.counters["keyframes"] += 1
        return len(m)

    def _record(self, k: int, ids, uv_left, uv_right, ok_right) -> None:
        """Observations (undistorted pixels) of map points at keyframe ``k``, for bundle adjustment."""
        ul = undistort_px(uv_left, self.rig.cam0.K, self.rig.cam0.dist)
        ur = undistort_px(uv_right[ok_right], self.rig.cam1.K, self.rig.cam1.dist)
        for cam, idv, uv in ((0, ids, ul), (1, ids[ok_right], ur)):
            if len(idv):
                self.observations.append(np.column_stack([np.full(len(idv), k), idv, np.full(len(idv), cam), uv]))

    def _default_depth(self) -> float:
        # a depth that gives a middle disparity on this rig
        return float(np.clip(self._rect.f * self._rect.baseline_m / 20.0, 0.5, 20.0))
