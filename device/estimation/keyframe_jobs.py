"""The keyframe worker of the ``stereo`` estimator: modified-ASIFT work off the frame loop.

One worker thread, one job running and one waiting (a newer keyframe replaces the waiting one): the
keyframe's affine views are detected, its SIFT matched against the previous keyframe's library around
the positions the tracked pose predicts, the keyframe pose solved from those matches and the tracked
map, and the keyframe's own library built.  The frame loop joins the result at the first frame after it
is ready and never waits: the correction moves the live state (pose and map) as one rigid motion, mapped
through the corrections applied since the job was submitted.
See docs/architecture.md, "The on-board estimator".
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from stereopath.device.core.geometry import invert_pose, project_to_se3 as rigid, rotation_angle_deg

log = logging.getLogger(__name__)

_LIVE_POSES = ("_T_world_cam", "_T_prev_prev", "_T_prev_left", "_T_kf", "_T_library", "_T_asift", "_T_bias_start")
MAX_SIMULATED_TILT = 4.0  # larger predicted view changes are simulated at this tilt (latitude ~76 deg)


@dataclass
class Library:
    """A keyframe's features of all views, each with a stereo 3D point in that keyframe's camera frame."""

    seq: int
    feats: object  # stereopath.device.core.features.Features
    X_cam: np.ndarray


@dataclass
class Job:
    """A keyframe job in flight: its future and the world it was submitted in."""

    future: object  # concurrent.futures.Future or Ready
    C_sub: np.ndarray  # the cumulative live-state correction when it was submitted
    prev: object  # what it matches against: a (Library, T_world_kf, C) triple, or the previous Job


@dataclass
class KeyframeResult:
    seq: int
    T_tracked: np.ndarray  # the keyframe pose the frame loop used (world at submission)
    T_refined: np.ndarray | None  # from the ASIFT matches and the tracked map, None if not solved
    n_asift: int
    library: Library | None  # this keyframe's library, or the one it matched against when it has none
    T_library: np.ndarray | None  # pose of that library's keyframe (world at submission, corrected)
    T_library_pre: np.ndarray | None = None  # the same without this job's own correction
    n_views: int = 0  # affine views simulated for the match (predicted from the view change)


class Ready:
    """A finished result with the Future interface (the synchronous mode)."""

    def __init__(self, value) -> None:
        self._value = value

    def done(self) -> bool:
        return True

    def result(self):
        return self._value


def predicted_view_change(X_world: np.ndarray, T_prev: np.ndarray, T_cur: np.ndarray) -> tuple[float, float]:
    """The affine view change from the previous keyframe to this one, as ASIFT parameters.

    Returns ``(tilt, longitude_deg)`` in the current image: ``tilt = 1 / cos(theta)`` with ``theta``
    the median angle between the two cameras' viewing rays to the points ``X_world`` (a pure
    rotation changes no viewing direction: tilt 1), and the longitude the image direction along
    which the viewpoint moved (where a surface facing one camera is foreshortened in the other)."""
    X = np.asarray(X_world, np.float64).reshape(-1, 3)
    if len(X) == 0:
        return 1.0, 0.0
    R_cw = T_cur[:3, :3].T
    rc = (X - T_cur[:3, 3]) @ R_cw.T  # rays in the current camera frame
    rp = (X - T_prev[:3, 3]) @ R_cw.T
    ok = (rc[:, 2] > 0) & (np.linalg.norm(rp, axis=1) > 0)
    if not ok.any():
        return 1.0, 0.0
    rc = rc[ok] / np.linalg.norm(rc[ok], axis=1, keepdims=True)
    rp = rp[ok] / np.linalg.norm(rp[ok], axis=1, keepdims=True)
    theta = float(np.median(np.arccos(np.clip(np.sum(rc * rp, axis=1), -1.0, 1.0))))
    tilt = 1.0 / max(np.cos(theta), 1e-3)
    d = rp - rc  # the move of the viewpoint, seen from the current camera (an axis: doubled angles)
    a = 2.0 * np.arctan2(d[:, 1], d[:, 0])
    w = np.hypot(d[:, 0], d[:, 1])
    phi = 0.5 * np.degrees(np.arctan2(np.sum(w * np.sin(a)), np.sum(w * np.cos(a))))
    return float(tilt), float(phi % 180.0)


def resolve_previous(source, C_sub: np.ndarray):
    """The library a job matches against and its keyframe pose, in the world of the job's submission.

    ``source`` is a ``(library, T_world_kf, C)`` triple, or the previous job (already finished:
    the worker runs jobs in order), whose result is mapped through the corrections between the
    two submissions."""
    if source is None:
        return None, None
    if isinstance(source, Job):
        try:
            res = source.future.result()
        except Exception:
            return None, None
        if res is None or res.library is None or res.T_library is None:
            return None, None
        # not joined before this job was submitted: this job's world lacks the previous job's own
        # correction, so the library sits where the tracked state put it
        return res.library, rigid(C_sub @ invert_pose(source.C_sub)) @ res.T_library_pre
    lib, T, C = source
    return lib, rigid(C_sub @ invert_pose(C)) @ T


class KeyframeJobs:
    """Mixin of :class:`~stereopath.device.estimation.stereo_vo.StereoEstimator`: the keyframe queue.

    Uses the estimator's ``cfg``, ``rig``, ``_geo`` (StereoMeasure), ``_map``, ``counters`` and
    live poses; owns ``_jobs``, ``_executor``, ``_C``, ``_library``, ``_T_library``."""

    def _init_keyframe_jobs(self) -> None:
        self._jobs: list[Job] = []  # keyframe jobs in flight, oldest first: at most one running, one waiting
        self._C = np.eye(4)  # product of the corrections applied to the live state so far
        self._library: Library | None = None  # the newest keyframe library joined
        self._T_library: np.ndarray | None = None  # its keyframe's pose in the live world
        self._T_asift: np.ndarray | None = None  # pose of the last keyframe whose ASIFT work was submitted
        self._asift_frame = -(10**9)  # its frame number
        self._executor = None
        self._feature_cfg = None
        self._match_cfg = None
        if self.cfg.asift.enabled and self.cfg.keyframes.background:
            from concurrent.futures import ThreadPoolExecutor

            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="keyframe-features")

    def close(self) -> None:
        """Stop the background keyframe worker (idempotent)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None

    def _features(self, img: np.ndarray, views: list[int] | None = None):
        from stereopath.device.core.features import detect, get_preset

        if self._feature_cfg is None:
            self._feature_cfg = get_preset(self.cfg.asift.feature_preset)
        return detect(img, self._feature_cfg, views=views)

    def _apply_correction(self, G: np.ndarray) -> None:
        """One rigid motion of the live state keeps the map and the current pose consistent."""
        self._map.move(G)
        for name in _LIVE_POSES:
            T = getattr(self, name)
            if T is not None:
                setattr(self, name, G @ T)
        self._C = rigid(G @ self._C)

    def _join_keyframe_job(self) -> None:
        """Take the finished keyframe jobs' results, oldest first (never waits)."""
        while self._jobs and self._jobs[0].future.done():
            job = self._jobs.pop(0)
            try:
                res: KeyframeResult | None = job.future.result()
            except Exception:  # a failed job costs one keyframe's ASIFT, never the session
                log.exception("keyframe feature job failed")
                continue
            if res is None:
                continue
            # the job worked in the world of its submission; corrections applied since map it to the live one
            C_since = self._C @ invert_pose(job.C_sub)
            if res.T_refined is not None:
                G = rigid(C_since @ res.T_refined @ invert_pose(res.T_tracked) @ invert_pose(C_since))
                ang = rotation_angle_deg(G[:3, :3])
                log.debug("keyframe %d: correction %.3f deg, %.4f m", res.seq, ang, float(np.linalg.norm(G[:3, 3])))
                if ang <= self.cfg.asift.max_correction_deg:
                    self._apply_correction(G)
                    self.counters["kf_corrections"] += 1
                    self.counters["asift_matches"] += res.n_asift
                else:
                    log.info("keyframe %d: ASIFT correction of %.2f deg rejected", res.seq, ang)
            self.counters["asift_views"] += res.n_views
            if res.library is not None and res.T_library is not None:
                # the job's belief of its keyframe (refined) in the live world, before its own correction
                self._library = res.library
                self._T_library = C_since @ res.T_library

    def _join_keyframe_jobs_moving(self, T_world_cam: np.ndarray) -> np.ndarray:
        """Join the jobs finished since the frame began, for a pose measured before the join: the
        corrections move the map and the live poses, and this pose is returned moved with them."""
        C0 = self._C.copy()
        self._join_keyframe_job()
        return T_world_cam if np.array_equal(C0, self._C) else rigid(self._C @ invert_pose(C0)) @ T_world_cam

    def _asift_matches(self, prev: Library, prev_X: np.ndarray, feats0, T_tracked: np.ndarray) -> np.ndarray:
        """(current, previous) index pairs of the keyframe's original view against the previous library."""
        from stereopath.device.core.matching import MatchConfig, match, match_guided

        if self.cfg.asift.guided_radius_px <= 0:
            mt = match(feats0, prev.feats, self._match_cfg or MatchConfig())
            return np.asarray(mt.idx).reshape(-1, 2)
        T_cw = invert_pose(T_tracked)
        Xc = prev_X @ T_cw[:3, :3].T + T_cw[:3, 3]
        pred = np.full((len(Xc), 2), np.nan)
        front = Xc[:, 2] > self.cfg.geometry.min_depth_m
        if np.any(front):
            pred[front] = cv2.projectPoints(Xc[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                            self.rig.cam0.K, self.rig.cam0.dist)[0].reshape(-1, 2)
        mt = match_guided(prev.feats, feats0, pred, self.cfg.asift.guided_radius_px, self._match_cfg or MatchConfig())
        return np.asarray(mt.idx).reshape(-1, 2)[:, ::-1]

    def _keyframe_job(self, seq: int, left, right, T_tracked: np.ndarray, z0: float, X_map: np.ndarray,
                      uv_map: np.ndarray, prev_source, C_sub: np.ndarray) -> KeyframeResult:
        """Modified-ASIFT work of one keyframe (on the worker thread): the joint pose, then the library.

        The keyframe's original-view SIFT is matched against the previous library (all views of
        the previous keyframe, each with a 3D point) around the positions the tracked pose
        predicts; those matches and the tracked map points give the keyframe pose."""
        prev, T_prev = resolve_previous(prev_source, C_sub)
        predicted = self.cfg.asift.views == "predicted"
        feats = self._features(left, views=[0] if predicted else None)
        T_ref, n_asift, n_views = None, 0, 0
        if prev is not None and len(feats):
            prev_X = prev.X_cam @ T_prev[:3, :3].T + T_prev[:3, 3]
            cur = feats.original_view()
            if predicted:
                cur = self._with_predicted_views(left, cur, prev_X, T_prev, T_tracked)
                n_views = int(cur.view.max())
            idx = self._asift_matches(prev, prev_X, cur, T_tracked)
            if len(idx) >= self.cfg.geometry.min_pnp_inliers:
                X = np.vstack([prev_X[idx[:, 1]], X_map])
                uv = np.vstack([cur.xy[idx[:, 0]].astype(np.float64), uv_map])
                T_new, _, mask = self._geo.solve_pose(left, right, X, uv, T_tracked, seed=seq)
                # the tracked map must still fit the joint pose: ASIFT matches that pull the pose away
                # from it (repeated texture, a wrong 3D point) would turn its points into outliers
                if T_new is not None and mask[len(idx):].sum() >= self.cfg.asift.map_agreement * len(X_map):
                    T_ref, n_asift = T_new, int(mask[: len(idx)].sum())
        library = self._library_of(seq, left, right, feats, z0)
        if library is None:  # the next keyframe matches against the one before
            return KeyframeResult(seq, T_tracked, T_ref, n_asift, prev, T_prev, T_prev, n_views)
        return KeyframeResult(seq, T_tracked, T_ref, n_asift, library, T_tracked if T_ref is None else T_ref,
                              T_tracked, n_views)

    def _with_predicted_views(self, left, feats0, prev_X: np.ndarray, T_prev: np.ndarray, T_tracked: np.ndarray):
        """The keyframe's original view, plus the affine views that undo the predicted view change.

        The tracked poses give the tilt and its direction since the previous keyframe (the one whose
        library is matched).  Below ``asift_view_min_tilt`` SIFT bridges the change itself and no
        view is simulated; above it, two views at the predicted tilt: squeezed along the move (a
        surface facing this camera) and across it (one facing the previous camera, up to scale),
        at the preset's view scale."""
        import dataclasses

        from stereopath.device.core.features import ORIGINAL_VIEW, Features, detect, get_preset

        tilt, phi = predicted_view_change(prev_X, T_prev, T_tracked)
        if tilt < self.cfg.asift.view_min_tilt:
            return feats0
        t = min(tilt, MAX_SIMULATED_TILT)
        cfg = dataclasses.replace(get_preset(self.cfg.asift.feature_preset),
                                  views=(ORIGINAL_VIEW, (t, phi), (t, (phi + 90.0) % 180.0)))
        log.debug("keyframe views at tilt %.2f, longitudes %.0f/%.0f deg", t, phi, (phi + 90.0) % 180.0)
        return Features.concat([feats0, detect(left, cfg, views=[1, 2])])

    def _library_of(self, seq: int, left, right, feats, z0: float) -> Library | None:
        """The keyframe's features with stereo 3D points (camera frame)."""
        if len(feats) == 0:
            return None
        if len(feats) > self.cfg.asift.library_max:  # the strongest keypoints of all views
            keep = np.argsort(-feats.response, kind="stable")[: self.cfg.asift.library_max]
            feats = feats.subset(np.sort(keep))
        # no forward-backward check: a wrong 3D point of the library is an outlier of the next
        # keyframe's RANSAC, and the check would double the cost of its largest stereo search
        _, Xc, ok = self._geo.stereo_points(left, right, feats.xy.astype(np.float32), z0, fb_check=False)
        if ok.sum() < self.cfg.geometry.min_pnp_inliers:
            return None
        return Library(seq, feats.subset(ok), Xc[ok])

    def _asift_needed(self, T_world_cam: np.ndarray) -> bool:
        """ASIFT work where the view changed: a rotation since the last ASIFT keyframe (the tilt the
        affine views bridge), or its age; a keyframe in between only tops up the tracked map."""
        cfg = self.cfg
        if self._T_asift is None or self._library is None and not self._jobs:
            return True
        if self._cur_seq - self._asift_frame >= cfg.asift.max_frames:
            return True
        return rotation_angle_deg(self._T_asift[:3, :3].T @ T_world_cam[:3, :3]) >= cfg.asift.min_rotation_deg

    def _submit_keyframe_job(self, left, right, T_world_cam: np.ndarray, z0: float) -> None:
        """Queue this keyframe's ASIFT work: one job running and one waiting at most (the newest wins).
        Finished jobs are joined before (:meth:`_join_keyframe_jobs_moving`), so that the queue and
        ``T_world_cam`` are those of the live state."""
        if not self.cfg.asift.enabled:
            return
        if not self._asift_needed(T_world_cam):
            self.counters["kf_jobs_deferred"] += 1
            return
        prev = self._jobs[-1] if self._jobs else (
            None if self._library is None else (self._library, self._T_library.copy(), self._C.copy()))
        if len(self._jobs) >= 2 and self._jobs[-1].future.cancel():
            # the waiting job never started: this newer keyframe takes its place and its source
            dropped = self._jobs.pop()
            prev = dropped.prev
            self.counters["kf_jobs_skipped"] += 1
        elif len(self._jobs) >= 2:
            self.counters["kf_jobs_skipped"] += 1
            return
        m = self._map
        C_sub = self._C.copy()
        args = (self._cur_seq, left, right, T_world_cam.copy(), z0, m.X.copy(), m.uv.astype(np.float64), prev, C_sub)
        self.counters["kf_jobs"] += 1
        self._T_asift, self._asift_frame = T_world_cam.copy(), self._cur_seq
        if self._executor is not None:
            fut = self._executor.submit(self._keyframe_job, *args)
        else:
            fut = Ready(self._keyframe_job(*args))
        self._jobs.append(Job(fut, C_sub, prev))
