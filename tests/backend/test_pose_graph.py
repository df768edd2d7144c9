"""The live map's incremental pose graph (iSAM2) against the batch pose graph and the true optimum."""

import numpy as np
import pytest

from stereopath.device.core.geometry import invert_pose, make_pose, so3_exp
from stereopath.host.backend.pose_graph import LivePoseGraph
from stereopath.host.backend import gtsam_ba
from stereopath.host.backend.loops import Loop

pytest.importorskip("gtsam")


def _walk(n, turns=2, r=1.5):
    """Two turns around a table, looking inwards."""
    a = 2 * np.pi * turns * np.arange(n) / n
    return np.array([make_pose(so3_exp([0, -x, 0]), [r * np.sin(x), 0.0, r * np.cos(x)]) for x in a])


def _drifted(T, rng, rot=2e-3, trans=2e-3):
    """The path as an on-board estimate reports it: each relative motion a little off."""
    out = [T[0].copy()]
    for k in range(1, len(T)):
        noise = make_pose(so3_exp(rng.normal(0, rot, 3)), rng.normal(0, trans, 3))
        out.append(out[-1] @ invert_pose(T[k - 1]) @ T[k] @ noise)
    return np.array(out)


def _loops(T_true, every):
    """Loops from each keyframe of the first turn to the same place one turn later (true relative pose)."""
    half = len(T_true) // 2
    return [Loop(i, i + half, invert_pose(T_true[i]) @ T_true[i + half], 100, 200, 1e-3, 2e-3, 0.0)
            for i in range(0, len(T_true) - half, every)]


def _optimum(T, loops):
    """The batch pose graph solved to machine precision."""
    return gtsam_ba.pose_graph(T, loops, max_iterations=200, tol=1e-14)


def _feed(graph, T_on, loops):
    """Keyframes in arrival order, each loop as soon as its later keyframe has arrived."""
    by_j = {}
    for lp in loops:
        by_j.setdefault(lp.j, []).append(lp)
    for k, T in enumerate(T_on):
        graph.add(T)
        for lp in by_j.get(k, []):
            graph.add_loop(lp)


def test_without_loops_the_poses_are_the_onboard_ones():
    T_on = _drifted(_walk(40), np.random.default_rng(0))
    g = LivePoseGraph()
    for T in T_on:
        g.add(T)
    assert len(g) == 40 and g.loops == []
    assert np.allclose(g.poses(), T_on, atol=1e-12)


@pytest.mark.parametrize("n", [60, 400])
def test_loops_solved_incrementally_reach_the_batch_optimum(n):
    rng = np.random.default_rng(n)
    T_true = _walk(n)
    T_on = _drifted(T_true, rng)
    loops = _loops(T_true, max(1, n // 12))
    g = LivePoseGraph()
    _feed(g, T_on, loops)
    P = g.poses()
    best = _optimum(T_on, loops)
    # iSAM2 relinearises a pose only once it moves by 3e-5: within half a millimetre of the optimum
    # (a TSDF voxel is 4 mm)
    assert np.abs(P[:, :3, 3] - best[:, :3, 3]).max() < 5e-4
    assert np.abs(P[:, :3, :3] - best[:, :3, :3]).max() < 5e-4
    # and the loops did their job: the path is much closer to the truth than the on-board one
    err = lambda T: np.sqrt(np.mean(np.sum((T[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1)))
    assert err(P) < 0.8 * err(T_on)
    # the batch solution (default tolerances) is no closer by much
    assert np.abs(gtsam_ba.pose_graph(T_on, loops)[:, :3, 3] - best[:, :3, 3]).max() < 5e-4


def test_keyframes_after_the_last_loop_follow_the_corrected_one_by_their_onboard_motion():
    rng = np.random.default_rng(3)
    T_true = _walk(60)
    T_on = _drifted(T_true, rng)
    g = LivePoseGraph()
    _feed(g, T_on[:45], [lp for lp in _loops(T_true, 5) if lp.j < 45])
    before = g.poses()
    for T in T_on[45:]:
        g.add(T)
    P = g.poses()
    assert np.allclose(P[:45], before, atol=1e-12)  # nothing earlier moves without a loop
    for k in range(45, 60):
        assert np.allclose(invert_pose(P[k - 1]) @ P[k], invert_pose(T_on[k - 1]) @ T_on[k], atol=1e-9)


def test_rebuild_without_the_last_keyframe_and_its_loop_is_a_graph_that_never_had_them():
    rng = np.random.default_rng(4)
    T_true = _walk(60)
    T_on = _drifted(T_true, rng)
    loops = _loops(T_true, 5)
    g = LivePoseGraph()
    _feed(g, T_on[:56], [lp for lp in loops if lp.j < 56])
    last = max(lp.j for lp in g.loops)
    kept = [lp for lp in g.loops if lp.j < last]
    g.rebuild(T_on[:last], kept)
    fresh = LivePoseGraph()
    _feed(fresh, T_on[:last], kept)
    assert len(g) == last and len(g.loops) == len(kept)
    assert np.abs(g.poses()[:, :3, 3] - fresh.poses()[:, :3, 3]).max() < 1e-6


def test_a_world_rebase_moves_the_keyframes_before_it_and_keeps_the_loops():
    """Every keyframe sent before a rebase (here all of them, a loop among them) in the new world: the
    graph is the one that had been given the moved poses from the start."""
    rng = np.random.default_rng(5)
    T_true = _walk(60)
    T_on = _drifted(T_true, rng)
    loops = _loops(T_true, 5)
    A = make_pose(so3_exp([0.05, -0.1, 0.4]), [0.2, -0.1, 0.05])
    g = LivePoseGraph()
    _feed(g, T_on, loops)
    with pytest.raises(ValueError, match="flags"):
        g.rebase(A, np.ones(5, bool))
    g.rebase(A, np.ones(60, bool))
    fresh = LivePoseGraph()
    _feed(fresh, A @ T_on, loops)
    assert len(g.loops) == len(loops)
    assert np.abs(g.poses()[:, :3, 3] - fresh.poses()[:, :3, 3]).max() < 1e-6
    # without loops, exactly the flagged keyframes move
    h = LivePoseGraph()
    _feed(h, T_on[:10], [])
    moved = np.arange(10) < 4
    h.rebase(A, moved)
    assert np.allclose(h.poses()[:4], A @ T_on[:4], atol=1e-9) and np.allclose(h.poses()[4:], T_on[4:10], atol=1e-9)


def test_the_live_closer_forgets_a_keyframe_it_could_not_fuse_and_the_loop_it_closed():
    from stereopath.device.core.rig import paper_rig
    from stereopath.host.live.live_loops import LiveLoopCloser

    rng = np.random.default_rng(6)
    T_true = _walk(40)
    T_on = _drifted(T_true, rng)
    closer = LiveLoopCloser(paper_rig())
    loops = {lp.j: lp for lp in _loops(T_true, 4)}
    T_on = T_on[:37]  # the last keyframe (36) closes a loop
    for k, T in enumerate(T_on):  # what add() does once a keyframe's features are known
        closer.feats.append(f"features of {k}")
        closer.graph.add(T)
        if k in loops:
            closer.graph.add_loop(loops[k])
    assert closer.loops[-1].j == 36
    closer.discard_last()
    assert len(closer) == 36 and len(closer.feats) == 36 and closer.feats[-1] == "features of 35"
    assert all(lp.j < 36 for lp in closer.loops)
    expected = LivePoseGraph()
    _feed(expected, T_on[:36], [lp for lp in loops.values() if lp.j < 36])
    assert np.abs(closer.poses()[:, :3, 3] - expected.poses()[:, :3, 3]).max() < 1e-6
    closer.discard_last()  # a keyframe without a loop: the others stay where they were
    assert np.abs(closer.poses()[:, :3, 3] - expected.poses()[:35, :3, 3]).max() < 1e-6
