"""Trajectory evaluation (against evo's own API), report schema and the path plot."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from stereopath.device.errors import DatasetError
from stereopath.device.core.geometry import make_pose, rot_x, rot_y, rot_z
from stereopath.device.formats.tum import Trajectory, read_trajectory
from stereopath.host.evaluation.evaluate import associate_and_align, end_point_error, evaluate
from stereopath.host.evaluation.report import REPORT_KEYS, make_report, read_report, write_report


@pytest.fixture(scope="module")
def traj_dir(data_dir):
    return data_dir / "trajectories"


def _evo_reference(gt_path, est_path, kitti=False):
    """evo's documented way: read files, associate, align SE(3) without scale, APE/RPE."""
    from evo.core import metrics, sync
    from evo.tools import file_interface

    if kitti:
        ref = file_interface.read_kitti_poses_file(str(gt_path))
        est = file_interface.read_kitti_poses_file(str(est_path))
        est_aligned = copy.deepcopy(est)
    else:
        ref = file_interface.read_tum_trajectory_file(str(gt_path))
        est = file_interface.read_tum_trajectory_file(str(est_path))
        ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
        est_aligned = copy.deepcopy(est)
    est_aligned.align(ref, correct_scale=False, correct_only_scale=False)
    data = (ref, est_aligned)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data(data)
    rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=1, delta_unit=metrics.Unit.frames)
    rpe.process_data(data)
    rpe_r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=1, delta_unit=metrics.Unit.frames)
    rpe_r.process_data(data)
    rmse = metrics.StatisticsType.rmse
    return (ape.get_statistic(rmse), rpe.get_statistic(rmse), rpe_r.get_statistic(rmse),
            len(ref.timestamps) if hasattr(ref, "timestamps") else ref.num_poses, ref.path_length)


def test_ate_equals_evo_on_v101(traj_dir):
    ate, rpe_t, rpe_r, n, length = _evo_reference(traj_dir / "V101_gt.txt", traj_dir / "V101_openvins.txt")
    res = evaluate(read_trajectory(traj_dir / "V101_gt.txt"), read_trajectory(traj_dir / "V101_openvins.txt"))
    assert res["n_associated"] == n == 2760
    assert abs(res["ate_rmse_m"] - ate) < 1e-9
    assert abs(res["rpe_trans_rmse_m"] - rpe_t) < 1e-9
    assert abs(res["rpe_rot_rmse_deg"] - rpe_r) < 1e-9
    assert res["path_length_m"] == pytest.approx(length, abs=1e-9)
    assert 0.01 < res["ate_rmse_m"] < 0.2  # OpenVINS on V1_01: a few centimetres
    assert res["accuracy_pct"] == pytest.approx(100 * (1 - res["end_error_m"] / res["path_length_m"]))


@pytest.mark.slow
def test_kitti_00_orb(traj_dir):
    ate, rpe_t, rpe_r, n, length = _evo_reference(traj_dir / "KITTI_00_gt.txt", traj_dir / "KITTI_00_ORB.txt",
                                                   kitti=True)
    res = evaluate(read_trajectory(traj_dir / "KITTI_00_gt.txt"), read_trajectory(traj_dir / "KITTI_00_ORB.txt"))
    assert res["n_associated"] == n == 4541
    assert abs(res["ate_rmse_m"] - ate) < 1e-9
    assert abs(res["rpe_trans_rmse_m"] - rpe_t) < 1e-9
    assert 3000 < res["path_length_m"] < 4500  # KITTI 00 is about 3.7 km
    assert res["ate_rmse_m"] < 10 and res["end_error_m"] < 20


def _path(n=60):
    t = np.linspace(0, 2 * np.pi, n)
    return Trajectory(np.arange(n, dtype=np.int64) * 50_000_000,
                      [make_pose(rot_y(0.3 * np.sin(a)) @ rot_x(0.1 * a), [np.cos(a), 0.2 * np.sin(2 * a), np.sin(a)])
                       for a in t])


def test_rigidly_moved_estimate_has_zero_errors():
    gt = _path()
    G = make_pose(rot_z(0.7) @ rot_x(-0.4), [3.0, -1.0, 2.0])
    est = Trajectory(gt.t_ns + 2_000_000, G @ gt.T_world_cam)  # 2 ms later, another world frame
    res = evaluate(gt, est)
    assert res["n_associated"] == 60
    assert res["ate_rmse_m"] < 1e-9 and res["end_error_m"] < 1e-9 and res["rpe_rot_rmse_deg"] < 1e-6
    assert res["accuracy_pct"] == pytest.approx(100.0)
    assert res["path_length_m"] == pytest.approx(gt.path_length_m())


def test_ate_is_the_rms_of_an_error_no_rigid_motion_can_explain():
    """A hand-computed ATE: the camera at the 8 corners of a cube, each estimate off by 4 cm along
    one axis with the sign x*y*z of its corner.  The errors sum to zero and are uncorrelated with
    the positions, so the best rigid fit is the true one and the ATE is exactly 4 cm."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    sign = corners.prod(axis=1)
    u = np.array([2.0, -1.0, 2.0]) / 3.0
    gt = Trajectory(np.arange(8, dtype=np.int64) * 50_000_000, [make_pose(np.eye(3), c) for c in corners])
    T = gt.T_world_cam.copy()
    T[:, :3, 3] += 0.04 * sign[:, None] * u
    G = make_pose(rot_z(0.7) @ rot_y(-0.2), [5.0, 1.0, -2.0])  # in another world frame
    res = evaluate(gt, Trajectory(gt.t_ns, G @ T))
    assert res["n_associated"] == 8
    assert res["ate_rmse_m"] == pytest.approx(0.04, abs=1e-9)
    assert res["end_error_m"] == pytest.approx(np.linalg.norm(0.04 * (sign[-1] - sign[0]) * u), abs=1e-9)


def test_end_point_error_is_drift_after_first_pose_alignment():
    gt = _path()
    drift = np.linspace(0, 1, len(gt))[:, None] * np.array([0.03, -0.04, 0.0])  # 5 cm at the end
    T = gt.T_world_cam.copy()
    T[:, :3, 3] += drift
    G = make_pose(rot_z(-1.1), [10.0, 0, 0])
    est = Trajectory(gt.t_ns, G @ T)
    res = evaluate(gt, est)
    assert res["end_error_m"] == pytest.approx(0.05, abs=1e-12)
    assert res["end_error_pct"] == pytest.approx(100 * 0.05 / gt.path_length_m())
    assert res["ate_rmse_m"] < res["end_error_m"]  # the Umeyama fit spreads the drift
    assert end_point_error(gt, est) == pytest.approx(0.05, abs=1e-12)


def test_association_respects_max_diff():
    gt = _path()
    est = Trajectory(gt.t_ns + 20_000_000, gt.T_world_cam)  # 20 ms off
    with pytest.raises(DatasetError, match="within 0.01 s"):
        evaluate(gt, est)
    assert evaluate(gt, est, max_diff_s=0.03)["n_associated"] == 60
    with pytest.raises(DatasetError, match="at least 3"):
        evaluate(gt, Trajectory(gt.t_ns[:2], gt.T_world_cam[:2]))


def test_alignment_exposes_aligned_estimate():
    gt = _path()
    G = make_pose(rot_x(0.5), [1.0, 2.0, 3.0])
    a = associate_and_align(gt, Trajectory(gt.t_ns, G @ gt.T_world_cam))
    np.testing.assert_allclose(a.T_gt_est, np.linalg.inv(G), atol=1e-9)
    np.testing.assert_allclose(a.est_aligned.T_world_cam, gt.T_world_cam, atol=1e-9)


def test_report_schema_with_and_without_ground_truth(tmp_path):
    gt = _path()
    metrics = evaluate(gt, gt)
    ms = [10.0, 12.0, 11.0, 50.0, float("nan")]
    rep = make_report("sim:0", "stereo", 60, 58, metrics, ms, "first_camera", extra={"n": np.int64(3)})
    assert tuple(rep) == (*REPORT_KEYS, "extra")
    assert rep["median_frame_ms"] == pytest.approx(11.5)
    assert rep["p95_frame_ms"] == pytest.approx(np.percentile([10, 12, 11, 50], 95))
    assert rep["accuracy_pct"] == pytest.approx(100.0) and rep["ate_rmse_m"] < 1e-9
    write_report(tmp_path / "r.json", rep)
    assert read_report(tmp_path / "r.json") == json.loads(json.dumps(rep))
    bare = make_report("kitti:x", "paper", 10, 0, None, [], "gravity_aligned")
    assert tuple(bare) == REPORT_KEYS
    for key in ("path_length_m", "end_error_m", "end_error_pct", "ate_rmse_m", "rpe_trans_rmse_m",
                "rpe_rot_rmse_deg", "accuracy_pct", "median_frame_ms", "p95_frame_ms"):
        assert bare[key] is None
    write_report(tmp_path / "b.json", bare)
    assert "null" in (tmp_path / "b.json").read_text()
    with pytest.raises(ValueError, match="world_frame"):
        make_report("x", "y", 1, 1, None, [], "camera")
    (tmp_path / "bad.json").write_text('{"source": 1}')
    with pytest.raises(DatasetError, match="missing"):
        read_report(tmp_path / "bad.json")


def test_plot_path_writes_png(tmp_path, traj_dir):
    import cv2

    from stereopath.host.evaluation.plots import plot_path

    gt = read_trajectory(traj_dir / "V101_gt.txt")
    est = read_trajectory(traj_dir / "V101_openvins.txt")
    plot_path(tmp_path / "p.png", gt, est, world_frame="gravity_aligned", title="V1_01")
    img = cv2.imread(str(tmp_path / "p.png"))
    assert img is not None and img.shape[1] > img.shape[0] > 200
    plot_path(tmp_path / "q.png", None, est)
    assert cv2.imread(str(tmp_path / "q.png")) is not None
    assert not list(tmp_path.glob(".*tmp"))
