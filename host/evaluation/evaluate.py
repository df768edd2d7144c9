"""Trajectory evaluation against ground truth, with evo underneath.

:func:`evaluate` associates the estimate with the ground truth by timestamp
(``evo.core.sync.associate_trajectories``, nearest stamp within ``max_diff_s``) and reports:

* ``ate_rmse_m`` (and mean/median/max): absolute trajectory error of the positions after aligning
  the estimate onto the ground truth with Umeyama's method, SE(3), **without scale**
  (``PoseTrajectory3D.align(correct_scale=False)`` then ``metrics.APE`` on the translation part),
  exactly what ``evo_ape tum GT EST -a`` computes;
* ``rpe_trans_rmse_m`` / ``rpe_rot_rmse_deg``: relative pose error between consecutive associated
  poses (delta = 1 frame), translation part and rotation angle (``metrics.RPE``);
* ``end_error_m``: the drift measure of the reference paper.  The estimate is moved rigidly so that
  its FIRST associated pose coincides with the ground truth's first associated pose (no fit over
  the path), and the end error is the distance between the LAST associated positions;
* ``path_length_m``: length of the ground-truth polyline through the associated poses;
* ``end_error_pct`` = 100 * end error / path length, ``accuracy_pct`` = 100 - ``end_error_pct``
  (the paper's 100 * (1 - end error / path length));
* ``n_associated``: number of associated pose pairs (``n_gt``, ``n_est`` for the inputs).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from stereopath.device.errors import DatasetError
from stereopath.device.core.geometry import invert_pose
from stereopath.device.formats.tum import Trajectory

if TYPE_CHECKING:
    from evo.core.trajectory import PoseTrajectory3D

MIN_ASSOCIATED = 3


def ns_to_seconds(t_ns: np.ndarray) -> np.ndarray:
    """Integer nanoseconds -> float seconds, rounding once (exact whole seconds + fraction)."""
    t = np.asarray(t_ns, dtype=np.int64)
    return (t // 1_000_000_000).astype(float) + (t % 1_000_000_000).astype(float) / 1e9


def to_evo(traj: Trajectory) -> PoseTrajectory3D:
    """Our :class:`Trajectory` as an ``evo.core.trajectory.PoseTrajectory3D``."""
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(poses_se3=list(np.asarray(traj.T_world_cam, dtype=float)),
                            timestamps=ns_to_seconds(traj.t_ns))


@dataclass
class Association:
    """Associated pose pairs and the SE(3) alignment of the estimate onto the ground truth."""

    gt: Trajectory  # associated ground-truth poses
    est: Trajectory  # associated estimated poses (as given)
    est_aligned: Trajectory  # est after the Umeyama SE(3) alignment (used for ATE)
    T_gt_est: np.ndarray  # the alignment: est_aligned = T_gt_est @ est
    evo_gt: PoseTrajectory3D
    evo_est_aligned: PoseTrajectory3D


def _indices(stamps_assoc: np.ndarray, stamps_all: np.ndarray) -> np.ndarray:
    idx = np.searchsorted(stamps_all, stamps_assoc)
    idx = np.clip(idx, 0, len(stamps_all) - 1)
    if not np.array_equal(stamps_all[idx], stamps_assoc):  # pragma: no cover - evo keeps stamps as they are
        raise DatasetError("association returned timestamps that are not in the input")
    return idx


def _sorted(traj: Trajectory, what: str) -> Trajectory:
    if len(traj) < 2:
        return traj
    d = np.diff(traj.t_ns)
    if np.all(d > 0):
        return traj
    order = np.argsort(traj.t_ns, kind="stable")
    t = traj.t_ns[order]
    if np.any(np.diff(t) == 0):
        raise DatasetError(f"{what} trajectory has duplicate timestamps")
    return Trajectory(t, traj.T_world_cam[order])


def associate_and_align(gt: Trajectory, est: Trajectory, max_diff_s: float = 0.01) -> Association:
    """Associate by timestamp (evo) and align the estimate onto the ground truth (SE(3), no scale)."""
    from evo.core import sync
    from evo.core.trajectory import PoseTrajectory3D

    gt = _sorted(gt, "ground-truth")
    est = _sorted(est, "estimated")
    if len(gt) < MIN_ASSOCIATED or len(est) < MIN_ASSOCIATED:
        raise DatasetError(f"evaluation needs at least {MIN_ASSOCIATED} poses in each trajectory "
                           f"(ground truth {len(gt)}, estimate {len(est)})")
    ref, est_e = to_evo(gt), to_evo(est)
    ref_stamps, est_stamps = ref.timestamps.copy(), est_e.timestamps.copy()
    try:
        ref_a, est_a = sync.associate_trajectories(ref, est_e, max_diff=max_diff_s)
    except sync.SyncException as exc:
        raise DatasetError(f"no estimated pose within {max_diff_s} s of a ground-truth pose: {exc}") from None
    n = len(ref_a.timestamps)
    if n < MIN_ASSOCIATED:
        raise DatasetError(f"only {n} estimated poses lie within {max_diff_s} s of a ground-truth pose "
                           f"(need {MIN_ASSOCIATED})")
    i_gt = _indices(ref_a.timestamps, ref_stamps)
    i_est = _indices(est_a.timestamps, est_stamps)
    gt_a = Trajectory(gt.t_ns[i_gt], gt.T_world_cam[i_gt])
    est_raw = Trajectory(est.t_ns[i_est], est.T_world_cam[i_est])
    aligned: PoseTrajectory3D = copy.deepcopy(est_a)
    _check_moves(gt_a, "ground-truth")
    _check_moves(est_raw, "estimated")
    from evo.core.geometry import GeometryException

    try:
        r, t, _ = aligned.align(ref_a, correct_scale=False, correct_only_scale=False)
    except GeometryException as exc:  # e.g. all positions on one line or one point
        raise DatasetError(f"cannot align the estimated path onto the ground truth ({exc}): one of the paths "
                           f"has no spatial extent (a straight line or a point)") from None
    T = np.eye(4)
    T[:3, :3] = r
    T[:3, 3] = t
    est_al = Trajectory(est_raw.t_ns, np.array(aligned.poses_se3))
    return Association(gt_a, est_raw, est_al, T, ref_a, aligned)


MIN_EXTENT_M = 1e-6


def _check_moves(traj: Trajectory, what: str) -> None:
    """A path whose positions all coincide cannot be aligned: say so instead of evo's rank error."""
    p = traj.positions
    extent = float(np.max(np.linalg.norm(p - p.mean(axis=0), axis=1))) if len(p) else 0.0
    if extent < MIN_EXTENT_M:
        hint = (" (the estimator never moved: tracking lost from the start, a wrong rig, or left and right "
                "images swapped?)" if what == "estimated" else "")
        raise DatasetError(f"the {what} path does not move: its {len(p)} associated positions all lie within "
                           f"{extent * 1000:.3f} mm of each other; nothing to evaluate{hint}")


def end_point_error(gt: Trajectory, est: Trajectory) -> float:
    """Distance between the last positions after moving ``est``'s first pose onto ``gt``'s first.

    Both trajectories must already be associated (same length, pose i with pose i).
    """
    T = gt.T_world_cam[0] @ invert_pose(est.T_world_cam[0])
    p_end = (T @ est.T_world_cam[-1])[:3, 3]
    return float(np.linalg.norm(p_end - gt.T_world_cam[-1][:3, 3]))


def evaluate(gt: Trajectory, est: Trajectory, max_diff_s: float = 0.01) -> dict[str, Any]:
    """All the figures of the module doc as a dict of plain floats/ints."""
    from evo.core import metrics

    a = associate_and_align(gt, est, max_diff_s)
    data = (a.evo_gt, a.evo_est_aligned)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data(data)
    rpe_t = metrics.RPE(metrics.PoseRelation.translation_part, delta=1, delta_unit=metrics.Unit.frames,
                        all_pairs=False)
    rpe_t.process_data(data)
    rpe_r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=1, delta_unit=metrics.Unit.frames,
                        all_pairs=False)
    rpe_r.process_data(data)
    path = a.gt.path_length_m()
    end = end_point_error(a.gt, a.est)
    end_pct = 100.0 * end / path if path > 0 else None
    return {
        "n_gt": len(gt),
        "n_est": len(est),
        "n_associated": len(a.gt),
        "max_diff_s": float(max_diff_s),
        "ate_rmse_m": float(ape.get_statistic(metrics.StatisticsType.rmse)),
        "ate_mean_m": float(ape.get_statistic(metrics.StatisticsType.mean)),
        "ate_median_m": float(ape.get_statistic(metrics.StatisticsType.median)),
        "ate_max_m": float(ape.get_statistic(metrics.StatisticsType.max)),
        "rpe_trans_rmse_m": float(rpe_t.get_statistic(metrics.StatisticsType.rmse)),
        "rpe_rot_rmse_deg": float(rpe_r.get_statistic(metrics.StatisticsType.rmse)),
        "end_error_m": end,
        "path_length_m": path,
        "end_error_pct": end_pct,
        "accuracy_pct": None if end_pct is None else 100.0 - end_pct,
        "duration_s": float((a.gt.t_ns[-1] - a.gt.t_ns[0]) / 1e9),
    }


def position_errors(a: Association) -> tuple[np.ndarray, np.ndarray]:
    """(distance travelled along the ground truth, aligned position error) per associated pose."""
    p = a.gt.positions
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    err = np.linalg.norm(a.est_aligned.positions - p, axis=1)
    return dist, err
