"""Bundle adjustment of long sessions: overlapping windows of keyframes, tied back by their loops.

A batch adjustment (:func:`stereopath.host.backend.gtsam_ba.bundle_adjust`) holds every point's
elimination factor at once: its memory grows with the scan (about 17 MB per keyframe on the
simulated table scan).  Up to :data:`BATCH_KEYFRAMES` keyframes the batch runs as it is (the reference);
above, :func:`adjust_in_windows`:

windows of :data:`WINDOW` consecutive keyframes, each overlapping the last by :data:`OVERLAP`, are
adjusted one after another (the same solver on the window's observations, loops, rotation priors and
IMU terms); the overlap's poses are held where the last window put them, so the windows join without a
seam, and only one window's problem is in memory at a time.  A loop from a window's keyframe back to an
earlier one brings that keyframe in, held where its window put it (an anchor): the loop pulls the new
window onto the path already adjusted instead of letting the windows drift apart.  The disparity offset
is estimated in the first window and held after it.

``on_window(n)`` after each window: a progress bar with a remaining-time estimate.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from stereopath.device.core.rig import Rig
from stereopath.device.errors import EstimationError
from stereopath.host.backend.ba_common import BAConfig, BAProblem, BAResult, RotationPrior, as_observations

if TYPE_CHECKING:
    from stereopath.host.backend.imu_factors import ImuTerms
    from stereopath.host.backend.loops import Loop

log = logging.getLogger(__name__)

BATCH_KEYFRAMES = 80  # up to this many keyframes: one batch adjustment
WINDOW = 48  # keyframes per window above it ...
OVERLAP = 24  # ... of which this many are the last window's, held


def window_starts(n_keyframes: int) -> list[int]:
    """The first keyframe of each window (the last window ends at the last keyframe)."""
    if n_keyframes <= WINDOW:
        return [0]
    step = WINDOW - OVERLAP
    starts = list(range(0, n_keyframes - WINDOW, step))
    starts.append(n_keyframes - WINDOW)
    return starts


@dataclass(frozen=True)
class _Window:
    """Keyframes ``s`` to ``e`` (exclusive) and, before them, the earlier ``anchors`` a loop ties them to:
    where each keyframe is in the window's problem."""

    s: int
    e: int
    anchors: tuple[int, ...]

    def at(self, k: int) -> int:
        return self.anchors.index(k) if k < self.s else len(self.anchors) + k - self.s

    def holds(self, k: int) -> bool:
        return self.s <= k < self.e or k in self.anchors


def _window(loops: list, s: int, e: int) -> _Window:
    """The window of keyframes ``s``-``e`` with the earlier keyframes its loops reach as anchors."""
    return _Window(s, e, tuple(sorted({lp.i for lp in loops if s <= lp.j < e and lp.i < s})))


def _imu_window(imu: ImuTerms | None, win: _Window) -> ImuTerms | None:
    """The IMU terms between the window's keyframes, numbered as in its problem; None without any."""
    if imu is None:
        return None
    pims = [(win.at(i), win.at(j), p) for i, j, p in imu.pims if win.s <= i and j < win.e]
    if not pims:
        return None
    vel = np.asarray(imu.velocities)
    vel = np.concatenate([vel[list(win.anchors)].reshape(-1, 3), vel[win.s:win.e]])
    return dataclasses.replace(imu, pims=pims, velocities=vel)


def _loops_window(loops: list[Loop], win: _Window) -> list[Loop]:
    return [dataclasses.replace(lp, i=win.at(lp.i), j=win.at(lp.j)) for lp in loops
            if win.s <= lp.j < win.e and win.holds(lp.i)]


def _priors_window(priors: Sequence[RotationPrior], win: _Window) -> list[RotationPrior]:
    return [dataclasses.replace(p, i=win.at(p.i), j=win.at(p.j)) for p in priors if win.s <= p.i and p.j < win.e]


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
    loops = list(problem.loops)
    for w, s in enumerate(window_starts(len(T))):
        e = min(len(T), s + WINDOW)
        win = _window(loops, s, e)
        na = len(win.anchors)
        lo, hi = np.searchsorted(k_of, [s, e])
        o = obs[lo:hi].copy()
        o[:, 0] += na - s
        cfg = dataclasses.replace(config, disparity_offset=estimate_offset)
        # held: the anchors, and after the first window the overlap, where the last windows put them (the
        # first pose's tilt was settled in the first window)
        T_w = np.concatenate([T[list(win.anchors)].reshape(-1, 4, 4), T[s:e]])
        pb = BAProblem(T_w, points, o, _loops_window(loops, win), _imu_window(problem.imu, win),
                       n_fixed=na + (problem.n_fixed if w == 0 else OVERLAP), disparity_offset_px=offset,
                       held_may_tilt=problem.held_may_tilt and w == 0 and na == 0)
        try:
            res = bundle_adjust(rig, pb, cfg, _priors_window(priors, win))
        except EstimationError as exc:  # a window with too little structure keeps its poses
            log.warning("bundle adjustment window %d (keyframes %d-%d) left as it was: %s", w, s, e - 1, exc)
            if on_window is not None:
                on_window(1)
            continue
        T[s:e] = res.T_world_cam[na:]
        points.update(res.points)
        offset, estimate_offset = res.disparity_offset_px, False
        if biases is not None and res.imu_biases is not None:
            ok = np.isfinite(res.imu_biases[na:, 0])
            biases[s:e][ok] = res.imu_biases[na:][ok]
        first = first or res
        rms0.append((res.rms_before_px, res.n_obs))
        rms1.append((res.rms_after_px, res.n_obs))
        inliers.append((res.inlier_fraction, res.n_obs))
        n_obs, iters, history = n_obs + res.n_obs, iters + res.iterations, history + res.history
        adjusted.update(res.points)
        log.info("bundle adjustment window %d: keyframes %d-%d, %d observations, %d loop anchors", w, s, e - 1,
                 res.n_obs, na)
        if on_window is not None:
            on_window(1)
    points = {i: points[i] for i in sorted(adjusted)}

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
