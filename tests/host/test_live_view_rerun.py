"""host live's rerun view: what lands on which timeline of the saved recording."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest


def test_live_mesh_is_on_the_device_time_timeline(tmp_path):
    """The mapper thread's mesh is logged at the session's latest device time (rerun's time is per thread),
    so the model shows on the timeline the poses and keyframes use, not only on log_time."""
    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader

    from stereopath.device.wire.messages import Pose
    from stereopath.host.live.view import RerunView

    rrd = tmp_path / "live.rrd"
    view = RerunView(save_path=rrd, spawn=False)
    for i in range(3):
        view.on_pose(Pose("s1", i, 1_000_000_000 + i * 50_000_000, (0.01 * i, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0),
                          inliers=200))

    class Mesh:  # the attributes mesh_arrays reads from an Open3D TriangleMesh
        vertices = np.array([[0, 0, 1], [0.1, 0, 1], [0, 0.1, 1]], float)
        triangles = np.array([[0, 1, 2]])

        @staticmethod
        def has_vertex_colors():
            return False

    worker = threading.Thread(target=view.on_mesh, args=("s1", Mesh()))  # as the live mapper's thread does
    worker.start()
    worker.join()
    view.close()
    timelines = {c.entity_path: c.timeline_names for c in RrdReader(rrd).stream() if not c.is_static}
    assert "device_time" in timelines["/world/s1/camera"]
    assert "device_time" in timelines["/world/s1/model"]
    model = next(c for c in RrdReader(rrd).stream() if c.entity_path == "/world/s1/model")
    (t,) = model.to_record_batch().column("device_time").cast("int64").to_pylist()
    assert t == 100_000_000  # the latest pose: 0.1 s after the session's first


def test_a_world_rebase_moves_the_path_shown_before_it():
    """The path and keyframe points the view holds from before the device's world rebase move into the new
    world (once, though the device repeats the message); what arrives later (the receiver maps it) stays."""
    pytest.importorskip("rerun")
    from stereopath.device.core.geometry import make_pose, so3_exp
    from stereopath.device.wire.messages import Pose
    from stereopath.device.wire.protocol import make_keyframe, make_rebase
    from stereopath.host.live.view import RerunView

    G = make_pose(so3_exp(np.array([0.1, -0.4, 0.2])), np.array([0.5, 0.0, -0.2]))
    view = RerunView(spawn=False)
    t = [1_000_000_000 + i * 50_000_000 for i in range(6)]
    for i in range(3):
        view.on_pose(Pose("s1", i, t[i], (0.1 * i, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    img = np.zeros((8, 8), np.uint8)
    kf_T = make_pose(np.eye(3), np.array([0.0, 0.2, 0.0]))
    view.on_keyframe(make_keyframe("s1", 0, 0, t[0], kf_T, (img, img), ("rig", "0123456789abcdef"), "png"), True)
    msg = make_rebase("s1", t[3], G)
    view.on_rebase(msg)
    view.on_rebase(msg)  # repeated with every status: applied once
    view.on_keyframe(make_keyframe("s1", 1, 1, t[1], G @ kf_T, (img, img), ("rig", "0123456789abcdef"), "png"), True)
    view.on_pose(Pose("s1", 4, t[4], (9.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    path = np.asarray(view._paths["s1"])
    expect = [G[:3, :3] @ np.array([0.1 * i, 0.0, 0.0]) + G[:3, 3] for i in range(3)] + [np.array([9.0, 0.0, 0.0])]
    np.testing.assert_allclose(path, np.stack(expect), atol=1e-9)
    kf_new = G[:3, :3] @ kf_T[:3, 3] + G[:3, 3]
    np.testing.assert_allclose(np.asarray(view._kf_points["s1"]), np.stack([kf_new, kf_new]), atol=1e-6)
    view.close()
