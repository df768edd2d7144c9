"""host live --map: keyframes fused as they arrive, mesh refreshed, full model at the end."""

import numpy as np
import pytest

from stereopath.device.core.geometry import matrix_to_quat_xyzw
from stereopath.device.wire.protocol import Keyframe, decode_keyframe, encode_image, encode_keyframe, rig_reference
from stereopath.device.core.rig import paper_rig
from stereopath.host.live.live_map import LiveMapper
from stereopath.device.formats.source import open_source


def _keyframes(seq, rig, step=4, n=6, session="s1"):
    name, h = rig_reference(rig)
    out = []
    for k, i in enumerate(range(30, 30 + step * n, step)):
        f = seq.render(i)
        T = f.meta["T_world_cam0"]
        kf = Keyframe(session, k, i, f.t_ns, tuple(T[:3, 3]), tuple(matrix_to_quat_xyzw(T[:3, :3])),
                      encode_image(f.left, "png"), encode_image(f.right, "png"), name, h)
        out.append(decode_keyframe(encode_keyframe(kf)))  # exactly what the receiver hands over
    return out


@pytest.mark.slow
def test_live_mapper_fuses_refreshes_and_writes_the_model(tmp_path):
    seq = open_source("sim:0", frames=60)
    kfs = _keyframes(seq, seq.rig)
    refreshed = []
    m = LiveMapper(seq.rig, tmp_path, every=2, on_mesh=lambda s, mesh: refreshed.append(len(mesh.vertices)))
    for kf in kfs:
        m.on_keyframe(kf, True)
    m.on_keyframe(kfs[0], False)  # a duplicate is not fused twice
    models = m.close()
    assert m.fused == 6 and m.rejected == 0
    assert m.refreshes == len(refreshed) >= 1 and min(refreshed) > 1000
    assert refreshed == sorted(refreshed)  # the model grows as keyframes arrive
    model = models["s1"]
    for name in ("mesh.ply", "cloud.ply", "model.png", "map.json"):
        assert (model / name).stat().st_size > 0


def test_live_mapper_rejects_keyframes_of_another_rig(tmp_path):
    seq = open_source("sim:0", frames=40)
    kfs = _keyframes(seq, paper_rig(), n=2)  # the rig without the IMU extrinsics: another hash
    m = LiveMapper(seq.rig, tmp_path, every=1)
    for kf in kfs:
        m.on_keyframe(kf, True)
    assert m.close() == {}
    assert m.rejected == 2 and m.fused == 0
    assert not (tmp_path / "s1").exists()


def _drifting_loop_keyframes(frames=range(11, 50, 4)):
    """Keyframes of the simulated `loop` path (a walk around the room, fused with the `room` preset)
    up to its first return to the start (90-frame version: the first turn ends near frame 47), sent
    with a drift that grows along the path (up to 1.5 deg about the vertical and 15 mm), as an
    on-board estimate would; (keyframes, true poses, sent poses)."""
    from stereopath.device.core.geometry import make_pose, so3_exp
    from stereopath.device.sim.session import SimConfig, open_sim

    seq = open_sim(SimConfig(trajectory="loop", frames=90))
    name, h = rig_reference(seq.rig)
    frames = list(frames)
    kfs, T_true, T_sent = [], [], []
    for k, i in enumerate(frames):
        f = seq.render(i)
        T = f.meta["T_world_cam0"]
        a = k / (len(frames) - 1)
        Ts = make_pose(so3_exp([0, 0, np.radians(1.5) * a]), [0.012 * a, -0.008 * a, 0.004 * a]) @ T
        T_true.append(T)
        T_sent.append(Ts)
        kfs.append(decode_keyframe(encode_keyframe(Keyframe(
            "s", k, i, f.t_ns, tuple(Ts[:3, 3]), tuple(matrix_to_quat_xyzw(Ts[:3, :3])),
            encode_image(f.left, "png"), encode_image(f.right, "png"), name, h))))
    return seq.rig, kfs, np.array(T_true), np.array(T_sent)


def _mean_distance(mesh_a, mesh_b) -> float:
    """Mean distance from mesh_a's vertices to the nearest vertex of mesh_b."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(np.asarray(mesh_b.vertices)).query(np.asarray(mesh_a.vertices))
    return float(np.mean(d))


@pytest.mark.slow
def test_a_loop_closed_while_scanning_is_in_the_next_mesh(tmp_path):
    from stereopath.host.backend.loops import LoopConfig

    rig, kfs, T_true, T_sent = _drifting_loop_keyframes()
    refreshes = []  # (keyframes fused, loops closed, mesh) at each refresh
    m = LiveMapper(rig, tmp_path, every=1000, preset="room", loops=LoopConfig(min_separation=5),
                   on_mesh=lambda s, mesh: refreshes.append((m.fused, m.loops_closed, mesh)))
    for kf in kfs:
        m.on_keyframe(kf, True)
    models = m.close()
    closer, mapper = m._closers["s"], m._mappers["s"]
    assert m.fused == len(kfs) and m.loops_closed == len(closer.loops) >= 1
    first = closer.loops[0]
    assert first.j - first.i > 5 and np.linalg.norm(T_true[first.i, :3, 3] - T_true[first.j, :3, 3]) < 0.3
    # with `every` this large, refreshes come from closed loops only, each with the keyframe that closed it
    assert [n for n, _, _ in refreshes] == [lp.j + 1 for lp in closer.loops]
    assert [c for _, c, _ in refreshes] == list(range(1, len(closer.loops) + 1))
    # the fused keyframes were re-posed: the end of the path is back near the truth
    P = np.array(mapper.poses)
    err_sent = np.linalg.norm(T_sent[:, :3, 3] - T_true[:, :3, 3], axis=1)
    err_fused = np.linalg.norm(P[:, :3, 3] - T_true[:, :3, 3], axis=1)
    assert err_fused[-1] < 0.5 * err_sent[-1]
    assert mapper.reposed == len(closer.loops)
    # ... and the refreshed mesh is the re-integrated one: closer to the model fused at the true poses
    # than the model fused at the drifting poses is
    mesh_loop = refreshes[-1][2]
    mapper.repose(T_true)
    truth = mapper.mesh()
    mapper.repose(T_sent)
    drifting = mapper.mesh()
    assert _mean_distance(mesh_loop, truth) < 0.7 * _mean_distance(drifting, truth)
    assert (models["s"] / "mesh.ply").stat().st_size > 0


@pytest.mark.parametrize("loops", [False, True])
def test_a_world_rebase_moves_what_was_fused_before_it(tmp_path, loops):
    """A device started in motion levels its world once gravity is known: the keyframes it sent before
    came in the earlier world.  After the rebase the fused keyframes are where the later ones put them,
    and the model is the one fused at those poses throughout."""
    from stereopath.device.core.geometry import invert_pose, make_pose, so3_exp
    from stereopath.device.wire.messages import WorldRebase

    seq = open_source("sim:0", frames=60)
    kfs = _keyframes(seq, seq.rig)
    T_true = np.array([kf.T_world_cam for kf in kfs])
    A = make_pose(so3_exp([0.05, -0.12, 0.3]), [0.1, -0.05, 0.02])  # T_new_old: the levelling turn
    before = [
        Keyframe(kf.session_id, kf.seq, kf.frame_seq, kf.t_ns, tuple((invert_pose(A) @ T)[:3, 3]),
                 tuple(matrix_to_quat_xyzw((invert_pose(A) @ T)[:3, :3])), kf.left, kf.right, kf.rig_name, kf.rig_hash)
        for kf, T in zip(kfs[:4], T_true[:4])]
    q = matrix_to_quat_xyzw(A[:3, :3])
    rebase = WorldRebase("s1", kfs[4].t_ns, tuple(A[:3, 3]), tuple(q))
    shown = []
    m = LiveMapper(seq.rig, tmp_path, every=1000, loops=loops, on_mesh=lambda s, mesh: shown.append(mesh))
    for kf in before:
        m.on_keyframe(kf, True)
    m.on_rebase(rebase)
    for kf in kfs[4:]:
        m.on_keyframe(kf, True)
    m.on_rebase(WorldRebase("other", kfs[4].t_ns, tuple(A[:3, 3]), tuple(q)))  # no model of that session
    models = m.close()
    mapper = m._mappers["s1"]
    assert m.fused == 6 and m.rebased == 1 and mapper.reposed == 1
    assert np.allclose(np.array(mapper.poses), T_true, atol=1e-6)
    assert len(shown) == 1  # shown at once in the new world
    moved = mapper.mesh()
    mapper.repose(T_true)  # the model fused at the new world's poses throughout
    truth = mapper.mesh()
    assert len(moved.vertices) == len(truth.vertices) > 1000
    assert _mean_distance(moved, truth) < 1e-5
    # the mesh shown at the rebase (four keyframes) lies on the model, not where the earlier world had it
    import open3d as o3d

    old = o3d.geometry.TriangleMesh(shown[0]).transform(invert_pose(A))
    assert _mean_distance(shown[0], truth) < 0.1 * _mean_distance(old, truth)
    assert (models["s1"] / "mesh.ply").stat().st_size > 0
