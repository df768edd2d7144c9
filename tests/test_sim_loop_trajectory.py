"""The `loop` trajectory of the simulator: turns around the table and back to the start."""

from __future__ import annotations

import numpy as np

from stereopath.device.core.geometry import rotation_angle_deg
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
    assert abs(abs(az[-1] - az[0]) - 2 * np.pi * LOOP_TURNS) < 0.01
    assert tr.path_length_m(t) > 10.0
    # still at the start, moving smoothly after (velocity from the analytic derivative vs differences)
    assert np.all(tr.state(np.array([0.2, STILL_S - 0.01])).v_world == 0)
    tt = np.linspace(5.0, 6.0, 201)
    s2 = tr.state(tt)
    fd = np.gradient(s2.p_world_cam, tt, axis=0)
    assert np.abs(fd[5:-5] - s2.v_world[5:-5]).max() < 1e-3
