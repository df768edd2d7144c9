"""The default ``stereo`` estimator: metric stereo visual-inertial odometry, a bounded amount of work per frame.

Per frame: the gyro (else a constant-velocity model) predicts the pose; the map points are tracked
into the left image by KLT at their predicted scale, checked backward, retried with a deeper pyramid,
else the frame is relocalised; PnP RANSAC seeds the pose and Levenberg-Marquardt refines it on the
reprojection error in both cameras.  Keyframes are chosen by what the path needs and top up the map
with stereo points; their modified-ASIFT work runs off the frame loop
(:mod:`~stereopath.device.estimation.keyframe_jobs`).  The disparity offset, the cameras' exposure and
the gyro bias are refined on line.  A frame that cannot be tracked is flagged ``imu_only`` or ``lost``
with the predicted pose, never ``ok``.  Design and reasons: docs/architecture.md, "The on-board estimator".
"""

from __future__ import annotations

import dataclasses
import logging
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from stereopath.device.estimation.base import PoseEstimate, TrackStatus, WorldFrame
from stereopath.device.estimation.inertial import (GyroIntegrator, VisionGyroBias, estimate_still,
                                                   gravity_aligned_rotation)
from stereopath.device.core.features import gray
from stereopath.device.core.photometric import measure_relation
from stereopath.device.core.stereo import stereo_right
from stereopath.device.core.scaled_klt import track_scaled
from stereopath.device.estimation.disparity_offset import (KeyframeObservations, OffsetFilter, PriorPath,
                                                          offset_between_keyframes)
from stereopath.device.estimation.offset_window import offset_over_keyframes
from stereopath.device.estimation.gyro_prior import GyroPrior, GyroRotation
from stereopath.device.estimation.keyframe_jobs import KeyframeJob, KeyframeWorker, Ready, Submitted
from stereopath.device.estimation.live_state import LiveState, StereoStats
from stereopath.device.estimation.local_window import WindowKeyframes
from stereopath.device.estimation.moving_start import MovingStart
from stereopath.device.estimation.right_exposure import RightExposure
from stereopath.device.estimation.stereo_measure import PoseGuess, RightMatches, StereoMeasure
from stereopath.device.estimation.tracked_map import TrackedMap
from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.core.geometry import invert_pose, make_pose, rotation_angle_deg, so3_exp, so3_log
from stereopath.device.core.rig import Rig
from stereopath.device.core.stereo_config import StereoConfig

log = logging.getLogger(__name__)

NEW_CORNER_SPACING_PX = 14  # new map points keep this far from the tracked ones
TRACK_KLT_LEVELS = 2  # pyramid of the tracking from the predicted pose
RETRY_KLT_LEVELS = 5  # deeper pyramid of the retry from the last positions when that tracking fails
FB_KLT_LEVELS = 1  # pyramid of the backward (check) track: it starts at the known answer, a refinement
MAX_FAILURES_KEEP_MAP = 10  # failed frames in a row before the map restarts
GYRO_BIAS_WINDOW_S = 1.0  # the gyro bias is refined from this much tracked time at once
STILL_BIAS_SIGMA_RAD_S = 5e-4  # the gyro bias measured still before the first frame (0.03 deg/s)
UNKNOWN_BIAS_SIGMA_RAD_S = 0.1  # no still start: the bias is anything a MEMS gyro has (~6 deg/s)

# a keyframe's stereo observations for the offset's window solve: point ids, rectified rows, the keyframe pose
OffsetView = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class StereoImages:
    """One frame's grey images: the right one in the left camera's grey levels (when the two cameras
    differ, else as captured) and as captured (what the exposure fits measure)."""

    left: np.ndarray
    right: np.ndarray
    right_raw: np.ndarray


class StereoEstimator:
    """The frame loop.  Its live state (poses, map, the corrections applied) is one :class:`LiveState`; the
    keyframes' ASIFT work is a :class:`KeyframeWorker`, polled once per frame, whose corrections the loop
    applies; what it has done is a :class:`StereoStats`."""

    name = "stereo"

    def __init__(self, rig: Rig, config: StereoConfig | None = None) -> None:
        self.rig = rig
        self.cfg = config or StereoConfig()
        self.world_frame: WorldFrame = "first_camera"
        self._geo = StereoMeasure(rig, self.cfg)
        self._state = LiveState()
        self._worker = KeyframeWorker(rig, self.cfg, self._geo)
        self.counts = StereoStats(disparity_offset_mpx=int(round(1000 * self.cfg.disparity_offset.prior_px)))
        self._n_at_kf = 0
        self._t_prev: int | None = None
        self._dt_prev: float | None = None
        self._prev_left: np.ndarray | None = None  # the last tracked image (its camera's pose: T_prev_left)
        self._exposure = RightExposure(self.cfg.exposure.tolerance, self.counts)  # the right camera's grey levels
        self._asift_frame = -(10**9)  # the frame of the last keyframe whose ASIFT work was submitted
        self._offset = OffsetFilter(prior=float(self.cfg.disparity_offset.prior_px))
        # keyframe pairs measured with the prior offset, kept until the offset is first learned
        self._prior_path = PriorPath()
        # the last keyframes' stereo observations for the offset's window solve
        self._offset_views: deque[OffsetView] = deque(maxlen=self.cfg.disparity_offset.keyframes - 1)
        self._pending_G: np.ndarray | None = None
        self._since_kf = 0
        self._failures = 0
        self._gyro: GyroIntegrator | None = None
        self._bias: VisionGyroBias | None = None
        self._start: MovingStart | None = None  # a start in motion, until the path gives gyro bias and gravity
        self.world_rebase: tuple[int, np.ndarray] | None = None  # see MovingStart: (frame seq, motion)
        self._gyro_step: tuple[np.ndarray, float] | None = None  # the gyro's body rotation over the last frame
        self._R_body_cam = None if rig.T_body_cam0 is None else rig.T_body_cam0[:3, :3]
        self._prior = GyroPrior(self.cfg.gyro, self._R_body_cam, UNKNOWN_BIAS_SIGMA_RAD_S)  # the pose solve's
        self._klt = dict(winSize=(self.cfg.klt.klt_window, self.cfg.klt.klt_window), maxLevel=self.cfg.klt.klt_levels,
                         criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))
        self._next_id = 0
        self._cur_seq = 0
        self._window = WindowKeyframes(self.cfg.window) if self.cfg.window.enabled else None

    # ------------------------------------------------------------------ public

    def stats(self) -> dict[str, int]:
        return dataclasses.asdict(self.counts)

    def close(self) -> None:
        """Stop the background keyframe worker (idempotent)."""
        self._worker.close()

    def settle(self) -> None:
        """Let the background work in flight finish, its results kept for the next frame as usual: the
        estimator can then be pickled and resumed (a reprocessing stage's stored progress)."""
        self._worker.settle()
        if self._start is not None:
            self._start.settle(Ready.of)

    def __del__(self) -> None:  # the worker thread must not outlive the estimator
        try:
            self.close()
        except Exception:
            pass

    def process(self, frame: StereoFrame, imu: ImuSamples | None) -> PoseEstimate:
        left, right = gray(frame.left), gray(frame.right)
        self._cur_seq = frame.seq
        if self._state.T_world_cam is None:
            return self._initialise(frame, left, right, imu)
        img = StereoImages(left, self._exposure.corrected(right), right)
        self._join_keyframe_work()
        dt = (frame.t_ns - self._t_prev) * 1e-9
        T_pred, have_rot_prior, gyro = self._predict(frame.t_ns, dt, imu)
        if self._window is not None:
            self._window.gyro_step(self._gyro_step, self._R_body_cam)
        est = self._track(frame, img, T_pred, have_rot_prior, gyro)
        self._refine_gyro_bias(est)
        if self._start is not None:
            self.counts.start_solves += self._start.feed(est, imu, self._worker)
        self._state.T_prev_prev = self._state.T_world_cam
        self._state.T_world_cam = est.T_world_cam
        self._t_prev = frame.t_ns
        self._dt_prev = dt
        return est

    def _join_keyframe_work(self) -> None:
        """The frame's one join point: the finished keyframe jobs' corrections (oldest first), then the
        path's re-measure with a newly learned disparity offset, each one rigid motion of the live state."""
        st = self._state
        for c in self._worker.poll(st.C):
            if c.window is not None:
                self._window.joined(c.window, c.G, c.C_since, st, self.counts)
                continue
            if c.G is not None:
                st.apply(c.G)
                self.counts.kf_corrections += 1
                self.counts.asift_matches += c.n_asift
            self.counts.asift_views += c.n_views
            if c.library is not None:
                st.library, st.T_library = c.library, c.T_library
        if self._pending_G is not None:  # the path since the start, re-measured with the learned offset
            st.apply(self._pending_G)
            self._pending_G = None
        if self._start is not None:
            self._take_moving_start()

    def _take_moving_start(self) -> None:
        """A start in motion, once solved: the gyro bias, and one rotation of the live state about the
        world's origin that makes the world gravity aligned as a still start would have."""
        st = self._state
        solved = self._start.poll()
        if solved is None:
            return
        self._start = None
        if self._bias is not None:  # the gyro bias estimated on line (gyro.estimate_bias)
            self._gyro.bias = solved.fit.gyro.bias_rad_s.copy()
            self._bias.reset(solved.fit.gyro.bias_rad_s, max(solved.fit.gyro.sigma_rad_s, STILL_BIAS_SIGMA_RAD_S))
            st.T_bias_start = None if st.T_bias_start is None else st.T_world_cam.copy()
        G = solved.leveling(st.C[:3, :3], self._R_body_cam)
        st.apply(G)  # and the offset window's starting poses, which its motions start from
        self._offset_views = deque([(i, b, G @ T) for i, b, T in self._offset_views], maxlen=self._offset_views.maxlen)
        self.world_frame, self.world_rebase = "gravity_aligned", (self._cur_seq, G)
        self.counts.start_solved_frame = self._cur_seq

    # ------------------------------------------------------------------ stages

    def _initialise(self, frame: StereoFrame, left: np.ndarray, right: np.ndarray,
                    imu: ImuSamples | None) -> PoseEstimate:
        R_world_cam = np.eye(3)
        if imu is not None and len(imu) and self._R_body_cam is not None:
            still = estimate_still(imu)
            if still is not None:
                self._gyro = GyroIntegrator(still.gyro_bias_rad_s)
                bias0, sigma0 = still.gyro_bias_rad_s, STILL_BIAS_SIGMA_RAD_S
                R_world_body = gravity_aligned_rotation(still.accel_mean_m_s2)
                R_world_cam = R_world_body @ self._R_body_cam
                self.world_frame = "gravity_aligned"
                log.info("IMU still at start: gyro bias %s rad/s, |g| = %.3f m/s^2; world frame gravity aligned",
                         np.round(still.gyro_bias_rad_s, 5), still.gravity_norm_m_s2)
            else:
                self._gyro = GyroIntegrator(None)
                bias0, sigma0 = None, UNKNOWN_BIAS_SIGMA_RAD_S
                self._start = MovingStart(self.rig.T_body_cam0)
                self._start.add_imu(imu)
                log.info("IMU not still before the first frame: world frame = first camera until the tracked"
                         " path gives the gyro bias and gravity")
            self._gyro.feed_and_integrate(imu, frame.t_ns, frame.t_ns)
            if self.cfg.gyro.estimate_bias:
                self._bias = VisionGyroBias(bias0, sigma0, window_s=GYRO_BIAS_WINDOW_S)
        T = make_pose(R_world_cam, np.zeros(3))
        self._state.T_world_cam = T
        self._state.T_bias_start = T.copy()
        self._t_prev = frame.t_ns
        self._prev_left, self._state.T_prev_left = left, T.copy()
        if self.cfg.exposure.match:
            # a first measurement of the two cameras' exposure on this frame's stereo matches
            xy = self._corners(left, np.full(left.shape[:2], 255, np.uint8), self.cfg.keyframes.max_points)
            if len(xy):
                z0 = self._default_depth()
                self._exposure.take(measure_relation(
                    left, right, xy, lambda image: self._geo.stereo_points(left, image, xy, z0)[::2]))
        n = self._new_keyframe(StereoImages(left, self._exposure.corrected(right), right), T)
        status = TrackStatus.OK if n >= self.cfg.geometry.min_pnp_inliers else TrackStatus.LOST
        if self._start is not None and status is TrackStatus.OK:
            self._start.add_pose(frame.t_ns, T)
        return PoseEstimate(frame.seq, frame.t_ns, T.copy(), status, inliers=n, keyframe=True,
                            note="" if status is TrackStatus.OK else "no_stereo_points")

    def _predict(self, t_ns: int, dt: float, imu: ImuSamples | None) -> tuple[np.ndarray, bool, GyroRotation | None]:
        T_prev = self._state.T_world_cam
        # constant velocity (translation and rotation) from the last two poses
        if self._state.T_prev_prev is not None and self._dt_prev:
            T_rel = invert_pose(self._state.T_prev_prev) @ T_prev  # motion in the previous camera frame
            scale = dt / self._dt_prev
            R_rel = so3_exp(so3_log(T_rel[:3, :3]) * scale)
            t_rel = T_rel[:3, 3] * scale
        else:
            R_rel, t_rel = np.eye(3), np.zeros(3)
        have_rot = False
        if self._gyro is not None and self._R_body_cam is not None:
            R_b = self._gyro.feed_and_integrate(imu, self._t_prev, t_ns)
            self._gyro_step = None if R_b is None else (R_b, dt)
            if R_b is not None:
                Rbc = self._R_body_cam
                R_rel = Rbc.T @ R_b @ Rbc
                have_rot = True
        return T_prev @ make_pose(R_rel, t_rel), have_rot, self._prior.frame(self._gyro_step, self._state.T_kf, self.counts.keyframes, self._bias)

    def _track(self, frame: StereoFrame, img: StereoImages, T_pred: np.ndarray, have_rot: bool, gyro: GyroRotation | None) -> PoseEstimate:
        cfg = self.cfg
        left = img.left
        m = self._state.map
        T_est = None
        n_inl = 0
        note = ""
        relocalised = False
        if len(m) >= cfg.geometry.min_pnp_inliers and self._prev_left is not None:
            # first from the predicted pose; then a deeper pyramid from the last positions (a motion
            # the prediction missed: the first frames without a velocity, a jolt, dropped frames)
            attempts = [(T_pred, TRACK_KLT_LEVELS)]
            if RETRY_KLT_LEVELS > TRACK_KLT_LEVELS:
                attempts.append((None, RETRY_KLT_LEVELS))
            map_right = None  # the right-image pixels of the kept points the pose solve measured (NaN: none)
            for k, (T_guess, levels) in enumerate(attempts):
                uv_new, good = self._klt_track(left, T_guess, levels)
                if good.sum() < cfg.geometry.min_pnp_inliers:
                    note = "too_few_tracked"
                    continue
                pairs: list[RightMatches] = []
                T_est, n_inl, inl = self._geo.solve_pose(left, img.right, m.X[good], uv_new[good], PoseGuess(T_pred, gyro=gyro),
                                                         self._cur_seq, stereo_out=pairs)
                if T_est is None:
                    note = "pose_failed"
                    continue
                if cfg.exposure.match:  # the cameras' exposure, measured at every frame
                    self._exposure.fit(left, img.right_raw, pairs[0].left, pairs[0].right)
                map_right = pairs[0].per_point(len(inl))[inl]
                m.uv = uv_new.astype(np.float32)
                m.keep(good)
                m.keep(inl)
                if k:
                    self.counts.retracked += 1
                break
        else:
            note = "no_map"
        if T_est is None:
            T_est, n_inl = self._relocalise(img, T_pred)
            relocalised = T_est is not None
        self._since_kf += 1
        if T_est is not None:
            self._failures = 0
            self._prev_left, self._state.T_prev_left = left, T_est.copy()
            if relocalised:
                self.counts.relocalised += 1
                self._state.map = TrackedMap()
                self._new_keyframe(img, T_est)
                return PoseEstimate(frame.seq, frame.t_ns, T_est, TrackStatus.OK, inliers=n_inl, keyframe=True,
                                    note="relocalised")
            is_kf = self._need_keyframe(T_est, n_inl)
            if is_kf:
                self._new_keyframe(img, T_est, map_right)
            return PoseEstimate(frame.seq, frame.t_ns, T_est, TrackStatus.OK, inliers=n_inl, keyframe=is_kf)
        # Vision failed (black frame, lens cap, no overlap, blur): fall back to the IMU rotation (or
        # constant velocity), flagged.  The map and the last good image are kept so the next good
        # frame can be tracked against them; after several failures in a row the map restarts here.
        status = TrackStatus.IMU_ONLY if have_rot else TrackStatus.LOST
        if have_rot:
            self.counts.imu_only += 1
        else:
            self.counts.lost += 1
        self._failures += 1
        is_kf = False
        if self._failures > MAX_FAILURES_KEEP_MAP or len(m) < cfg.geometry.min_pnp_inliers:
            self._state.map = TrackedMap()
            n = self._new_keyframe(img, T_pred)
            if n >= cfg.geometry.min_pnp_inliers:
                self._prev_left, self._state.T_prev_left = left, T_pred.copy()
                is_kf = True
        return PoseEstimate(frame.seq, frame.t_ns, T_pred, status, inliers=0, keyframe=is_kf, note=note)

    def _refine_gyro_bias(self, est: PoseEstimate) -> None:
        """Feed the bias window this frame's gyro step; close it with the tracked rotation when full.
        A frame that is not tracked (or relocalised: a new map) restarts the window."""
        if self._bias is None or self._R_body_cam is None:
            return
        ok = est.status is TrackStatus.OK
        if not ok or est.note == "relocalised" or self._gyro_step is None or self._state.T_bias_start is None:
            self._bias.restart()
            self._state.T_bias_start = est.T_world_cam.copy() if ok else None
            return
        self._bias.add(*self._gyro_step)
        if not self._bias.window_full:
            return
        Rbc = self._R_body_cam
        R_vis_body = Rbc @ (self._state.T_bias_start[:3, :3].T @ est.T_world_cam[:3, :3]) @ Rbc.T
        if self._bias.update(R_vis_body):
            self._gyro.bias = self._bias.bias.copy()
            self.counts.gyro_bias_updates = self._bias.updates
            log.debug("gyro bias %s rad/s (+- %.5f)", np.round(self._bias.bias, 5), self._bias.sigma_rad_s)
        self.counts.gyro_bias_rejected = self._bias.rejected
        self._state.T_bias_start = est.T_world_cam.copy()

    @property
    def gyro_bias_rad_s(self) -> np.ndarray | None:
        """The gyro bias in use (None without an IMU)."""
        return None if self._gyro is None else self._gyro.bias.copy()

    def _need_keyframe(self, T_est: np.ndarray, n_inl: int) -> bool:
        """What the path needs: points to track, a view change ASIFT can still bridge, or age."""
        cfg = self.cfg
        if n_inl < cfg.keyframes.min_tracked or n_inl < cfg.keyframes.track_ratio * self._n_at_kf:
            return True
        if self._since_kf >= cfg.keyframes.max_frames:
            return True
        if self._state.T_kf is not None and rotation_angle_deg(self._state.T_kf[:3, :3].T @ T_est[:3, :3]) > cfg.keyframes.rotation_deg:
            return True
        m = self._state.map
        if cfg.keyframes.parallax_px > 0 and len(m):
            return float(np.median(np.linalg.norm(m.uv - m.uv_kf, axis=1))) > cfg.keyframes.parallax_px
        return False

    def _klt_track(self, left: np.ndarray, T_pred: np.ndarray | None, levels: int) -> tuple[np.ndarray, np.ndarray]:
        """Track the map into ``left``; returns new pixels and the good mask (the map is not changed).

        ``T_pred`` seeds each point at its projection; ``None`` starts from the last positions."""
        m = self._state.map
        guess = m.uv.copy()
        scale = np.ones(len(m.uv))
        if T_pred is not None:
            T_cw = invert_pose(T_pred)
            Xc = m.X @ T_cw[:3, :3].T + T_cw[:3, 3]
            front = Xc[:, 2] > 1e-3
            if np.any(front):
                pts = cv2.projectPoints(Xc[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                        self.rig.cam0.K, self.rig.cam0.dist)[0].reshape(-1, 2)
                guess[front] = pts
            if self.cfg.klt.klt_scale_step > 0 and self._state.T_prev_left is not None:
                # each point's window grows by its depth in the previous image over its predicted depth now
                T_pw = invert_pose(self._state.T_prev_left)
                z_prev = m.X @ T_pw[2, :3] + T_pw[2, 3]
                known = front & (z_prev > 1e-3)
                scale[known] = z_prev[known] / Xc[known, 2]
        # a point predicted farther outside the image than KLT's coarsest level reaches has left the view
        w, h = self.rig.cam0.size
        reach = (self.cfg.klt.klt_window // 2 + 2) * 2**levels + 2
        live = np.flatnonzero(((guess >= -reach) & (guess < (w - 1 + reach, h - 1 + reach))).all(1))
        p1, both, fb = guess.astype(np.float32), np.zeros(len(guess), bool), np.full(len(guess), np.inf)
        # forward, then back from the new positions seeded with the old ones: a true track converges there at once
        p1[live], both[live], fb[live] = track_scaled(self._prev_left, left, m.uv[live], guess[live], scale[live],
                                                      self.cfg.klt.klt_scale_step, dict(self._klt, maxLevel=levels),
                                                      min(levels, FB_KLT_LEVELS))
        good = both & (fb < self.cfg.klt.fb_max_px)
        good &= (p1[:, 0] >= 0) & (p1[:, 0] < w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] < h - 1)
        return p1, good

    def _relocalise(self, img: StereoImages, T_pred: np.ndarray) -> tuple[np.ndarray | None, int]:
        """The pose from SIFT matches against the newest keyframe library (no trust in the prediction)."""
        lib = self._state.library
        if lib is None or not self.cfg.asift.enabled:
            return None, 0
        from stereopath.device.core.matching import MatchConfig, match

        feats0 = self._worker.features(img.left, views=[0])
        mt = match(feats0, lib.feats, MatchConfig())
        idx = np.asarray(mt.idx).reshape(-1, 2)
        if len(idx) < self.cfg.geometry.min_pnp_inliers:
            return None, 0
        T_l = self._state.T_library
        X = lib.X_cam[idx[:, 1]] @ T_l[:3, :3].T + T_l[:3, 3]
        T, n, _ = self._geo.solve_pose(img.left, img.right, X, feats0.xy[idx[:, 0]].astype(np.float64),
                                       PoseGuess(T_pred, trusted=False), self._cur_seq)
        if T is None:
            return None, 0
        log.info("frame %d relocalised against keyframe %d (%d inliers)", self._cur_seq, lib.seq, n)
        return T, n

    # ------------------------------------------------------------------ keyframes

    def _new_keyframe(self, img: StereoImages, T_world_cam: np.ndarray, map_right: np.ndarray | None = None) -> int:
        """Top up the map with new stereo points; hand the keyframe's ASIFT work to the worker.  ``map_right``: the
        map's right-image pixels the frame's pose solve measured (NaN: none), else they are measured here."""
        cfg = self.cfg
        m = self._state.map
        left, right = img.left, img.right
        T_cw = invert_pose(T_world_cam)
        # right-image guess from the median depth of the current map (or a middle depth)
        z0 = self._default_depth()
        if len(m):
            Xc_m = m.X @ T_cw[:3, :3].T + T_cw[:3, 3]
            if np.any(Xc_m[:, 2] > 0):
                z0 = float(np.median(Xc_m[Xc_m[:, 2] > 0, 2]))
        self._submit_keyframe_job(img, T_world_cam, z0)
        # candidate new map points: corners away from the existing tracks
        need = cfg.keyframes.max_points - len(m)
        mask = np.full(left.shape[:2], 255, np.uint8)
        for u, v in m.uv.astype(int):
            cv2.circle(mask, (int(u), int(v)), NEW_CORNER_SPACING_PX, 0, -1)
        cands_all = np.zeros((0, 2), np.float32)
        if need > 0:
            cands_all = self._corners(left, mask, need)
        # observations of the existing points at this keyframe (refinement, disparity offset)
        seen = (np.zeros((0, 2)), np.zeros((0, 2)))
        if len(m):
            seen = self._observe_map(img, T_world_cam, map_right)
        sel = np.zeros(0, np.int64)
        uvr = np.zeros((0, 2), np.float32)
        Xw = np.zeros((0, 3))
        if len(cands_all):
            uvr, Xc, ok = self._geo.stereo_points(left, right, cands_all, z0)
            Xw = Xc @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
            # corners (not SIFT keypoints) become tracked map points, up to max_points
            sel = np.flatnonzero(ok)[: max(0, need)]
        if cfg.exposure.match:
            self._exposure.fit(left, img.right_raw, np.vstack([seen[0], cands_all[sel]]), np.vstack([seen[1], uvr[sel]]))
        new_ids = np.arange(self._next_id, self._next_id + len(sel), dtype=np.int64)
        self._next_id += len(sel)
        m.X = np.vstack([m.X, Xw[sel]])
        m.uv = np.vstack([m.uv, cands_all[sel]]).astype(np.float32)
        m.ids = np.concatenate([m.ids, new_ids])
        m.nobs = np.concatenate([m.nobs, np.ones(len(sel))])
        new_obs = self._geo.rectified_observations(cands_all[sel], uvr[sel]) if len(sel) else np.zeros((0, 3))
        m.obs = np.vstack([m.obs, new_obs])
        m.obs_kf = np.concatenate([m.obs_kf, np.full(len(sel), self.counts.keyframes, np.int64)])
        m.uv_kf = m.uv.copy()
        if cfg.disparity_offset.estimate and cfg.disparity_offset.keyframes > 2:
            # the points measured in stereo here, as measured (no offset removed); the pose only starts the
            # window's solve (its motions are unknowns), so a later keyframe correction does not stale it
            at = m.obs_kf == self.counts.keyframes
            self._offset_views.append((m.ids[at].copy(), m.obs[at].copy(), T_world_cam.copy()))
        self._submit_window(T_world_cam)
        self._since_kf = 0
        self._state.T_kf = T_world_cam.copy()
        self._n_at_kf = len(m)
        self.counts.keyframes += 1
        return len(m)

    def _submit_window(self, T_world_cam: np.ndarray) -> None:
        """This keyframe's stereo observations into the local window, and its solve to the worker."""
        if self._window is not None:
            m, st = self._state.map, self._state
            at = m.obs_kf == self.counts.keyframes
            self._window.add(self._cur_seq, T_world_cam, m.ids[at], m.obs[at], st.C)
            job = self._window.job(st.C, self._geo.disparity_offset_px, self._bias, m)
            if job is not None and self._worker.submit_window(job) is not Submitted.DROPPED:
                self.counts.window_solves += 1

    def _asift_needed(self, T_world_cam: np.ndarray) -> bool:
        """ASIFT work where the view changed: a rotation since the last ASIFT keyframe (the tilt the
        affine views bridge), or its age; a keyframe in between only tops up the tracked map."""
        st = self._state
        if st.T_asift is None or st.library is None and not self._worker.in_flight:
            return True
        if self._cur_seq - self._asift_frame >= self.cfg.asift.max_frames:
            return True
        return rotation_angle_deg(st.T_asift[:3, :3].T @ T_world_cam[:3, :3]) >= self.cfg.asift.min_rotation_deg

    def _submit_keyframe_job(self, img: StereoImages, T_world_cam: np.ndarray, z0: float) -> None:
        """Hand this keyframe's ASIFT work to the worker (which keeps one job running and one waiting)."""
        if not self.cfg.asift.enabled:
            return
        if not self._asift_needed(T_world_cam):
            self.counts.kf_jobs_deferred += 1
            return
        st, m = self._state, self._state.map
        library = None if st.library is None else (st.library, st.T_library.copy(), st.C.copy())
        job = KeyframeJob(self._cur_seq, img.left, img.right, T_world_cam.copy(), z0, m.X.copy(),
                          m.uv.astype(np.float64), st.C.copy(), library)
        outcome = self._worker.submit(job)
        if outcome is not Submitted.QUEUED:
            self.counts.kf_jobs_skipped += 1
        if outcome is Submitted.DROPPED:
            return
        self.counts.kf_jobs += 1
        st.T_asift, self._asift_frame = T_world_cam.copy(), self._cur_seq

    def _corners(self, left: np.ndarray, mask: np.ndarray, n: int) -> np.ndarray:
        """Up to ``n`` corners of ``left`` where ``mask`` is set (candidate new map points)."""
        c = cv2.goodFeaturesToTrack(left, maxCorners=n, qualityLevel=0.005,
                                    minDistance=NEW_CORNER_SPACING_PX, mask=mask, blockSize=5)
        return np.zeros((0, 2), np.float32) if c is None else c.reshape(-1, 2).astype(np.float32)

    def _observe_map(self, img: StereoImages, T_world_cam: np.ndarray,
                     map_right: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Stereo of the tracked points at this keyframe: the running mean of each point's
        triangulations, and the disparity offset from the last keyframe to this one.
        Returns the left and right pixels of the points found in the right image."""
        cfg = self.cfg
        m = self._state.map
        if map_right is None:
            T_cw = invert_pose(T_world_cam)
            Xc_old = m.X @ T_cw[:3, :3].T + T_cw[:3, 3]
            uvr_old, ok_old = stereo_right(self.rig, img.left, img.right, m.uv, self._geo.right_guess(Xc_old), cfg.klt,
                                          fb_check=False, levels=cfg.klt.seeded_stereo_levels)
        else:
            uvr_old, ok_old = map_right, np.isfinite(map_right[:, 0])
        idx_o = np.flatnonzero(ok_old)
        seen = (m.uv[idx_o], uvr_old[idx_o])  # copies (index arrays)
        if not ok_old.any():
            return seen
        offset_before = self._geo.disparity_offset_px
        if cfg.disparity_offset.estimate:
            self._update_disparity_offset(idx_o, uvr_old[idx_o], T_world_cam)
        Xc_new, err_new = self._geo.triangulate(m.uv[idx_o], uvr_old[idx_o])
        good = self._geo.good_points(Xc_new, err_new)
        idx = idx_o[good]
        if self._geo.disparity_offset_px != offset_before:
            # the earlier triangulations carry the old offset: restart each point's mean from this keyframe
            m.nobs[idx] = 0
        # running mean of each tracked point over its stereo observations at keyframes
        Xw_new = Xc_new[good] @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
        n = m.nobs[idx][:, None]
        m.X[idx] = (m.X[idx] * n + Xw_new) / (n + 1)
        m.nobs[idx] += 1
        return seen

    def _update_disparity_offset(self, idx: np.ndarray, uv_right: np.ndarray, T_world_cam: np.ndarray) -> None:
        """Fuse the offset seen between the last keyframe and this one (points measured in stereo at both)."""
        m = self._state.map
        B = self._geo.rectified_observations(m.uv[idx], uv_right)
        kf = self.counts.keyframes
        both = m.obs_kf[idx] == kf - 1
        if self._state.T_kf is not None and both.sum() >= self.cfg.geometry.min_pnp_inliers:
            pair = KeyframeObservations(m.obs[idx[both]], B[both], self._state.T_kf, T_world_cam)
            if self.cfg.disparity_offset.keyframes > 2 and len(self._offset_views) >= 2:
                est = offset_over_keyframes(self._geo.rect, list(self._offset_views) + [(m.ids[idx], B, T_world_cam)],
                                            self._offset.max_inflation)
                self.counts.disparity_offset_windows += 1
            else:
                est = offset_between_keyframes(self._geo.rect, pair, self._offset.max_inflation)
            if not (learned_before := self._offset.ready):  # motions measured with the prior, for the correction
                self._prior_path.add(kf, pair)
            used = self._offset.update(est)
            self.counts.disparity_offset_pairs = self._offset.n
            self.counts.disparity_offset_unidentified = self._offset.unidentified
            log.debug("keyframe %d: disparity offset %s (used %s), fused %.3f +- %.3f px", self._cur_seq, est, used,
                      self._offset.value, self._offset.sigma)
            if used and self._offset.ready:
                if not learned_before:
                    self._pending_G = self._prior_path.correction(  # applied at the next frame
                        self._geo.rect, kf, T_world_cam, self._geo.disparity_offset_px, self._offset.value,
                        self.cfg.asift.max_correction_deg)
                    self.counts.disparity_offset_path_corrections += int(self._pending_G is not None)
                self._geo.disparity_offset_px = self._offset.value
                self.counts.disparity_offset_mpx = int(round(1000 * self._offset.value))
        m.obs[idx] = B
        m.obs_kf[idx] = kf

    def _default_depth(self) -> float:
        # a depth that gives a middle disparity on this rig
        return float(np.clip(self._geo.rect.f * self._geo.rect.baseline_m / 20.0, 0.5, 20.0))
