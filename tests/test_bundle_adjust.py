import numpy as np
import pytest

from device.errors import EstimationError
from device.estimation.stereo_geometry import project
from device.geometry import invert_pose, make_pose, rotation_angle_deg, so3_exp
from device.rig import paper_rig
from host.bundle_adjust import bundle_adjust, propagate_to_frames


def _problem(rng, n_kf=6, n_pts=200):
    rig = paper_rig()
    pts = {i: np.array([rng.uniform(-1, 1), rng.uniform(-0.6, 0.6), rng.uniform(1.0, 2.5)]) for i in range(n_pts)}
    T_wc = [make_pose(so3_exp([0, 0.03 * k, 0]), [0.08 * k, 0, 0]) for k in range(n_kf)]
    obs = []
    for k, T in enumerate(T_wc):
        Tcw = invert_pose(T)
        for i, X in pts.items():
            Xc = Tcw[:3, :3] @ X + Tcw[:3, 3]
            uv0, _ = project(rig.cam0.K, Xc[None])
            uv1, _ = project(rig.cam1.K, (rig.R @ Xc + rig.T)[None])
            obs.append([k, i, 0, *(uv0[0] + rng.normal(0, 0.3, 2))])
            obs.append([k, i, 1, *(uv1[0] + rng.normal(0, 0.3, 2))])
    return rig, np.array(T_wc), pts, np.array(obs)


def test_bundle_adjustment_recovers_perturbed_poses():
    rng = np.random.default_rng(0)
    rig, T_true, pts, obs = _problem(rng)
    T_noisy = T_true.copy()
    for k in range(1, len(T_noisy)):
        T_noisy[k] = T_noisy[k] @ make_pose(so3_exp(rng.normal(0, 0.01, 3)), rng.normal(0, 0.02, 3))
    pts_noisy = {i: X + rng.normal(0, 0.02, 3) for i, X in pts.items()}
    res = bundle_adjust(rig, T_noisy, pts_noisy, obs)
    assert res.rms_after_px < 0.5 < res.rms_before_px
    for k in range(len(T_true)):
        assert np.linalg.norm(res.T_world_cam[k][:3, 3] - T_true[k][:3, 3]) < 2e-3
        assert rotation_angle_deg(res.T_world_cam[k][:3, :3].T @ T_true[k][:3, :3]) < 0.05


def test_bundle_adjustment_rejects_too_little_data():
    rng = np.random.default_rng(1)
    rig, T_true, pts, obs = _problem(rng, n_kf=2, n_pts=5)
    with pytest.raises(EstimationError):
        bundle_adjust(rig, T_true, pts, obs)
    with pytest.raises(EstimationError):
        bundle_adjust(rig, T_true[:1], pts, obs)


def test_propagation_moves_frames_with_their_keyframe():
    T_old = np.array([np.eye(4), make_pose(np.eye(3), [1, 0, 0])])
    T_new = np.array([np.eye(4), make_pose(so3_exp([0, 0, 0.1]), [1, 0.1, 0])])
    frames = np.array([np.eye(4), make_pose(np.eye(3), [1.5, 0, 0])])
    out = propagate_to_frames(frames, np.array([0, 1]), T_old, T_new)
    assert np.allclose(out[0], np.eye(4))
    assert np.allclose(out[1], T_new[1] @ make_pose(np.eye(3), [0.5, 0, 0]))
