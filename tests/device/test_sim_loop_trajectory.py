"""The `loop` trajectory of the simulator: walks around the room, looking at its walls, and back to the start."""

from __future__ import annotations

import numpy as np

from stereopath.device.core.geometry import rotation_angle_deg
from stereopath.device.sim.scene import ROOM_HALF_M, TARGET_WORLD
from stereopath.device.sim.trajectories import LOOP_TURNS, STILL_S, default_frame_times, get_trajectory


def test_loop_returns_to_its_start_after_several_turns():
    t = default_frame_times()
    tr = get_trajectory("loop", float(t[-1]))
    st = tr.state(t)
    start, end = st.T_world_cam[0], st.T_world_cam[-1]
    # only the hand shake (about 2 mm, 0.3 deg) is not periodic over the loop
    assert np.linalg.norm(end[:3, 3] - start[:3, 3]) < 0.006
    assert rotation_angle_deg(start[:3, :3].T @ end[:3, :3]) < 1.0
    # it does go around: the azimuth of the camera centre turns LOOP_TURNS times
    az = np.unwrap(np.arctan2(st.p_world_cam[:, 1], st.p_world_cam[:, 0]))
    assert LOOP_TURNS >= 2 and abs(abs(az[-1] - az[0]) - 2 * np.pi * LOOP_TURNS) < 0.01
    assert tr.path_length_m(t) > 15.0
    # still at the start, moving smoothly after (velocity from the analytic derivative vs differences)
    assert np.all(tr.state(np.array([0.2, STILL_S - 0.01])).v_world == 0)
    tt = np.linspace(5.0, 6.0, 201)
    s2 = tr.state(tt)
    fd = np.gradient(s2.p_world_cam, tt, axis=0)
    assert np.abs(fd[5:-5] - s2.v_world[5:-5]).max() < 1e-3
    # a hand-held speed: at most a brisk walk and a quick turn of the wrist
    assert np.linalg.norm(st.v_world, axis=1).max() < 1.5
    assert np.degrees(np.linalg.norm(st.omega_cam, axis=1)).max() < 90.0


def test_loop_walks_the_room_looking_at_its_walls():
    """Room-sized, facing away from the table most of the time (what makes the on-board path drift
    more than on turns around the table, where it keeps seeing the same close objects), and every
    turn comes back past the start in the same direction (loop closure candidates)."""
    t = default_frame_times()
    st = get_trajectory("loop", float(t[-1])).state(t)
    p = st.p_world_cam
    wall_gap = ROOM_HALF_M - np.abs(p[:, :2]).max(axis=1)
    assert wall_gap.min() > 0.35 and wall_gap.min() < 0.6
    forward = st.R_world_cam[:, :, 2]
    to_table = TARGET_WORLD - p
    cos = np.sum(forward * to_table, axis=1) / np.linalg.norm(to_table, axis=1)
    assert np.mean(cos < np.cos(np.radians(45.0))) > 0.8
    az = np.unwrap(np.arctan2(p[:, 1], p[:, 0]))
    first_return = int(np.argmax(np.abs(az - az[0]) >= 2 * np.pi))
    assert 0 < first_return < len(t) - 1
    assert np.linalg.norm(p[first_return] - p[0]) < 0.3
    assert rotation_angle_deg(st.R_world_cam[0].T @ st.R_world_cam[first_return]) < 35.0
