import numpy as np
import pytest

from stereopath.device.core.geometry import invert_pose, make_pose, so3_exp
from stereopath.host.backend import ba_common, windowed_ba
from stereopath.device.errors import EstimationError
from stereopath.host.backend.ba_common import (
    BAConfig,
    BAProblem,
    as_observations,
)
from stereopath.host.backend.observations import compact_observations, observation_keyframes
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


@pytest.fixture
def small_windows(monkeypatch):
    """Windows of 24 keyframes overlapping by 8, the first 4 held: several on a 40-keyframe problem."""
    monkeypatch.setattr(windowed_ba, "WINDOW", 24)
    monkeypatch.setattr(windowed_ba, "OVERLAP", 8)
    monkeypatch.setattr(windowed_ba, "HELD", 4)


def test_windows_recover_the_poses_a_batch_recovers(small_windows):
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


def test_a_loop_back_to_an_earlier_window_holds_that_keyframe_in_the_window(small_windows, monkeypatch):
    """The window holding a loop's later keyframe gets the earlier keyframe as a held anchor, the loop
    between them, and everything else renumbered after it; the windows before it get neither."""
    from stereopath.host.backend import gtsam_ba

    rng = np.random.default_rng(12)
    rig, T_true, pts, obs = _corridor(rng, n_pts=300)
    loop = Loop(2, 39, invert_pose(T_true[2]) @ T_true[39], 100, 100, 1e-4, 1e-4, 0.0)
    seen = []
    solve = gtsam_ba.bundle_adjust

    def spy(rig, problem, config, priors=(), on_iteration=None):
        seen.append(problem)
        return solve(rig, problem, config, priors, on_iteration)

    monkeypatch.setattr(gtsam_ba, "bundle_adjust", spy)
    res = windowed_ba.adjust_in_windows(rig, BAProblem(T_true, pts, obs, [loop]), BAConfig(disparity_offset=False))
    starts = windowed_ba.window_starts(40)
    assert len(seen) == len(starts)
    for pb, s in zip(seen, starts):
        if s + windowed_ba.WINDOW <= 39:  # a window without the loop's later keyframe
            assert not pb.loops and len(pb.T_world_cam) == windowed_ba.WINDOW
            continue
        assert len(pb.T_world_cam) == windowed_ba.WINDOW + 1 and np.allclose(pb.T_world_cam[0], T_true[2], atol=2e-3)
        assert pb.n_fixed == 1 + windowed_ba.HELD and [(lp.i, lp.j) for lp in pb.loops] == [(0, 1 + 39 - s)]
        assert pb.observations[:, 0].min() >= 1  # the anchor has no observations of its own
    assert np.abs(res.T_world_cam[2] - T_true[2]).max() < 2e-3


class _Interrupted(Exception):
    pass


def test_windows_interrupted_resume_after_the_last_stored_window_with_the_same_result(small_windows, monkeypatch,
                                                                                     tmp_path):
    """A run stopped in its third window resumes from the two stored ones (solving only the windows after
    them) and ends where a run without interruption ends, bit for bit."""
    from stereopath.host.backend import gtsam_ba

    rng = np.random.default_rng(13)
    rig, T_true, pts, obs = _corridor(rng, n_kf=72, n_pts=600)
    T_noisy, pts_noisy = _perturbed(rng, T_true, pts, 0.002, 0.005, 0.01)
    loop = Loop(3, 66, invert_pose(T_true[3]) @ T_true[66], 100, 100, 1e-4, 1e-4, 0.0)
    problem = BAProblem(T_noisy, pts_noisy, obs, [loop])
    cfg = BAConfig(disparity_offset=True)
    n_windows = len(windowed_ba.window_starts(72))
    assert n_windows >= 4
    whole = windowed_ba.adjust_in_windows(rig, problem, cfg)

    solve, calls = gtsam_ba.bundle_adjust, []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise _Interrupted
        return solve(*args, **kwargs)

    monkeypatch.setattr(gtsam_ba, "bundle_adjust", failing)
    store = windowed_ba.WindowCheckpoint(tmp_path / "parts")
    with pytest.raises(_Interrupted):
        windowed_ba.adjust_in_windows(rig, problem, cfg, checkpoint=store)
    ticks: list[int] = []
    calls.clear()
    resumed = windowed_ba.adjust_in_windows(rig, problem, cfg, on_window=ticks.append, checkpoint=store)
    assert len(calls) == n_windows - 2 and sum(ticks) == n_windows and ticks[0] == 2
    assert np.array_equal(resumed.T_world_cam, whole.T_world_cam)
    assert resumed.points.keys() == whole.points.keys()
    assert all(np.array_equal(resumed.points[i], whole.points[i]) for i in whole.points)
    assert (resumed.rms_after_px, resumed.iterations, resumed.history, resumed.disparity_offset_px) == \
        (whole.rms_after_px, whole.iterations, whole.history, whole.disparity_offset_px)


def test_a_checkpoint_of_another_problem_is_not_resumed(small_windows, tmp_path):
    rng = np.random.default_rng(14)
    rig, T_true, pts, obs = _corridor(rng, n_kf=40, n_pts=300)
    store = windowed_ba.WindowCheckpoint(tmp_path)
    cfg = BAConfig(disparity_offset=False)
    windowed_ba.adjust_in_windows(rig, BAProblem(T_true, pts, obs), cfg, checkpoint=store)
    assert store.load(40, pts) is not None and store.load(41, pts) is None
    store.path.write_bytes(b"not an npz")
    assert store.load(40, pts) is None


def test_the_windows_start_from_the_path_with_its_loops_closed(small_windows, monkeypatch):
    """A path drifting along its length with a loop back to its start: the first window is handed the
    loop-closed path (the pose graph's), whose far end the loop has pulled back towards the truth."""
    from stereopath.host.backend import gtsam_ba

    rng = np.random.default_rng(15)
    rig, T_true, pts, obs = _corridor(rng, n_pts=300)
    drift = np.array([make_pose(np.eye(3), [0.0, 0.0, 0.0005 * k]) for k in range(40)])  # 2 cm at the end
    T_drift = np.einsum("nij,njk->nik", drift, T_true)
    loop = Loop(2, 39, invert_pose(T_true[2]) @ T_true[39], 100, 100, 1e-4, 1e-4, 0.0)
    seen = []
    solve = gtsam_ba.bundle_adjust

    def spy(rig, problem, config, priors=(), on_iteration=None):
        seen.append(problem.T_world_cam.copy())
        return solve(rig, problem, config, priors, on_iteration)

    monkeypatch.setattr(gtsam_ba, "bundle_adjust", spy)
    windowed_ba.adjust_in_windows(rig, BAProblem(T_drift, pts, obs, [loop]), BAConfig(disparity_offset=False))
    closed = gtsam_ba.pose_graph(T_drift, [loop])
    assert np.allclose(seen[0], closed[:windowed_ba.WINDOW])
    assert abs(closed[39][2, 3] - T_true[39][2, 3]) < 0.5 * abs(T_drift[39][2, 3] - T_true[39][2, 3])


def test_compact_observations_give_the_windows_the_same_poses(small_windows, monkeypatch):
    """Rows held compact (int32 ids, float32 pixels) and widened a window at a time: the same poses as
    float rows within the float32 rounding of the pixels (far below the 0.3 px noise)."""
    rng = np.random.default_rng(5)
    rig, T_true, pts, obs = _corridor(rng)
    T_noisy, pts_noisy = _perturbed(rng, T_true, pts, 0.002, 0.005, 0.01)
    obs = np.column_stack([obs, rng.uniform(0.5, 1.0, len(obs))])
    packed = compact_observations(obs[:, 0].astype(int), obs[:, 1].astype(int), obs[:, 2].astype(np.uint8),
                                  obs[:, 3:5], obs[:, 5])
    assert packed.nbytes < 0.45 * obs.nbytes
    cfg = BAConfig(disparity_offset=False)
    wide = windowed_ba.adjust_in_windows(rig, BAProblem(T_noisy, pts_noisy, obs), cfg)
    widen, widened_rows = ba_common.widened, []

    def counting(rows):
        widened_rows.append(len(rows))
        return widen(rows)

    monkeypatch.setattr(ba_common, "widened", counting)
    slim = windowed_ba.adjust_in_windows(rig, BAProblem(T_noisy, pts_noisy, packed), cfg)
    assert len(widened_rows) >= 2 and max(widened_rows) < 0.8 * len(packed)  # a window's rows at a time
    moved = [np.linalg.norm(slim.T_world_cam[k][:3, 3] - wide.T_world_cam[k][:3, 3]) for k in range(len(T_true))]
    assert max(moved) < 1e-5 and slim.n_obs == wide.n_obs


def test_compact_observations_round_trip_and_reject_what_does_not_fit():
    rows = np.array([[3, 70000, 1, 512.25, 300.125, 0.75], [0, 2, 0, 10.5, 20.0, 1.0]])
    packed = compact_observations(rows[:, 0].astype(int), rows[:, 1].astype(int), rows[:, 2].astype(np.uint8),
                                  rows[:, 3:5], rows[:, 5])
    assert np.array_equal(as_observations(packed), rows)  # these values are exact in float32
    assert np.array_equal(observation_keyframes(packed), [3, 0])
    with pytest.raises(EstimationError, match="point ids"):
        compact_observations(np.zeros(1, int), np.array([2**31]), np.zeros(1, np.uint8), np.zeros((1, 2)), np.ones(1))
    with pytest.raises(EstimationError, match="keyframe index"):
        compact_observations(np.array([-1]), np.zeros(1, int), np.zeros(1, np.uint8), np.zeros((1, 2)), np.ones(1))
    other = np.zeros(2, [("kf", "<i4"), ("u", "<f4")])
    with pytest.raises(EstimationError, match="fields"):
        as_observations(other)


def test_relative_pose_sigmas_follow_the_points_and_floor_the_pixel_noise():
    from stereopath.host.backend.loops import MIN_RELATIVE_PIXEL_SIGMA, relative_pose_sigmas

    s_rot, s_t = relative_pose_sigmas(500.0, 0.1, 100, 2.0)  # 0.1 px is below the floor
    assert s_rot == pytest.approx(2 * MIN_RELATIVE_PIXEL_SIGMA / 500.0 / 10.0) and s_t == pytest.approx(2.0 * s_rot)
    assert relative_pose_sigmas(500.0, 0.6, 400, 2.0)[0] == pytest.approx(s_rot)  # twice the noise, four times the points


def test_chain_sigmas_weigh_consecutive_keyframes_by_the_points_they_share():
    from stereopath.host.backend.loops import relative_pose_sigmas

    rng = np.random.default_rng(21)
    rig, T_true, pts, obs = _corridor(rng, n_kf=12, n_pts=300)
    keep = ~((obs[:, 0] == 6) & (obs[:, 2] == 0) & (obs[:, 1] > 4))  # keyframe 6's left image: a few points only
    obs = obs[keep]
    kfs = obs[:, 0].astype(int)
    sig = windowed_ba.chain_sigmas(rig, obs, kfs, T_true, pts, 0.3)
    assert sig.shape == (11, 2) and np.isnan(sig[5]).all() and np.isnan(sig[6]).all()
    left = {k: set(obs[(obs[:, 0] == k) & (obs[:, 2] == 0), 1].astype(int)) for k in range(12)}
    shared = sorted(left[2] & left[3])
    depth = float(np.median([pts[i][2] for i in shared]))  # the cameras look along +z
    px = np.sqrt(2.0) * 0.3  # the adjustment's per-coordinate figure as a loop's 2D error
    assert sig[2] == pytest.approx(relative_pose_sigmas(rig.cam0.K[0, 0], px, len(shared), depth))
    # the whole scene turned: the depths along the turned optical axes are the same
    R = so3_exp(np.array([0.3, -0.5, 0.2]))
    turn = make_pose(R, [0.4, -0.2, 1.0])
    turned = windowed_ba.chain_sigmas(rig, obs, kfs, np.einsum("ij,njk->nik", turn, T_true),
                                      {i: R @ X + turn[:3, 3] for i, X in pts.items()}, 0.3)
    assert np.allclose(turned, sig, equal_nan=True)
    behind = windowed_ba.chain_sigmas(rig, obs, kfs, T_true, {i: -X for i, X in pts.items()}, 0.3)
    assert np.isnan(behind).all()  # points behind the cameras give no weight
    packed = compact_observations(obs[:, 0].astype(int), obs[:, 1].astype(int), obs[:, 2].astype(np.uint8),
                                  obs[:, 3:5], np.ones(len(obs)))
    assert np.array_equal(windowed_ba.chain_sigmas(rig, packed, kfs, T_true, pts, 0.3), sig, equal_nan=True)


def test_after_the_windows_the_loops_pull_the_first_windows_too(small_windows, monkeypatch):
    """Windows that leave a path bent along its length (the later windows held onto the earlier ones)
    and a loop measuring its true end: the last pass, on the consecutive keyframes' shared-point
    weights, moves the end most of the way back and holds the first keyframe; the points follow their
    keyframes back towards the truth."""
    from stereopath.host.backend import gtsam_ba

    rng = np.random.default_rng(16)
    rig, T_true, pts, obs = _corridor(rng, n_pts=300)
    bend = np.array([make_pose(np.eye(3), [0.0, 0.0, 0.0004 * k]) for k in range(40)])  # 1.6 cm at the end
    T_bent = np.einsum("nij,njk->nik", bend, T_true)
    kf_first = {int(i): int(obs[obs[:, 1] == i, 0].min()) for i in np.unique(obs[:, 1])}
    bent_pts = {i: bend[k][:3, :3] @ pts[i] + bend[k][:3, 3] for i, k in kf_first.items()}

    def windows_as_bent(rig, problem, config, priors, prog, w, s, kfs):
        e = min(len(prog.T), s + windowed_ba.WINDOW)
        prog.T[s:e] = T_bent[s:e]
        prog.points.update(bent_pts)
        prog.adjusted.update(bent_pts)
        prog.figures.append((0.5, 0.3, 1.0, int(np.sum((kfs >= s) & (kfs < e)))))
        prog.history += [1.0, 0.5]

    monkeypatch.setattr(windowed_ba, "_adjust_window", windows_as_bent)
    graphs, solve = [], gtsam_ba.pose_graph

    def spy(T, loops, *args, edge_sigmas=None, **kwargs):
        graphs.append(edge_sigmas)
        return solve(T, loops, *args, edge_sigmas=edge_sigmas, **kwargs)

    monkeypatch.setattr(gtsam_ba, "pose_graph", spy)
    loop = Loop(2, 39, invert_pose(T_true[2]) @ T_true[39], 300, 300, 1e-4, 2e-4, 0.0)
    res = windowed_ba.adjust_in_windows(rig, BAProblem(T_bent, pts, obs, [loop]), BAConfig(disparity_offset=False))
    off_before = np.linalg.norm(T_bent[39][:3, 3] - T_true[39][:3, 3])
    off_after = np.linalg.norm(res.T_world_cam[39][:3, 3] - T_true[39][:3, 3])
    assert off_after < 0.3 * off_before
    assert np.allclose(res.T_world_cam[0], T_bent[0], atol=1e-6)
    last = graphs[-1]  # the first pose graph closes the loops before the windows, the last one after them
    assert last is not None and np.isfinite(last).all() and np.all(last > 0)
    ids = sorted(bent_pts)
    off_pts = [np.median([np.linalg.norm(P[i] - pts[i]) for i in ids]) for P in (bent_pts, res.points)]
    assert off_pts[1] < 0.5 * off_pts[0]  # unmoved they would stay where the bend put them
    # no loop, or one window: the windows' path as it is
    plain = windowed_ba.adjust_in_windows(rig, BAProblem(T_bent, pts, obs), BAConfig(disparity_offset=False))
    assert np.array_equal(plain.T_world_cam, T_bent)
