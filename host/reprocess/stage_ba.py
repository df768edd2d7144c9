"""Stage ``ba``: bundle adjustment of the keyframe poses and track points, then every other frame.

The keyframes: :func:`stereopath.host.backend.gtsam_ba.bundle_adjust` on GTSAM (reprojection
error in both cameras, robust loss; the rig's constant disparity error estimated too and applied
when it exceeds ``ba.disparity_offset_min_px``; the verified loops; IMU preintegration between
keyframes when the session has a usable IMU; optional gyro rotation priors), outlier removal and
a second solve.  Every other frame: the keyframe corrections interpolated in time, then a
motion-only refinement on the adjusted points (each frame observes its neighbouring keyframes'
adjusted points by one KLT step each, from where they project in the keyframe).

Outputs (``ba.npz``): ``T_kf``, ``T_frames`` (every frame), the adjusted ``point_ids`` and
``point_xyz``, and ``stats``.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from stereopath.device.core.rig import Rig
from stereopath.device.formats.sequence import SequenceBase
from stereopath.device.errors import EstimationError, ImuMismatchError
from stereopath.device.estimation.base import TrackStatus
from stereopath.host.reprocess.config import ReprocessPreset, StageInputs
from stereopath.host.progress import Bar, progress_bar
from stereopath.host.reprocess.memory import MB, peak_rss_mb, rss_mb
from stereopath.host.reprocess.store import json_array, meta

if TYPE_CHECKING:
    from stereopath.host.backend.tracks import TrackedKeypoints

log = logging.getLogger(__name__)

NAME = "ba"
FRAME_BATCH = 16  # frames read ahead and refined side by side


def settings(config: ReprocessPreset) -> dict[str, Any]:
    return {k: v for k, v in dataclasses.asdict(config).items()
            if k not in ("description", "tracks", "estimator_preset", "estimator_options")}


def gyro_rotation_priors(seq: SequenceBase, t_kf: np.ndarray, sigma_rad_per_sqrt_s: float,
                         T_kf: np.ndarray | None = None) -> list:
    """Relative rotations between consecutive keyframes from the gyro (bias from the still start; without
    one, from the keyframe path ``T_kf``; with neither, none: an unknown bias would bend the path)."""
    from stereopath.device.estimation.inertial import GyroIntegrator, estimate_still
    from stereopath.device.estimation.inertial_init import gyro_bias_from_path
    from stereopath.host.backend.ba_common import RotationPrior

    imu = getattr(seq, "imu", None)
    rig = seq.rig
    if imu is None or not len(imu) or rig.T_body_cam0 is None:
        return []
    Rbc = np.asarray(rig.T_body_cam0)[:3, :3]
    still = estimate_still(imu.between(int(imu.t_ns[0]) - 1, int(seq.t_ns[0])))
    if still is not None:
        bias = still.gyro_bias_rad_s
    else:
        fit = None if T_kf is None else gyro_bias_from_path(imu, t_kf, np.asarray(T_kf)[:, :3, :3] @ Rbc.T)
        if fit is None:
            log.warning("no gyro rotation priors: no still start and too short a path for the gyro bias")
            return []
        bias = fit.bias_rad_s
    out = []
    for i in range(len(t_kf) - 1):
        g = GyroIntegrator(bias)
        blk = imu.between(int(t_kf[i]) - 50_000_000, int(t_kf[i + 1]) + 50_000_000)
        Rb = g.feed_and_integrate(blk, int(t_kf[i]), int(t_kf[i + 1]))
        if Rb is None:
            continue
        dt = (int(t_kf[i + 1]) - int(t_kf[i])) * 1e-9
        out.append(RotationPrior(i, i + 1, Rbc.T @ Rb @ Rbc, max(sigma_rad_per_sqrt_s * np.sqrt(dt), 1e-6)))
    return out


def loops_of(trk: dict[str, np.ndarray]) -> list:
    """The verified loops stored by the tracks stage."""
    from stereopath.host.backend.loops import loops_from_array

    return loops_from_array(trk["loops"]) if "loops" in trk else []


def end_to_start(T: np.ndarray) -> dict[str, float]:
    """The path's end relative to its start: distance (m) and rotation (deg)."""
    from stereopath.device.core.geometry import invert_pose, rotation_angle_deg

    rel = invert_pose(T[0]) @ T[-1]
    return {"distance_m": float(np.linalg.norm(rel[:3, 3])), "rotation_deg": float(rotation_angle_deg(rel[:3, :3]))}


def imu_terms_of(config: ReprocessPreset, inputs: StageInputs):
    """Preintegrated IMU between the keyframes, and whether the IMU may be used at all: (None, False)
    without ``ba.imu`` or an IMU, or when its readings were shown not to fit the path; (None, True)
    when it was not refused but gives no factors (too few keyframe intervals, e.g. a session that
    rests: then the checks against the path could not run either)."""
    from stereopath.host.backend.imu_factors import imu_terms

    if not config.ba.imu or getattr(inputs.seq, "imu", None) is None:
        return None, False
    est, trk = inputs.results["estimate"], inputs.results["tracks"]
    try:
        return imu_terms(inputs.seq, est["t_ns"][trk["kf_index"]], trk["T_kf"]), True
    except EstimationError as exc:
        log.warning("bundle adjustment without the IMU: %s", exc)
        return None, not isinstance(exc, ImuMismatchError)


def imu_report(terms, res, t_kf: np.ndarray) -> dict[str, Any] | None:
    """The IMU part of the stage's stats: noise used, gravity, the biases estimated per keyframe."""
    if terms is None or res.imu_biases is None:
        return None
    b = res.imu_biases
    ok = np.flatnonzero(np.isfinite(b[:, 0]))
    return {"factors": len(terms.pims), "noise": dataclasses.asdict(terms.noise),
            "gravity_world_initial": terms.gravity_world.tolist(),
            "biases": {"t_ns": t_kf[ok].tolist(), "accel_m_s2": b[ok, :3].tolist(), "gyro_rad_s": b[ok, 3:].tolist()},
            "accel_bias_mean_m_s2": b[ok, :3].mean(axis=0).tolist() if len(ok) else None,
            "gyro_bias_mean_rad_s": b[ok, 3:].mean(axis=0).tolist() if len(ok) else None}


def adjust_keyframes(config: ReprocessPreset, inputs: StageInputs, priors: list, imu=None):
    """Bundle adjustment of the keyframes (a ``BAResult``); EstimationError when there is too little."""
    from stereopath.host.backend.ba_common import BAProblem
    from stereopath.host.backend.gtsam_ba import bundle_adjust
    from stereopath.host.backend.windowed_ba import BATCH_KEYFRAMES, WindowCheckpoint, adjust_in_windows, window_starts

    trk = inputs.results["tracks"]
    points = {int(i): x for i, x in zip(trk["point_ids"], trk["point_xyz"])}
    problem = BAProblem(trk["T_kf"], points, trk["observations"], loops=loops_of(trk), imu=imu)
    if len(trk["T_kf"]) > BATCH_KEYFRAMES:  # a long session: windows of keyframes, memory independent of its length
        with Bar(len(window_starts(len(trk["T_kf"]))), "bundle adjustment", inputs.progress, "window") as tick:
            # each window's outcome is stored: a stage interrupted on a long session resumes after the last one
            store = None if inputs.parts is None else WindowCheckpoint(inputs.parts)
            return adjust_in_windows(inputs.seq.rig, problem, config.ba, priors, on_window=tick, checkpoint=store)
    bar = progress_bar(config.ba.max_iterations * (1 + config.ba.outlier_rounds), "bundle adjustment",
                       inputs.progress, "iteration")
    try:
        return bundle_adjust(inputs.seq.rig, problem, config.ba, priors, on_iteration=None if bar is None else bar.update)
    finally:
        if bar is not None:
            bar.close()


def solver_stats(n_keyframes: int, n_loops: int) -> dict[str, Any]:
    """How the keyframes were adjusted, for a session above the batch's length (nothing below it)."""
    from stereopath.host.backend.windowed_ba import BATCH_KEYFRAMES, HELD, OVERLAP, WINDOW, window_starts

    if n_keyframes <= BATCH_KEYFRAMES:
        return {}
    n_windows = len(window_starts(n_keyframes))
    return {"solver": {"windows": n_windows, "window_keyframes": WINDOW, "overlap": OVERLAP,
                       "held": HELD, "loops_closed_first": n_loops > 0, "loops_closed_last": n_loops > 0 and n_windows > 1}}


def _frame_jobs(config: ReprocessPreset, inputs: StageInputs, res, is_kf: np.ndarray
                ) -> Iterator[tuple[int, np.ndarray, list[TrackedKeypoints]]]:
    """Each non-keyframe's refinement input, one frame at a time: ``(frame index, left image, its two
    keyframes' adjusted points as followed from each keyframe's left image)`` (:func:`adjusted_pixels`).

    The left image only: with the points fixed, a frame's pose needs no depth from it, and at the same
    CPU twice as many left points (``frame_points`` from each keyframe) fit it better than left and
    right observations of half as many (figures in CHANGELOG).  The left image is as recorded, so no
    exposure fit is needed for it."""
    from stereopath.host.backend.tracks import TrackedKeypoints

    seq, est, trk = inputs.seq, inputs.results["estimate"], inputs.results["tracks"]
    kf, offs = trk["kf_index"], trk["kf_offsets"]
    kf_img: dict[int, TrackedKeypoints] = {}
    read = getattr(seq, "frame_as_recorded", seq.frame)  # the left image is never exposure-corrected

    def read_left(i: int) -> np.ndarray:
        return read(i).left

    for i in np.flatnonzero(~is_kf):
        j = int(np.searchsorted(kf, i))
        left = read_left(int(est["seq"][i]))
        around = []
        for k in (j - 1, j):
            if not 0 <= k < len(kf):
                continue
            if k not in kf_img:  # the keyframe's image and the points followed from it, for the frames around it
                kf_img = {kk: v for kk, v in kf_img.items() if kk >= k - 1}  # keep the cache small
                ids, xy = adjusted_pixels(seq.rig, res, k, trk["kf_ids"][offs[k]:offs[k + 1]],
                                          trk["kf_xy"][offs[k]:offs[k + 1]])
                if len(ids) > config.frame_points:
                    pick = np.linspace(0, len(ids) - 1, config.frame_points).astype(int)
                    ids, xy = ids[pick], xy[pick]
                kf_img[k] = TrackedKeypoints(read_left(int(est["seq"][kf[k]])), xy, ids)
            around.append(kf_img[k])
        yield int(i), left, around


def _refined_frame(shared: tuple, job) -> np.ndarray | None:
    """One frame of :func:`_frame_jobs` refined (a piece; ``shared`` = preset, rig, adjustment, every
    frame's pose): the keyframes' points followed by KLT into its left image, then its pose fitted to
    them (:func:`refine_frame`); None when it cannot be."""
    from stereopath.host.backend.tracks import frame_observations

    config, rig, res, T_frames = shared
    i, left, around = job
    T_frame = T_frames[i]
    rows = []
    for kp in around:
        o = frame_observations(rig, kp, res.points, (left, None), T_frame, config.tracks, right_image=False)
        o[:, 0] = i
        rows.append(o)
    part = np.vstack(rows) if rows else np.zeros((0, 6))
    if not len(part):
        return None
    return refine_frame(rig, T_frame, res.points, part, config.ba.robust_px, res.disparity_offset_px)


# a keypoint is followed from where its adjusted point projects in the keyframe when its detection is
# within this many of the adjustment's RMS residuals of it (``rms_after_px``: per coordinate, both
# cameras, the observations weighted by their keypoint size as in the adjustment) ...
ADJUSTED_GATE_RMS = 3.0
MIN_GATE_RMS_PX = 0.05  # ... taken as at least this (an adjustment of exact synthetic pixels)


def adjusted_pixels(rig: Rig, res, k: int, ids: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where keyframe ``k``'s adjusted points ``ids`` project in its left image (raw pixels), for the
    keypoints ``xy`` (raw) whose detection lies within :data:`ADJUSTED_GATE_RMS` RMS residuals of that
    projection (the others are dropped).

    A detection carries its own noise; the adjusted point is fitted to every keyframe of its track,
    and its projection with the adjusted pose is where the keyframe sees it.  Followed from there into
    a frame, the frame's observation agrees with the point instead of copying one detection's error."""
    import cv2

    from stereopath.device.core.geometry import invert_pose

    known = np.fromiter((int(i) in res.points for i in ids), bool, len(ids))
    ids, xy = ids[known], xy[known]
    if not len(ids):
        return ids, xy
    X = np.array([res.points[int(i)] for i in ids])
    T_cw = invert_pose(res.T_world_cam[k])
    Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    front = Xc[:, 2] > 1e-6
    ids, xy, Xc = ids[front], xy[front], Xc[front]
    if not len(ids):
        return ids, xy
    uv = cv2.projectPoints(Xc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), rig.cam0.K, rig.cam0.dist)[0].reshape(-1, 2)
    rms = float(res.rms_after_px)
    gate = ADJUSTED_GATE_RMS * max(rms, MIN_GATE_RMS_PX) if np.isfinite(rms) else np.inf  # no figure: no gate
    near = np.linalg.norm(uv - xy, axis=1) <= gate
    return ids[near], uv[near].astype(np.float32)


def refine_frame(rig: Rig, T_world_cam: np.ndarray, points: dict[int, np.ndarray], rows: np.ndarray,
                 huber_px: float, disparity_offset_px: float, min_obs: int = 6) -> np.ndarray | None:
    """One frame's pose moved to fit the fixed adjusted ``points`` (its observation ``rows``); None
    with fewer than ``min_obs`` rows.  Each frame is independent once the points are fixed, so this is
    a 6-unknown Levenberg-Marquardt per frame (Huber, both cameras; the right camera's principal point
    shifted by the adjusted disparity offset, as in the bundle adjustment)."""
    from stereopath.device.core.geometry import invert_pose
    from stereopath.device.core.stereo import LMOptions, PointObservations, refine_pose_lm

    rows = rows[np.fromiter((int(p) in points for p in rows[:, 1]), bool, len(rows))]
    if len(rows) < min_obs:
        return None
    X = np.array([points[int(i)] for i in rows[:, 1]])
    left, right = rows[:, 2] == 0, rows[:, 2] == 1
    uv_r = rows[right, 3:5] - [disparity_offset_px, 0.0]
    res = refine_pose_lm(rig, invert_pose(T_world_cam), PointObservations(X[left], rows[left, 3:5]),
                         PointObservations(X[right], uv_r), LMOptions(huber_px=huber_px, max_iter=10, outlier_px=3.0 * huber_px))
    T = invert_pose(res.T_cam_world)
    return T if np.all(np.isfinite(T)) else None


def refine_frames(config: ReprocessPreset, inputs: StageInputs, res, T_frames: np.ndarray) -> int:
    """Motion-only refinement of the non-keyframes of ``T_frames`` (in place), one frame at a time; the
    number refined."""
    import cv2

    from stereopath.host.backend.parallel import ThreadSpreader

    is_kf = np.zeros(len(T_frames), bool)
    is_kf[inputs.results["tracks"]["kf_index"]] = True
    n = 0
    # frames are independent once the points are fixed: read in order, refined side by side on the
    # threads OpenCV may use, applied in order
    spread = ThreadSpreader(max(1, cv2.getNumThreads()))
    shared = (config, inputs.seq.rig, res, T_frames)
    jobs = _frame_jobs(config, inputs, res, is_kf)
    with Bar(int(np.count_nonzero(~is_kf)), "frame refinement", inputs.progress, "frame") as tick:
        while batch := list(itertools.islice(jobs, FRAME_BATCH)):
            for (i, _, _), T in zip(batch, spread(_refined_frame, shared, batch)):
                if T is not None:
                    T_frames[i] = T
                    n += 1
            tick(len(batch))
    return n


def level_world(inputs: StageInputs, res, T_frames: np.ndarray, imu_usable: bool = False) -> dict[str, Any] | None:
    """A session estimated in its first camera's world (no still IMU start) whose gravity is known
    after all: measured by the bundle adjustment's IMU factors, else (``imu_usable``: the IMU was not
    refused for disagreeing with the path, nor switched off) by the IMU where the rig rests during
    tracked frames (:func:`~stereopath.device.estimation.inertial_init.gravity_from_still_frames`).
    The adjusted poses and points (``res``, in place) and every frame (``T_frames``, in place) are
    turned into the gravity-aligned world a still start gives, z up, so that the model comes out
    upright.  Returns the turn (degrees, and ``R_new_old``, which takes the estimate's and the
    tracks' world to the new one), what measured gravity and gravity in the new world; None when the
    world stays as it was."""
    from stereopath.device.core.geometry import make_pose, rotation_angle_deg
    from stereopath.device.estimation.inertial import leveling_rotation
    from stereopath.device.estimation.inertial_init import gravity_from_still_frames

    est = inputs.results["estimate"]
    rig, imu = inputs.seq.rig, getattr(inputs.seq, "imu", None)
    if rig.T_body_cam0 is None or meta(est, "meta").get("world_frame") != "first_camera":
        return None
    R_body_cam = np.asarray(rig.T_body_cam0)[:3, :3]
    gravity, by = res.gravity_world, "imu_factors"
    if gravity is None and imu_usable and imu is not None and len(imu):
        tracked = np.asarray(est["status"]) == TrackStatus.OK.code if "status" in est else None
        T_world_body = T_frames @ make_pose(R_body_cam.T, np.zeros(3))
        gravity, by = gravity_from_still_frames(imu, est["t_ns"], T_world_body, tracked), "still_imu"
    if gravity is None:
        return None
    R = leveling_rotation(T_frames[0][:3, :3], R_body_cam, gravity)
    A = make_pose(R, np.zeros(3))
    T_frames[:] = A @ T_frames
    res.T_world_cam = A @ res.T_world_cam
    res.points = {i: R @ x for i, x in res.points.items()}
    if res.gravity_world is not None:
        res.gravity_world = R @ res.gravity_world
    log.info("world frame turned %.2f deg onto gravity (measured by %s)", rotation_angle_deg(R),
             "the IMU factors" if by == "imu_factors" else "the IMU where the rig rests")
    return {"deg": round(float(rotation_angle_deg(R)), 3), "by": by, "R_new_old": R.tolist(),
            "gravity_world": (R @ np.asarray(gravity, float)).tolist()}


def run(config: ReprocessPreset, inputs: StageInputs) -> dict[str, np.ndarray]:
    from stereopath.host.backend.ba_common import interpolate_corrections

    est, trk = inputs.results["estimate"], inputs.results["tracks"]
    kf, T_kf = trk["kf_index"], trk["T_kf"]
    priors = []
    if config.imu_rotation_priors:
        priors = gyro_rotation_priors(inputs.seq, est["t_ns"][kf], config.gyro_sigma_rad_per_sqrt_s, T_kf)
    t0 = time.perf_counter()
    imu, imu_usable = imu_terms_of(config, inputs)
    inputs.memory.note("observations", trk["observations"].nbytes)
    rss0 = rss_mb()
    try:
        with inputs.memory.timed("bundle_adjustment"):
            res = adjust_keyframes(config, inputs, priors, imu)
        inputs.memory.note("gtsam_graph", int((peak_rss_mb() - rss0) * MB))  # the solver's growth of the peak
    except EstimationError as exc:
        # too little structure to adjust (e.g. a very short or featureless session): keep the re-estimate
        log.warning("bundle adjustment not possible (%s): the re-estimated path is kept", exc)
        return {"T_kf": T_kf, "T_frames": est["T_world_cam"].copy(), "point_ids": np.zeros(0, np.int64),
                "point_xyz": np.zeros((0, 3)), "stats": json_array({"skipped": str(exc), "poses": len(kf)})}
    t_ba = time.perf_counter() - t0
    T_frames = interpolate_corrections(est["t_ns"], est["T_world_cam"], est["t_ns"][kf], T_kf, res.T_world_cam)
    T_frames[kf] = res.T_world_cam
    t1 = time.perf_counter()
    with inputs.memory.timed("frame_refinement"):
        n_refined = refine_frames(config, inputs, res, T_frames) if config.refine_frames else 0
    leveled = level_world(inputs, res, T_frames, imu_usable)
    loops = loops_of(trk)
    stats = {"poses": len(kf), "points": res.n_points, "observations": res.n_obs,
             "rms_before_px": res.rms_before_px, "rms_after_px": res.rms_after_px, "iterations": res.iterations,
             "inlier_fraction": res.inlier_fraction, "rotation_priors": len(priors),
             "pixel_sigma_px": res.pixel_sigma_px,
             "disparity_offset_px": res.disparity_offset_px if config.ba.disparity_offset else None,
             "frames_refined": n_refined, "ba_seconds": round(t_ba, 3), **solver_stats(len(kf), len(loops)),
             "frame_refinement_seconds": round(time.perf_counter() - t1, 3),
             "loops": [lp.as_dict() for lp in loops],
             "imu": imu_report(imu, res, est["t_ns"][kf]),
             "world_frame": "gravity_aligned" if leveled is not None else meta(est, "meta").get("world_frame"),
             "leveled": leveled,
             "end_to_start": {"reestimated": end_to_start(est["T_world_cam"]), "bundle_adjusted": end_to_start(T_frames)}}
    ids = np.fromiter(res.points.keys(), np.int64, len(res.points))
    return {
        "T_kf": res.T_world_cam,
        "T_frames": T_frames,
        "point_ids": ids,
        "point_xyz": np.array([res.points[int(i)] for i in ids]).reshape(-1, 3),
        "stats": json_array(stats),
    }
