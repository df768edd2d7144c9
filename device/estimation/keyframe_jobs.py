"""The keyframe worker of the ``stereo`` estimator: modified-ASIFT work off the frame loop.

One worker thread, one job running and one waiting (a newer keyframe replaces the waiting one): the
keyframe's affine views are detected, its SIFT matched against the previous keyframe's library around
the positions the tracked pose predicts, the keyframe pose solved from those matches and the tracked
map, and the keyframe's own library built.  The local window's solve
(:mod:`~stereopath.device.estimation.local_window`) runs on the same thread, in submission order.
The frame loop polls the worker once per frame and never waits: each finished job gives a
correction of the live state (pose and map, one rigid motion) mapped through the corrections
applied since the job was submitted, which the estimator applies to its
:class:`~stereopath.device.estimation.live_state.LiveState`.  The worker never sees that state: a job
carries copies of what it needs.
See docs/architecture.md, "The on-board estimator".
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from enum import Enum
from typing import Callable, Generic, TypeVar

import cv2
import numpy as np

from stereopath.device.core.features import Features
from stereopath.device.core.geometry import invert_pose, project_to_se3 as rigid, rotation_angle_deg
from stereopath.device.core.rig import Rig
from stereopath.device.core.stereo_config import KeyframePolicy, StereoConfig
from stereopath.device.errors import EstimationError
from stereopath.device.estimation.live_state import Library, compose
from stereopath.device.estimation.local_window import WindowJob, WindowResult
from stereopath.device.estimation.stereo_measure import PoseGuess, StereoMeasure

log = logging.getLogger(__name__)

ResultT = TypeVar("ResultT")

MAX_SIMULATED_TILT = 4.0  # larger predicted view changes are simulated at this tilt (latitude ~76 deg)


# a joined keyframe library: (library, its keyframe's pose, the cumulative correction of that pose's world)
LibrarySource = tuple[Library, np.ndarray, np.ndarray]


@dataclass
class KeyframeJob:
    """One keyframe's ASIFT work as the frame loop hands it over (copies: the loop goes on)."""

    seq: int
    left: np.ndarray
    right: np.ndarray
    T_tracked: np.ndarray  # the keyframe pose the frame loop used
    z0: float  # a depth for the right-image search
    X_map: np.ndarray  # the tracked map (world) ...
    uv_map: np.ndarray  # ... and its pixels in this keyframe
    C_sub: np.ndarray  # the cumulative live-state correction at submission
    library: LibrarySource | None  # the newest library joined (matched when no job is in flight)


@dataclass
class Job:
    """A keyframe job in flight: its future and the world it was submitted in."""

    future: Future | Ready
    C_sub: np.ndarray  # the cumulative live-state correction when it was submitted
    prev: Job | LibrarySource | None  # what it matches against: a joined library, or the previous job
    order: int = 0  # submission order among the worker's jobs of both kinds


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


@dataclass
class KeyframeCorrection:
    """A finished job as the live state takes it: the correction to apply (None: not solved or
    rejected), counts, and the keyframe library to match next with its pose (live world)."""

    seq: int
    G: np.ndarray | None
    n_asift: int
    n_views: int
    library: Library | None
    T_library: np.ndarray | None
    window: WindowResult | None = None  # a local window's solve (G: its newest keyframe's correction)
    C_since: np.ndarray | None = None  # ... and the corrections applied since it was submitted


class Submitted(Enum):
    """What became of a submitted job."""

    QUEUED = "queued"
    REPLACED = "replaced"  # queued in place of the waiting job, which never started
    DROPPED = "dropped"  # one running and one waiting that had started: not queued


class Ready(Generic[ResultT]):
    """A finished result with the Future interface (the synchronous mode, and settled work)."""

    def __init__(self, value: ResultT, error: BaseException | None = None) -> None:
        self._value = value
        self._error = error

    @classmethod
    def of(cls, fut: Future | Ready) -> Ready:
        """The finished ``fut`` (its result or its exception) held as plain data (waits for it)."""
        if isinstance(fut, Ready):
            return fut
        try:
            return cls(fut.result())
        except Exception as exc:  # kept: poll() reports it as it would have from the Future
            return cls(None, exc)

    def done(self) -> bool:
        return True

    def cancel(self) -> bool:
        return False

    def result(self) -> ResultT:
        if self._error is not None:
            raise self._error
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


def resolve_previous(source: Job | LibrarySource | None,
                     C_sub: np.ndarray) -> tuple[Library | None, np.ndarray | None]:
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


def lower_thread_priority(nice: int) -> int | None:
    """Raise the calling thread's niceness by ``nice`` (at most 19); returns the new niceness, None where
    threads have no priority of their own (Linux gives each thread one, set through its native id).

    The keyframe worker calls it first: on a core the frame loop shares with it, the scheduler then
    runs the frame loop whenever it is ready, and the worker in the time left."""
    if nice <= 0 or not sys.platform.startswith("linux") or not hasattr(threading, "get_native_id"):
        return None  # elsewhere PRIO_PROCESS with a thread id would name a process
    tid = threading.get_native_id()
    try:
        target = min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice)
        os.setpriority(os.PRIO_PROCESS, tid, target)
        got = os.getpriority(os.PRIO_PROCESS, tid)
    except OSError as e:  # a sandbox without the call: the worker runs at the loop's priority
        log.info("keyframe worker priority unchanged (%s): it runs at the frame loop's", e)
        return None
    log.info("keyframe worker at niceness %d (one core shared with the frame loop)", got)
    return got


def worker_niceness(policy: KeyframePolicy) -> int:
    """The keyframe worker's niceness above the frame loop's: ``policy.worker_nice`` when the process
    may run on at most ``policy.worker_nice_max_cores`` cores (the worker then shares the loop's core),
    else 0 (a core of its own: a lower priority would only lose it time to other processes)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return policy.worker_nice if cores <= policy.worker_nice_max_cores else 0


class KeyframeWorker:
    """The keyframe queue: at most one job running and one waiting, on a worker thread (below the frame
    loop's priority when it shares the loop's core, :func:`worker_niceness`; in line when
    ``keyframes.background`` is off).  :meth:`submit` takes a job, :meth:`poll` the finished ones."""

    def __init__(self, rig: Rig, cfg: StereoConfig, geo: StereoMeasure) -> None:
        self.rig = rig
        self.cfg = cfg
        self._geo = geo
        self._jobs: list[Job] = []  # in flight, oldest first: at most one running, one waiting
        self._windows: list[Job] = []  # local window solves in flight, the same way
        self._order = 0
        self._feature_cfg = None
        self._executor = self._start_executor()

    def _start_executor(self) -> ThreadPoolExecutor | None:
        cfg = self.cfg
        if not ((cfg.asift.enabled or cfg.window.enabled) and cfg.keyframes.background):
            return None
        return ThreadPoolExecutor(max_workers=1, thread_name_prefix="keyframe-features",
                                  initializer=lower_thread_priority, initargs=(worker_niceness(cfg.keyframes),))

    def settle(self) -> None:
        """Wait for the work in flight and hold every result as plain data (:class:`Ready`), which
        :meth:`poll` takes as before: the worker can then be pickled (a stage's stored progress)."""
        if self._executor is not None:
            self._executor.submit(int).result()  # one worker thread, in order: all the work before it is done
        for queue in (self._jobs, self._windows):
            for job in queue:  # every job has run: what it matched against is no longer needed
                job.future, job.prev = Ready.of(job.future), None

    def __getstate__(self) -> dict[str, object]:
        pending = [j for q in (self._jobs, self._windows) for j in q if not isinstance(j.future, Ready)]
        if pending:
            raise EstimationError(f"{len(pending)} keyframe job(s) in flight: settle() before pickling the worker")
        return {k: v for k, v in self.__dict__.items() if k != "_executor"}

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__dict__.update(state)
        self._executor = self._start_executor()

    @property
    def in_flight(self) -> int:
        """Keyframe (ASIFT) jobs submitted and not yet polled."""
        return len(self._jobs)

    def submit_window(self, job: WindowJob) -> Submitted:
        """Queue a local window's solve (one running and one waiting at most: the newest wins)."""
        from stereopath.device.estimation.disparity_offset import RectifiedCamera
        from stereopath.device.estimation.local_window import solve_window

        replaced = len(self._windows) >= 2 and self._windows[-1].future.cancel()
        if replaced:  # the waiting solve never started: this newer window takes its place
            self._windows.pop()
        elif len(self._windows) >= 2:
            return Submitted.DROPPED
        rect = self._geo.rect
        args = (job, RectifiedCamera.of(rect), rect.R0, self.cfg.window)
        fut: Future | Ready = (self._executor.submit(solve_window, *args) if self._executor
                               else Ready(solve_window(*args)))
        self._order += 1
        self._windows.append(Job(fut, job.C_sub, None, self._order))
        return Submitted.REPLACED if replaced else Submitted.QUEUED

    def close(self) -> None:
        """Stop the worker thread (idempotent)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None

    def run_aside(self, fn: Callable[[], ResultT]) -> Future | Ready:
        """Other keyframe-rate work (``fn``, pure compute on copies) on the worker thread after the jobs
        queued, or in line without a worker thread; the caller polls its ``done()``."""
        if self._executor is None:
            return Ready(fn())
        return self._executor.submit(fn)

    def features(self, img: np.ndarray, views: list[int] | None = None) -> Features:
        from stereopath.device.core.features import detect, get_preset

        if self._feature_cfg is None:
            self._feature_cfg = get_preset(self.cfg.asift.feature_preset)
        return detect(img, self._feature_cfg, views=views)

    def submit(self, job: KeyframeJob) -> Submitted:
        """Queue a keyframe's ASIFT work: one job running and one waiting at most (the newest wins)."""
        prev = self._jobs[-1] if self._jobs else job.library
        outcome = Submitted.QUEUED
        if len(self._jobs) >= 2 and self._jobs[-1].future.cancel():
            # the waiting job never started: this newer keyframe takes its place and its source
            prev = self._jobs.pop().prev
            outcome = Submitted.REPLACED
        elif len(self._jobs) >= 2:
            return Submitted.DROPPED
        if self._executor is not None:
            fut: Future | Ready = self._executor.submit(self.run, job, prev)
        else:
            fut = Ready(self.run(job, prev))
        self._order += 1
        self._jobs.append(Job(fut, job.C_sub, prev, self._order))
        return outcome

    def poll(self, C: np.ndarray) -> list[KeyframeCorrection]:
        """The finished jobs, oldest first (never waits), as corrections of a live state whose cumulative
        correction is ``C``; each correction is expressed for the live state the ones before it moved."""
        out = []
        while True:
            queues = [q for q in (self._jobs, self._windows) if q]
            if not queues:
                break
            first = min(queues, key=lambda q: q[0].order)
            if not first[0].future.done():
                break
            job = first.pop(0)
            job.prev = None  # it has run (the next job reads only this one's result): the chain ends here
            try:
                res = job.future.result()
            except Exception:  # a failed job costs one keyframe's work, never the session
                log.exception("keyframe job failed")
                continue
            if res is None:
                continue
            if isinstance(res, WindowResult):
                corr = self._window_correction(res, C @ invert_pose(job.C_sub))
                out.append(corr)
                if corr.G is not None:
                    C = compose(corr.G, C)
                continue
            # the job worked in the world of its submission; corrections applied since map it to the live one
            C_since = C @ invert_pose(job.C_sub)
            G = None
            if res.T_refined is not None:
                G = rigid(C_since @ res.T_refined @ invert_pose(res.T_tracked) @ invert_pose(C_since))
                ang = rotation_angle_deg(G[:3, :3])
                log.debug("keyframe %d: correction %.3f deg, %.4f m", res.seq, ang, float(np.linalg.norm(G[:3, 3])))
                if ang > self.cfg.asift.max_correction_deg:
                    log.info("keyframe %d: ASIFT correction of %.2f deg rejected", res.seq, ang)
                    G = None
            library, T_library = None, None
            if res.library is not None and res.T_library is not None:
                # the job's belief of its keyframe (refined) in the live world, before its own correction
                library, T_library = res.library, C_since @ res.T_library
            out.append(KeyframeCorrection(res.seq, G, res.n_asift, res.n_views, library, T_library))
            if G is not None:
                C = compose(G, C)
        return out

    def _window_correction(self, res: WindowResult, C_since: np.ndarray) -> KeyframeCorrection:
        """A solved window as the live state takes it: its newest keyframe's refinement."""
        if not (np.isfinite(res.T_after[-1]).all() and np.isfinite(res.T_before[-1]).all()):
            log.info("window at keyframe %d: non-finite result refused", res.seq)
            return KeyframeCorrection(res.seq, None, 0, 0, None, None, res, C_since)
        G = rigid(C_since @ res.T_after[-1] @ invert_pose(res.T_before[-1]) @ invert_pose(C_since))
        ang = rotation_angle_deg(G[:3, :3])
        log.debug("window at keyframe %d: %d points, %.2f px, correction %.3f deg, %.4f m, %.1f ms", res.seq,
                  res.n_points, res.rms_px, ang, float(np.linalg.norm(G[:3, 3])), res.cpu_ms)
        # the newest keyframe's own shift, bounded as its rotation is: a shift s at the points' depth z moves
        # them as a rotation of s / z would
        shift = float(np.linalg.norm(res.T_after[-1][:3, 3] - res.T_before[-1][:3, 3]))
        max_shift = np.radians(self.cfg.window.max_correction_deg) * res.depth_m if np.isfinite(res.depth_m) else np.inf
        if ang > self.cfg.window.max_correction_deg or not np.isfinite(G).all() or not shift <= max_shift:
            log.info("window at keyframe %d: correction of %.2f deg, %.4f m refused", res.seq, ang, shift)
            return KeyframeCorrection(res.seq, None, 0, 0, None, None, res, C_since)
        return KeyframeCorrection(res.seq, G, 0, 0, None, None, res, C_since)

    def _asift_matches(self, prev: Library, prev_X: np.ndarray, feats0: Features, T_tracked: np.ndarray) -> np.ndarray:
        """(current, previous) index pairs of the keyframe's original view against the previous library."""
        from stereopath.device.core.matching import MatchConfig, match, match_guided

        radius = self.cfg.asift.guided_radius_px
        if radius <= 0:
            mt = match(feats0, prev.feats, MatchConfig())
            return np.asarray(mt.idx).reshape(-1, 2)
        T_cw = invert_pose(T_tracked)
        Xc = prev_X @ T_cw[:3, :3].T + T_cw[:3, 3]
        pred = np.full((len(Xc), 2), np.nan)
        front = Xc[:, 2] > self.cfg.geometry.min_depth_m
        if np.any(front):
            pred[front] = cv2.projectPoints(Xc[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                            self.rig.cam0.K, self.rig.cam0.dist)[0].reshape(-1, 2)
        mt = match_guided(prev.feats, feats0, pred, radius, MatchConfig())
        return np.asarray(mt.idx).reshape(-1, 2)[:, ::-1]

    def run(self, job: KeyframeJob, prev_source: Job | LibrarySource | None) -> KeyframeResult:
        """Modified-ASIFT work of one keyframe (on the worker thread): the joint pose, then the library.

        The keyframe's original-view SIFT is matched against the previous library (all views of
        the previous keyframe, each with a 3D point) around the positions the tracked pose
        predicts; those matches and the tracked map points give the keyframe pose."""
        prev, T_prev = resolve_previous(prev_source, job.C_sub)
        left, right, T_tracked = job.left, job.right, job.T_tracked
        predicted = self.cfg.asift.views == "predicted"
        feats = self.features(left, views=[0] if predicted else None)
        T_ref, n_asift, n_views = None, 0, 0
        if prev is not None and len(feats):
            prev_X = prev.X_cam @ T_prev[:3, :3].T + T_prev[:3, 3]
            cur = feats.original_view()
            if predicted:
                cur = self._with_predicted_views(left, cur, prev_X, T_prev, T_tracked)
                n_views = int(cur.view.max())
            idx = self._asift_matches(prev, prev_X, cur, T_tracked)
            if len(idx) >= self.cfg.geometry.min_pnp_inliers:
                X = np.vstack([prev_X[idx[:, 1]], job.X_map])
                uv = np.vstack([cur.xy[idx[:, 0]].astype(np.float64), job.uv_map])
                T_new, _, mask = self._geo.solve_pose(left, right, X, uv, PoseGuess(T_tracked), seed=job.seq)
                # the tracked map must still fit the joint pose: ASIFT matches that pull the pose away
                # from it (repeated texture, a wrong 3D point) would turn its points into outliers
                if T_new is not None and mask[len(idx):].sum() >= self.cfg.asift.map_agreement * len(job.X_map):
                    T_ref, n_asift = T_new, int(mask[: len(idx)].sum())
        library = self._library_of(job, feats)
        if library is None:  # the next keyframe matches against the one before
            return KeyframeResult(job.seq, T_tracked, T_ref, n_asift, prev, T_prev, T_prev, n_views)
        return KeyframeResult(job.seq, T_tracked, T_ref, n_asift, library, T_tracked if T_ref is None else T_ref,
                              T_tracked, n_views)

    def _with_predicted_views(self, left: np.ndarray, feats0: Features, prev_X: np.ndarray, T_prev: np.ndarray,
                              T_tracked: np.ndarray) -> Features:
        """The keyframe's original view, plus the affine views that undo the predicted view change.

        The tracked poses give the tilt and its direction since the previous keyframe (the one whose
        library is matched).  Below ``asift.view_min_tilt`` SIFT bridges the change itself and no
        view is simulated; above it, two views at the predicted tilt: squeezed along the move (a
        surface facing this camera) and across it (one facing the previous camera, up to scale),
        at the preset's view scale."""
        import dataclasses

        from stereopath.device.core.features import ORIGINAL_VIEW, detect, get_preset

        tilt, phi = predicted_view_change(prev_X, T_prev, T_tracked)
        if tilt < self.cfg.asift.view_min_tilt:
            return feats0
        t = min(tilt, MAX_SIMULATED_TILT)
        cfg = dataclasses.replace(get_preset(self.cfg.asift.feature_preset),
                                  views=(ORIGINAL_VIEW, (t, phi), (t, (phi + 90.0) % 180.0)))
        log.debug("keyframe views at tilt %.2f, longitudes %.0f/%.0f deg", t, phi, (phi + 90.0) % 180.0)
        return Features.concat([feats0, detect(left, cfg, views=[1, 2])])

    def _library_of(self, job: KeyframeJob, feats: Features) -> Library | None:
        """The keyframe's features with stereo 3D points (camera frame)."""
        if len(feats) == 0:
            return None
        keep_max = self.cfg.asift.library_max
        if len(feats) > keep_max:  # the strongest keypoints of all views
            keep = np.argsort(-feats.response, kind="stable")[:keep_max]
            feats = feats.subset(np.sort(keep))
        # no forward-backward check: a wrong 3D point of the library is an outlier of the next
        # keyframe's RANSAC, and the check would double the cost of its largest stereo search
        _, Xc, ok = self._geo.stereo_points(job.left, job.right, feats.xy.astype(np.float32), job.z0, fb_check=False)
        if ok.sum() < self.cfg.geometry.min_pnp_inliers:
            return None
        return Library(job.seq, feats.subset(ok), Xc[ok])
