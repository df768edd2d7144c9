"""The device's world rebase on the host: poses held before it mapped once, later arrivals mapped, recorded."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stereopath.device.core.geometry import euler_xyz_to_matrix, make_pose
from stereopath.device.formats.tum import read_tum
from stereopath.device.wire.protocol import make_rebase, pose_from_matrix
from stereopath.host.live.world_rebase import REBASE_JSON, SessionRebases, read_rebases, record, rewrite_tum
from tests.device.test_streaming_support import make_device, small_images, wait_for
from tests.host.test_streaming_integration import _receiver

pytestmark = pytest.mark.timeout(60)
G = make_pose(euler_xyz_to_matrix(np.radians([8.0, -20.0, 35.0])), [0.3, -0.2, 0.1])


def _T(i: int) -> np.ndarray:
    return make_pose(euler_xyz_to_matrix(np.radians([0.5 * i, 1.0 * i, 0.0])), [0.01 * i, 0.002 * i, -0.003 * i])


def _t(i: int) -> int:
    return 1_000_000 + i * 50_000_000


def test_session_rebases_apply_once_and_map_poses_timed_before():
    rb = SessionRebases()
    msg = make_rebase("s1", _t(10), G)
    first = rb.add(msg)
    assert first is not None and rb.add(msg) is None  # the device repeats it: applied once
    early, late = pose_from_matrix("s1", 3, _t(3), _T(3)), pose_from_matrix("s1", 12, _t(12), G @ _T(12))
    np.testing.assert_allclose(rb.map_pose(early).T_world_cam, G @ _T(3), atol=1e-6)
    assert rb.map_pose(late) is late
    other = pose_from_matrix("s2", 3, _t(3), _T(3))
    assert rb.map_pose(other) is other  # another session's world is its own


def test_tum_rewrite_and_record_round_trip(tmp_path):
    from stereopath.device.formats.tum import Trajectory, write_tum

    path = tmp_path / "poses.tum"
    write_tum(path, Trajectory(np.array([_t(i) for i in range(20)]), np.stack([_T(i) for i in range(20)])))
    rb = SessionRebases()
    r = rb.add(make_rebase("s1", _t(10), G))
    assert rewrite_tum(path, r) == 10
    traj = read_tum(path)
    expect = np.stack([G @ _T(i) if i < 10 else _T(i) for i in range(20)])
    np.testing.assert_allclose(traj.T_world_cam, expect, atol=1e-5)
    record(tmp_path, rb.of("s1"))
    back = read_rebases(tmp_path)
    assert len(back) == 1 and back[0].from_t_ns == _t(10) and back[0].same(r)
    (tmp_path / REBASE_JSON).write_text(json.dumps({"rebases": [{"from_t_ns": 1, "T_new_old": [[1, 0], [0, 1]]}]}))
    from stereopath.device.errors import DatasetError

    with pytest.raises(DatasetError, match="4x4"):
        read_rebases(tmp_path)


def test_the_host_holds_one_world_after_the_device_rebases(tmp_path):
    """Poses 0-9 are streamed in the first camera's world, then the device levels its world (rebase from
    pose 10's time) and streams 10-29 in the new one: the host's poses.tum and live pose end in the new
    world for every pose, the rebase applied once although the device repeats it with every status."""
    dev = make_device(tmp_path, None, "sessR")
    rx = _receiver(dev, None, tmp_path / "out")
    seen, kfs = [], []
    rx.on_rebase = seen.append
    rx.on_keyframe = lambda kf, new: kfs.append(kf)
    try:
        assert wait_for(lambda: rx.live.connected, 5, between=lambda: rx.poll(0.02))
        wait_for(lambda: False, 0.3, between=lambda: rx.poll(0.02))  # let the SUB subscription propagate
        for i in range(10):
            dev.publish_pose(i, _t(i), _T(i))
            rx.poll(0.01)
        assert wait_for(lambda: rx.stats.received.pose >= 8, 5, between=lambda: rx.poll(0.02))
        dev.publish_rebase(_t(10), G)
        for i in range(10, 30):
            dev.publish_pose(i, _t(i), G @ _T(i))
            rx.poll(0.01)
        assert wait_for(lambda: rx.stats.received.rebase >= 1, 10, between=lambda: rx.poll(0.02))
        # a keyframe of the earlier world that reaches the host after the rebase (a resend, a late host)
        assert dev.offer_keyframe(5, _t(5), _T(5), *small_images(5))
        # repeated with every status (0.2 s here): seen several times, applied once
        assert wait_for(lambda: rx.stats.received.rebase >= 3, 10, between=lambda: rx.poll(0.02))
        wait_for(lambda: False, 0.3, between=lambda: rx.poll(0.02))
        live = rx.live.pose
    finally:
        rx.close()
        dev.close()
    assert len(seen) == 1 and seen[0].from_t_ns == _t(10)
    assert len(kfs) == 1 and np.allclose(kfs[0].T_world_cam, G @ _T(5), atol=1e-5)  # shown in the new world
    traj = read_tum(tmp_path / "out" / "sessR" / "poses.tum")
    idx = [int(round((t - _t(0)) / 50_000_000)) for t in traj.t_ns]
    assert min(idx) < 10 <= max(idx)
    np.testing.assert_allclose(traj.T_world_cam, np.stack([G @ _T(i) for i in idx]), atol=1e-4)
    np.testing.assert_allclose(live.T_world_cam, G @ _T(int(round((live.t_ns - _t(0)) / 50_000_000))), atol=1e-4)
    rec = read_rebases(tmp_path / "out" / "sessR")
    assert len(rec) == 1 and np.allclose(rec[0].T_new_old, G, atol=1e-6)


def test_a_malformed_rebase_is_rejected_by_name(tmp_path):
    """A rebase whose motion is not rigid is refused where it is made, and one malformed on the wire is
    counted as a rejected message; the receiver carries on."""
    import msgpack

    from stereopath.device.errors import ProtocolError
    from stereopath.device.wire.protocol import KEYFRAME_LIMITS, DecodeError, decode_message, encode_rebase

    dev = make_device(tmp_path, None, "sessM")
    try:
        with pytest.raises(ProtocolError, match="rigid"):
            dev.publish_rebase(_t(1), np.diag([2.0, 1.0, 1.0, 1.0]))
    finally:
        dev.close()
    wire = msgpack.unpackb(encode_rebase(make_rebase("sessM", _t(1), G)))
    wire["q"] = [1.0, 1.0, 0.0, 0.0]
    with pytest.raises(DecodeError, match="unit quaternion"):
        decode_message(msgpack.packb(wire), KEYFRAME_LIMITS, ("keyframe", "status", "session", "rebase"))
