"""Bundle adjustment of long sessions: overlapping windows of keyframes, tied back by their loops.

A batch adjustment (:func:`stereopath.host.backend.gtsam_ba.bundle_adjust`) holds every point's
elimination factor at once: its memory grows with the scan (about 17 MB per keyframe on the
simulated table scan).  Up to :data:`BATCH_KEYFRAMES` keyframes the batch runs as it is (the
reference); above, :func:`adjust_in_windows`:

the verified loops are first closed on the whole path by a pose graph
(:func:`stereopath.host.backend.gtsam_ba.pose_graph`: the keyframes' relative motion and the loops,
poses only, a few MB at any length), so that the windows start from a path without the drift the
loops measured; then windows of :data:`WINDOW` consecutive keyframes, each overlapping the last by
:data:`OVERLAP`, are adjusted one after another (the same solver on the window's observations,
loops, rotation priors and IMU terms).  The first :data:`HELD` keyframes of the overlap are held
where the last window put them, so the windows join without a seam; the rest of the overlap is
adjusted again: the last window had them at its end, seen from one side only, and this window sees
them from both, at no extra cost.  Only one window's problem is in memory at a time, and its memory
is handed back to the system before the next.  A loop from a window's keyframe back to an earlier
one brings that keyframe in, held where its window put it (an anchor): the loop pulls the new window
onto the path already adjusted instead of letting the windows drift apart.  The disparity offset is
estimated in the first window and held after it.  Held as anchors, the first windows' keyframes never
learn what the later loops measured of them; so after the last window the loops are closed once more,
on the adjusted path (:func:`_close_loops_last`: a pose graph whose consecutive keyframes are weighted
by the points they share, as a loop is by its inliers), and the points move with their keyframes.

``on_window(n)`` after each window: a progress bar with a remaining-time estimate.  Each window's outcome
can be stored (:class:`WindowCheckpoint`): an adjustment interrupted on a long session resumes after
the last window stored, with the result a run without interruption gives.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import zipfile
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stereopath.device.core.rig import Rig
from stereopath.device.errors import EstimationError
from stereopath.host.backend.ba_common import (
    BAConfig,
    BAProblem,
    BAResult,
    RotationPrior,
    as_observations,
)
from stereopath.host.backend.observations import observation_keyframes

if TYPE_CHECKING:
    from stereopath.host.backend.imu_factors import ImuTerms
    from stereopath.host.backend.loops import Loop

log = logging.getLogger(__name__)

BATCH_KEYFRAMES = 80  # up to this many keyframes: one batch adjustment
WINDOW = 48  # keyframes per window above it ...
OVERLAP = 16  # ... of which this many are the last window's ...
HELD = 8  # ... and the first this many of them held (the others adjusted again, now with neighbours on both sides)
MIN_SHARED_POINTS = 6  # consecutive keyframes sharing fewer points keep the pose graph's drift model


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


@dataclass
class _Progress:
    """What the windows adjusted so far have settled: the poses, the points they adjusted, the disparity
    offset (and whether it is still to be estimated), the IMU biases, the first window's gravity and
    pixel noise, and the per-window figures the result averages.  ``done`` windows are in it."""

    T: np.ndarray
    points: dict[int, np.ndarray]  # every point: as the windows left it, or as given
    adjusted: set[int]
    offset: float
    estimate_offset: bool
    biases: np.ndarray | None
    done: int = 0
    gravity_world: np.ndarray | None = None
    pixel_sigma_px: float | None = None
    figures: list[tuple[float, float, float, int]] = field(default_factory=list)  # rms before, after, inliers, n
    iterations: int = 0
    history: list[float] = field(default_factory=list)

    def arrays(self) -> dict[str, np.ndarray]:
        ids = np.array(sorted(self.adjusted), np.int64)
        out = {"T": self.T, "point_ids": ids,
               "point_xyz": np.array([self.points[int(i)] for i in ids], float).reshape(-1, 3),
               "offset": np.array(self.offset), "estimate_offset": np.array(self.estimate_offset),
               "done": np.array(self.done), "figures": np.array(self.figures, float).reshape(-1, 4),
               "iterations": np.array(self.iterations), "history": np.array(self.history, float)}
        if self.biases is not None:
            out["biases"] = self.biases
        if self.gravity_world is not None:
            out["gravity_world"] = np.asarray(self.gravity_world, float)
        if self.pixel_sigma_px is not None:
            out["pixel_sigma_px"] = np.array(self.pixel_sigma_px)
        return out

    @classmethod
    def from_arrays(cls, a: dict[str, np.ndarray], points: dict[int, np.ndarray]) -> _Progress:
        """The progress stored by :meth:`arrays` on the problem's ``points``."""
        ids = [int(i) for i in a["point_ids"]]
        points = {**points, **dict(zip(ids, a["point_xyz"]))}
        return cls(a["T"], points, set(ids), float(a["offset"]),
                   bool(a["estimate_offset"]), a.get("biases"), int(a["done"]), a.get("gravity_world"),
                   float(a["pixel_sigma_px"]) if "pixel_sigma_px" in a else None,
                   [(float(r[0]), float(r[1]), float(r[2]), int(r[3])) for r in a["figures"]],
                   int(a["iterations"]), [float(x) for x in a["history"]])


class WindowCheckpoint:
    """The windows' progress in a folder (``window_progress.npz``, replaced after each window): a
    stage interrupted on a long session resumes after the last window stored there.  The folder must
    belong to this one problem (the reprocessing's stage key names it)."""

    FILE = "window_progress.npz"

    def __init__(self, folder: Path) -> None:
        self.path = Path(folder) / self.FILE

    def load(self, n_keyframes: int, points: dict[int, np.ndarray]) -> _Progress | None:
        """The stored progress on the problem's ``points`` (None when there is none, it is unreadable or
        not of ``n_keyframes``)."""
        if not self.path.is_file():
            return None
        try:
            with np.load(self.path, allow_pickle=False) as z:
                prog = _Progress.from_arrays({k: z[k] for k in z.files}, points)
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            log.warning("%s unreadable (%s): the windows start from the first", self.path, exc)
            return None
        return prog if len(prog.T) == n_keyframes else None

    def save(self, prog: _Progress) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.stem + ".tmp.npz")
        np.savez(tmp, **prog.arrays())
        os.replace(tmp, self.path)


def _release_freed() -> None:
    """Hand the freed window's memory back to the system (glibc keeps freed heap pages otherwise, and the
    resident set would stay at the largest window's until the stage ends); nothing elsewhere."""
    import ctypes

    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _adjust_window(rig: Rig, problem: BAProblem, config: BAConfig, priors: Sequence[RotationPrior],
                   prog: _Progress, w: int, s: int, kfs: np.ndarray) -> None:
    """Window ``w`` (keyframes from ``s``) adjusted from ``prog`` and its outcome put into ``prog``."""
    from stereopath.host.backend.gtsam_ba import bundle_adjust

    T, loops = prog.T, list(problem.loops)
    e = min(len(T), s + WINDOW)
    win = _window(loops, s, e)
    na = len(win.anchors)
    obs = problem.observations  # in keyframe order (adjust_in_windows), either form: widened here, a window at a time
    lo, hi = np.searchsorted(kfs, [s, e])  # kfs: the rows' keyframes, one contiguous column
    o = as_observations(obs[lo:hi])
    if np.may_share_memory(o, obs):  # a view of float rows given as they are: not to be changed
        o = o.copy()
    o[:, 0] += na - s
    cfg = dataclasses.replace(config, disparity_offset=prog.estimate_offset)
    # held: the anchors, and after the first window the overlap, where the last windows put them (the
    # first pose's tilt was settled in the first window)
    T_w = np.concatenate([T[list(win.anchors)].reshape(-1, 4, 4), T[s:e]])
    pb = BAProblem(T_w, prog.points, o, _loops_window(loops, win), _imu_window(problem.imu, win),
                   n_fixed=na + (problem.n_fixed if w == 0 else HELD), disparity_offset_px=prog.offset,
                   held_may_tilt=problem.held_may_tilt and w == 0 and na == 0)
    try:
        res = bundle_adjust(rig, pb, cfg, _priors_window(priors, win))
    except EstimationError as exc:  # a window with too little structure keeps its poses
        log.warning("bundle adjustment window %d (keyframes %d-%d) left as it was: %s", w, s, e - 1, exc)
        return
    T[s:e] = res.T_world_cam[na:]
    prog.points.update(res.points)
    prog.adjusted.update(res.points)
    prog.offset, prog.estimate_offset = res.disparity_offset_px, False
    if prog.biases is not None and res.imu_biases is not None:
        ok = np.isfinite(res.imu_biases[na:, 0])
        prog.biases[s:e][ok] = res.imu_biases[na:][ok]
    if not prog.figures:  # the first window adjusted
        prog.gravity_world, prog.pixel_sigma_px = res.gravity_world, res.pixel_sigma_px
    prog.figures.append((res.rms_before_px, res.rms_after_px, res.inlier_fraction, res.n_obs))
    prog.iterations += res.iterations
    prog.history += res.history
    log.info("bundle adjustment window %d: keyframes %d-%d, %d observations, %d loop anchors", w, s, e - 1,
             res.n_obs, na)


def adjust_in_windows(rig: Rig, problem: BAProblem, config: BAConfig, priors: Sequence[RotationPrior] = (),
                      on_window: Callable[[int], object] | None = None,
                      checkpoint: WindowCheckpoint | None = None) -> BAResult:
    """The windowed adjustment of the module doc (any number of keyframes; EstimationError when no
    window has enough to adjust).  With a ``checkpoint`` the progress is stored after each window and a
    run finding progress stored there continues after its last window (the same result as a run
    without interruption)."""
    T = np.asarray(problem.T_world_cam, float).reshape(-1, 4, 4).copy()
    obs = problem.observations  # kept in the form given (compact rows stay compact)
    if np.asarray(obs).dtype.names is None:
        obs = as_observations(obs)
    kfs = np.ascontiguousarray(observation_keyframes(obs))
    if np.any(np.diff(kfs) < 0):  # the tracks stage writes them in keyframe order: no copy then
        order = np.argsort(kfs, kind="stable")
        obs, kfs = obs[order], kfs[order]
    problem = dataclasses.replace(problem, observations=obs)
    starts = window_starts(len(T))
    prog = checkpoint.load(len(T), problem.points) if checkpoint is not None else None
    if prog is not None:
        log.info("bundle adjustment: %d of %d windows stored, resuming after them", prog.done, len(starts))
        if on_window is not None and prog.done:
            on_window(prog.done)
    else:
        if problem.loops:  # the loops closed on the whole path first: the windows start from a consistent one
            from stereopath.host.backend.gtsam_ba import pose_graph

            T = pose_graph(T, list(problem.loops))
        prog = _Progress(T, dict(problem.points), set(), float(problem.disparity_offset_px), config.disparity_offset,
                         np.full((len(T), 6), np.nan) if problem.imu is not None else None)
    for w in range(prog.done, len(starts)):
        _adjust_window(rig, problem, config, priors, prog, w, starts[w], kfs)
        prog.done = w + 1
        _release_freed()
        if checkpoint is not None:
            checkpoint.save(prog)
        if on_window is not None:
            on_window(1)
    if problem.loops and len(starts) > 1 and prog.figures:
        _close_loops_last(rig, problem, prog, kfs)
    return _result(prog)


def _points_and_left(observations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each observation row's point id and whether it is in the left camera (either form of rows)."""
    obs = np.asarray(observations)
    if obs.dtype.names is not None:
        return obs["point"].astype(np.int64), obs["cam"] == 0
    return obs[:, 1].astype(np.int64), obs[:, 2] == 0


def chain_sigmas(rig: Rig, observations: np.ndarray, kfs: np.ndarray, T: np.ndarray, points: dict[int, np.ndarray],
                 rms_px: float) -> np.ndarray:
    """(K - 1, 2) rotation and translation deviations of consecutive keyframes' relative poses: the
    loops' model (:func:`~stereopath.host.backend.loops.relative_pose_sigmas`) on the ``points`` both see
    in the left camera, at their median depth in the first of the two, with the pixel error ``rms_px``
    (per image coordinate, as the adjustment reports it: a loop's is the length of the 2D error, so it
    is taken times sqrt(2)); NaN where they share fewer than :data:`MIN_SHARED_POINTS` or the points are
    not in front.  ``observations`` in keyframe order (either form), ``kfs`` their keyframes."""
    from stereopath.host.backend.loops import relative_pose_sigmas

    pid, left = _points_and_left(observations)
    bounds = np.searchsorted(kfs, np.arange(len(T) + 1))
    seen = [np.unique(pid[bounds[k]:bounds[k + 1]][left[bounds[k]:bounds[k + 1]]]) for k in range(len(T))]
    out = np.full((max(len(T) - 1, 0), 2), np.nan)
    f = float(rig.cam0.K[0, 0])
    for k in range(len(T) - 1):
        shared = [int(i) for i in np.intersect1d(seen[k], seen[k + 1], assume_unique=True) if int(i) in points]
        if len(shared) < MIN_SHARED_POINTS:
            continue
        X = np.array([points[i] for i in shared], float)
        z = (X - T[k][:3, 3]) @ T[k][:3, 2]  # depth along the first keyframe's optical axis
        depth = float(np.median(z))
        if depth > 0:
            out[k] = relative_pose_sigmas(f, np.sqrt(2.0) * rms_px, len(shared), depth)
    return out


def _close_loops_last(rig: Rig, problem: BAProblem, prog: _Progress, kfs: np.ndarray) -> None:
    """The loops closed once more, on the adjusted path (``prog`` updated): a window's keyframes are held
    where they are by the loops of later windows, which pull those windows onto them, so what the later
    loops know of the earlier keyframes reaches them only here.  A pose graph of the adjusted keyframes
    (consecutive ones tied by their adjusted relative pose, weighted by the points they share as a loop is
    by its inliers: :func:`chain_sigmas`) and every loop; the adjusted points move with the keyframes
    that see them (:func:`_move_points`)."""
    from stereopath.host.backend.gtsam_ba import pose_graph

    rms = _over_windows(np.array(prog.figures, float), 1)
    sig = chain_sigmas(rig, problem.observations, kfs, prog.T, {i: prog.points[i] for i in prog.adjusted}, rms)
    T_old = prog.T
    T_new = pose_graph(T_old, list(problem.loops), edge_sigmas=sig)
    C = T_new @ np.linalg.inv(T_old)  # each keyframe's correction, world to world
    _move_points(prog, problem.observations, kfs, C)
    moved = np.linalg.norm(T_new[:, :3, 3] - T_old[:, :3, 3], axis=1)
    log.info("loops closed on the adjusted path: %d loops, %d of %d keyframe pairs weighted by shared points, "
             "keyframes moved by %.3f mm median, %.3f mm at most", len(problem.loops), int(np.isfinite(sig[:, 0]).sum()),
             len(sig), 1000 * float(np.median(moved)), 1000 * float(moved.max()))
    prog.T = T_new


def _move_points(prog: _Progress, observations: np.ndarray, kfs: np.ndarray, C: np.ndarray, chunk: int = 1 << 20) -> None:
    """Each adjusted point moved by the mean of its left-camera observations' keyframe corrections ``C``
    (K, 4, 4), world to world: a point seen before and after a loop takes both sides' corrections, not
    only its first keyframe's.  Rows in chunks of ``chunk`` (millions on a long scan)."""
    pid, left = _points_and_left(observations)
    ids = np.array(sorted(prog.adjusted), np.int64)
    if not len(ids):
        return
    X = np.array([prog.points[int(i)] for i in ids], float).reshape(-1, 3)
    total, count = np.zeros_like(X), np.zeros(len(ids))
    rows = np.flatnonzero(left)
    for a in range(0, len(rows), chunk):
        r = rows[a:a + chunk]
        at = np.searchsorted(ids, pid[r])
        ok = at < len(ids)
        ok[ok] = ids[at[ok]] == pid[r][ok]
        at, k = at[ok], kfs[r][ok].astype(np.int64)
        np.add.at(total, at, np.einsum("nij,nj->ni", C[k, :3, :3], X[at]) + C[k, :3, 3])
        np.add.at(count, at, 1.0)
    seen = count > 0
    X[seen] = total[seen] / count[seen, None]
    prog.points.update(zip(ids[seen].tolist(), X[seen]))


def _over_windows(figures: np.ndarray, column: int) -> float:
    """An RMS figure (``column`` of the windows' figures) over every window, weighted by observations."""
    n = figures[:, 3]
    return float(np.sqrt(np.sum(figures[:, column] ** 2 * n) / np.sum(n))) if n.sum() else float("nan")


def _result(prog: _Progress) -> BAResult:
    """The windows' outcome as one :class:`BAResult` (figures averaged over the windows by observations)."""
    if not prog.figures:
        raise EstimationError("bundle adjustment: no window had enough structure to adjust")
    f = np.array(prog.figures, float)
    n = f[:, 3]
    n_obs = int(n.sum())
    points = {i: prog.points[i] for i in sorted(prog.adjusted)}
    out = BAResult(prog.T, points, _over_windows(f, 0), _over_windows(f, 1), n_obs, len(points), prog.iterations,
                   prog.history[0], prog.history[-1], float(np.sum(f[:, 2] * n) / max(n_obs, 1)), prog.history,
                   prog.offset)
    out.imu_biases = prog.biases
    out.gravity_world = prog.gravity_world
    out.pixel_sigma_px = prog.pixel_sigma_px
    return out
