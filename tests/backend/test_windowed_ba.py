import numpy as np
import pytest

from stereopath.device.core.geometry import invert_pose, make_pose
from stereopath.host.backend import windowed_ba
from stereopath.host.backend.ba_common import BAConfig, BAProblem
from stereopath.host.backend.loops import Loop
from stereopath.device.core.rig import paper_rig
from stereopath.device.core.stereo import project
from tests.backend.ba_support import adjust
from tests.backend.test_bundle_adjust import _perturbed


def _corridor(rng, n_kf=40, n_pts=600):
    """Keyframes sliding 7.5 cm apart along a textured wall 1.5-2.5 m away; each sees the points in
    front of it (stereo observations with 0.3 px noise)."""
    rig = paper_rig()
    length = 0.075 * n_kf
    pts = {i: np.array([rng.uniform(-0.6, length + 0.6), rng.uniform(-0.5, 0.5), rng.uniform(1.5, 2.5)])
           for i in range(n_pts)}
    T_wc = np.array([make_pose(np.eye(3), [0.075 * k, 0, 0]) for k in range(n_kf)])
    obs = []
    for k, T in enumerate(T_wc):
        for i, X in pts.items():
            Xc = X - T[:3, 3]
            if abs(Xc[0]) > 0.6:
                continue
            uv0, _ = project(rig.cam0.K, Xc[None])
            uv1, _ = project(rig.cam1.K, (rig.R @ Xc + rig.T)[None])
            obs.append([k, i, 0, *(uv0[0] + rng.normal(0, 0.3, 2))])
            obs.append([k, i, 1, *(uv1[0] + rng.normal(0, 0.3, 2))])
    return rig, T_wc, pts, np.array(obs)


@pytest.mark.parametrize("n", [1, 5, 24, 25, 40, 41, 100, 1000])
def test_windows_cover_every_keyframe_and_overlap(n):
    starts = windowed_ba.window_starts(n)
    W, O = windowed_ba.WINDOW, windowed_ba.OVERLAP
    assert starts[0] == 0 and starts == sorted(set(starts))
    assert min(n, starts[-1] + W) == n  # the last window ends at the last keyframe
    assert all(b - a <= W - O for a, b in zip(starts, starts[1:]))  # each window overlaps the last by OVERLAP or more


def test_windows_recover_the_poses_a_batch_recovers():
    rng = np.random.default_rng(11)
    rig, T_true, pts, obs = _corridor(rng)
    T_noisy, pts_noisy = _perturbed(rng, T_true, pts, 0.002, 0.005, 0.01)
    cfg = BAConfig(disparity_offset=False)
    ticks = []
    res = windowed_ba.adjust_in_windows(rig, BAProblem(T_noisy, pts_noisy, obs), cfg, on_window=ticks.append)
    assert sum(ticks) == len(windowed_ba.window_starts(40)) >= 2
    batch = adjust(rig, T_noisy, pts_noisy, obs, max_iterations=30)

    def err(r):
        return np.array([np.linalg.norm(r.T_world_cam[k][:3, 3] - T_true[k][:3, 3]) for k in range(len(T_true))])

    assert err(res).max() < 1.3 * err(batch).max() and err(res).mean() < 1.3 * err(batch).mean()
    assert max(np.linalg.norm(res.T_world_cam[k][:3, 3] - batch.T_world_cam[k][:3, 3]) for k in range(40)) < 2e-3
    assert res.n_points == batch.n_points and res.rms_after_px < 0.5 < res.rms_before_px
    assert np.median([np.linalg.norm(res.points[i] - pts[i]) for i in res.points]) < 5e-3


def test_a_loop_between_windows_is_closed_by_the_pose_graph():
    """A path whose last keyframe drifted: the windows keep the drift (no window holds both ends), the
    loop between the first and last keyframes moves the end onto the measured pose."""
    rng = np.random.default_rng(12)
    rig, T_true, pts, obs = _corridor(rng, n_pts=100)
    T_adj = T_true.copy()
    drift = make_pose(np.eye(3), [0.0, 0.0, 0.02])
    points = dict(pts)
    loop = Loop(0, 39, invert_pose(T_true[0]) @ T_true[39], 100, 100, 1e-5, 1e-5, 0.0)
    T_adj[20:] = np.einsum("ij,njk->nik", drift, T_adj[20:])
    T_new, _ = windowed_ba._close_loops(T_adj, points, obs, [loop])
    assert np.linalg.norm(T_new[39][:3, 3] - T_true[39][:3, 3]) < 2e-3 < np.linalg.norm(T_adj[39][:3, 3] - T_true[39][:3, 3])
