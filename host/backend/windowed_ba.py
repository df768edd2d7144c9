"""Bundle adjustment of long sessions: overlapping windows of keyframes, then the loops by a pose graph.

A batch adjustment (:func:`stereopath.host.backend.gtsam_ba.bundle_adjust`) holds every point's
elimination factor at once: its memory grows with the scan (about 17 MB per keyframe on the
simulated table scan).  Up to :data:`BATCH_KEYFRAMES` keyframes the batch runs as it is (the reference);
above, :func:`adjust_in_windows`:

1. windows of :data:`WINDOW` consecutive keyframes, each overlapping the last by :data:`OVERLAP`, are
   adjusted one after another (the same solver on the window's observations, loops, rotation priors and
   IMU terms); the overlap's poses are held where the last window put them, so the windows join without
   a seam, and only one window's problem is in memory at a time.  The disparity offset is estimated in
   the first window and held after it;
2. the loops between keyframes of different windows then close the path: a pose graph of the adjusted
   keyframes' relative motion and the loops (:func:`~stereopath.host.backend.gtsam_ba.pose_graph`)
   spreads each loop's correction over the path, and every point moves with its first keyframe.

``on_window(n)`` after each window: a progress bar with a remaining-time estimate.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence

import numpy as np

from stereopath.device.core.geometry import invert_pose
from stereopath.device.core.rig import Rig
from stereopath.device.errors import EstimationError
from stereopath.host.backend.ba_common import BAConfig, BAProblem, BAResult, RotationPrior, as_observations

log = logging.getLogger(__name__)

BATCH_KEYFRAMES = 80  # up to this many keyframes: one batch adjustment
WINDOW = 24  # keyframes per window above it ...
OVERLAP = 8  # ... of which this many are the last window's, held


def window_starts(n_keyframes: int) -> list[int]:
    """The first keyframe of each window (the last window ends at the last keyframe)."""
    if n_keyframes <= WINDOW:
        return [0]
    step = WINDOW - OVERLAP
    starts = list(range(0, n_keyframes - WINDOW, step))
    starts.append(n_keyframes - WINDOW)
    return starts


def _imu_window(imu, s: int, e: int):
    """The IMU terms between keyframes ``s`` and ``e`` (exclusive), renumbered from 0; None without any."""
    if imu is None:
        return None
    pims = [(i - s, j - s, p) for i, j, p in imu.pims if s <= i and j < e]
    if not pims:
        return None
    return dataclasses.replace(imu, pims=pims, velocities=np.asarray(imu.velocities)[s:e])


def _loops_window(loops: list, s: int, e: int) -> list:
    return [dataclasses.replace(lp, i=lp.i - s, j=lp.j - s) for lp in loops if s <= lp.i and lp.j < e]


def _priors_window(priors: Sequence[RotationPrior], s: int, e: int) -> list[RotationPrior]:
    return [dataclasses.replace(p, i=p.i - s, j=p.j - s) for p in priors if s <= p.i and p.j < e]


def adjust_in_windows(rig: Rig, problem: BAProblem, config: BAConfig, priors: Sequence[RotationPrior] = (),
                      on_window: Callable[[int], object] | None = None) -> BAResult:
    """The windowed adjustment of the module doc (any number of keyframes; EstimationError when a window
    has too little to adjust)."""
    from stereopath.host.backend.gtsam_ba import bundle_adjust

    T = np.asarray(problem.T_world_cam, float).reshape(-1, 4, 4).copy()
    obs = as_observations(problem.observations)
    if np.any(np.diff(obs[:, 0]) < 0):  # the tracks stage writes them in keyframe order: no copy then
        obs = obs[np.argsort(obs[:, 0], kind="stable")]
    k_of = obs[:, 0]
    points = dict(problem.points)
    offset, estimate_offset = float(problem.disparity_offset_px), config.disparity_offset
    biases = np.full((len(T), 6), np.nan) if problem.imu is not None else None
    first: BAResult | None = None
    rms0, rms1, n_obs, iters, inliers = [], [], 0, 0, []
    history: list[float] = []
    adjusted: set[int] = set()
    for w, s in enumerate(window_starts(len(T))):
        e = min(len(T), s + WINDOW)
        lo, hi = np.searchsorted(k_of, [s, e])
        o = obs[lo:hi].copy()
        o[:, 0] -= s
        cfg = dataclasses.replace(config, disparity_offset=estimate_offset)
        # after the first window the held overlap stays where it is (the first pose's tilt was settled there)
        pb = BAProblem(T[s:e], points, o, _loops_window(list(problem.loops), s, e), _imu_window(problem.imu, s, e),
                       n_fixed=problem.n_fixed if w == 0 else OVERLAP, disparity_offset_px=offset,
                       held_may_tilt=problem.held_may_tilt and w == 0)
        try:
            res = bundle_adjust(rig, pb, cfg, _priors_window(priors, s, e))
        except EstimationError as exc:  # a window with too little structure keeps its poses
            log.warning("bundle adjustment window %d (keyframes %d-%d) left as it was: %s", w, s, e - 1, exc)
            if on_window is not None:
                on_window(1)
            continue
        T[s:e] = res.T_world_cam
        points.update(res.points)
        offset, estimate_offset = res.disparity_offset_px, False
        if biases is not None and res.imu_biases is not None:
            ok = np.isfinite(res.imu_biases[:, 0])
            biases[s:e][ok] = res.imu_biases[ok]
        first = first or res
        rms0.append((res.rms_before_px, res.n_obs))
        rms1.append((res.rms_after_px, res.n_obs))
        inliers.append((res.inlier_fraction, res.n_obs))
        n_obs, iters, history = n_obs + res.n_obs, iters + res.iterations, history + res.history
        adjusted.update(res.points)
        log.info("bundle adjustment window %d: keyframes %d-%d, %d observations", w, s, e - 1, res.n_obs)
        if on_window is not None:
            on_window(1)
    points = {i: points[i] for i in sorted(adjusted)}
    T, points = _close_loops(T, points, obs, list(problem.loops))

    def mean(pairs: list[tuple[float, int]]) -> float:
        v, n = np.array([p[0] for p in pairs], float), np.array([p[1] for p in pairs], float)
        return float(np.sqrt(np.sum(v ** 2 * n) / np.sum(n))) if n.sum() else float("nan")

    if first is None:
        raise EstimationError("bundle adjustment: no window had enough structure to adjust")
    out = BAResult(T, points, mean(rms0), mean(rms1), n_obs, len(points), iters, history[0], history[-1],
                   float(np.sum([f * n for f, n in inliers]) / max(n_obs, 1)), history, offset)
    out.imu_biases = biases
    out.gravity_world = first.gravity_world
    out.pixel_sigma_px = first.pixel_sigma_px
    return out


def _close_loops(T: np.ndarray, points: dict[int, np.ndarray], obs: np.ndarray, loops: list
                 ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """The adjusted keyframes with the loops between windows closed by a pose graph; each point moved with
    the correction of the first keyframe that observes it."""
    from stereopath.host.backend.gtsam_ba import pose_graph

    across = [lp for lp in loops if lp.j - lp.i >= WINDOW - OVERLAP]
    if not across:
        return T, points
    T_new = pose_graph(T, loops)
    C = np.einsum("nij,njk->nik", T_new, np.array([invert_pose(t) for t in T]))
    ids, first = np.unique(obs[:, 1].astype(np.int64), return_index=True)
    kf = obs[first, 0].astype(np.int64)
    moved = {}
    for i, k in zip(ids.tolist(), kf.tolist()):
        x = points.get(i)
        if x is not None:
            moved[i] = C[k, :3, :3] @ x + C[k, :3, 3]
    log.info("bundle adjustment windows joined: %d loops between windows closed by the pose graph", len(across))
    return T_new, {**points, **moved}
