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
