"""Simulator trajectories and IMU: exact derivatives, gyro/accel truth, MPU-6050 noise, quantisation."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.errors import ConfigError
from stereopath.device.core.frames import ImuSamples
from stereopath.device.core.geometry import invert_pose, rotation_angle_deg, so3_exp, so3_log
from stereopath.device.sim.imu import (
    ACCEL_LSB_PER_G, G_M_S2, GYRO_LSB_PER_DPS, T_BODY_CAM0, ImuNoiseModel, counts_to_si, measure,
)
from stereopath.device.sim.session import open_sim
from stereopath.device.sim.trajectories import (
    DEFAULT_DURATION_S, STILL_S, TRAJECTORIES, default_frame_times, get_trajectory,
)


@pytest.mark.parametrize("name", sorted(TRAJECTORIES))
def test_analytic_derivatives_match_finite_differences(name):
    if name == "handheld":
        from stereopath.device.sim.handheld import motion_file

        try:
            motion_file()
        except ConfigError:
            pytest.skip("the recorded flight (shared data trajectories/V101_gt.txt) is not available")
    tr = get_trajectory(name, DEFAULT_DURATION_S, seed=3)
    t = np.linspace(0.05, DEFAULT_DURATION_S - 0.05, 301)
    h = 1e-5
    s, sp, sm = tr.state(t), tr.state(t + h), tr.state(t - h)
    assert np.allclose((sp.p_world_cam - sm.p_world_cam) / (2 * h), s.v_world, atol=1e-7)
    assert np.allclose((sp.v_world - sm.v_world) / (2 * h), s.a_world, atol=1e-6)
    w_fd = np.array([so3_log(a.T @ b) for a, b in zip(sm.R_world_cam, sp.R_world_cam)]) / (2 * h)
    assert np.allclose(w_fd, s.omega_cam, atol=1e-7)
    assert np.allclose((sp.omega_cam - sm.omega_cam) / (2 * h), s.alpha_cam, atol=1e-6)
    R = s.R_world_cam
    assert np.allclose(np.einsum("nji,njk->nik", R, R), np.eye(3), atol=1e-12)


def test_default_arc_is_the_papers_5120_mm_with_a_still_start():
    tr = get_trajectory("arc")
    t = default_frame_times()
    assert len(t) == 400 and t[0] == 1.0 and t[-1] == pytest.approx(DEFAULT_DURATION_S)
    assert tr.path_length_m(t) == pytest.approx(5.12, abs=1e-3)
    still = tr.state(np.linspace(0.0, STILL_S, 50))
    assert np.all(still.v_world == 0) and np.all(still.omega_cam == 0) and np.all(still.a_world == 0)
    s = tr.state(np.linspace(STILL_S + 0.5, DEFAULT_DURATION_S - 0.5, 2000))
    assert np.all(np.linalg.norm(s.v_world, axis=1) > 0.05)  # it keeps moving, handheld speed
    assert np.max(np.linalg.norm(s.v_world, axis=1)) < 0.6
    # the camera looks at the objects: the table centre stays in front of it and mostly in view
    target = np.array([0.0, 0.0, 0.85])
    Xc = np.einsum("nji,nj->ni", s.R_world_cam, target - s.p_world_cam)
    assert np.all(Xc[:, 2] > 0.4) and np.all(Xc[:, 2] < 1.8)
    ang = np.degrees(np.arctan2(np.linalg.norm(Xc[:, :2], axis=1), Xc[:, 2]))
    assert np.percentile(ang, 90) < 30
    # camera-frame excursions reach about 20-30 deg about every axis (relative to looking at the target)
    shape = tr.shape
    g = np.linspace(0, tr.law.g_end, 3000)
    peaks = [np.degrees(np.max(np.abs(e(g)[0]))) for e in shape.exc]
    assert all(18 < p < 32 for p in peaks) and max(peaks) > 28


def test_other_trajectories_and_unknown_name():
    orbit = get_trajectory("orbit", 12.0)
    p = orbit.state(np.array([STILL_S, 12.0])).p_world_cam
    assert np.allclose(p[0], p[1], atol=0.01)  # a full circle
    line = get_trajectory("line", 10.0, seed=1)
    a, b = line.state(np.array([0.5, 10.0])).p_world_cam
    assert abs(np.linalg.norm(b - a) - 1.0) < 0.01
    still = get_trajectory("still", 5.0)
    st = still.state(np.linspace(0, 5, 20))
    assert np.all(st.v_world == 0) and np.all(st.omega_cam == 0)
    with pytest.raises(ConfigError, match="spiral"):
        get_trajectory("spiral", 5.0)


def _integrate_gyro(imu: ImuSamples, R0: np.ndarray) -> np.ndarray:
    dt = np.diff(imu.t_ns) * 1e-9
    w_mid = 0.5 * (imu.gyro_rad_s[1:] + imu.gyro_rad_s[:-1])
    Rs = [R0]
    for k in range(len(dt)):
        Rs.append(Rs[-1] @ so3_exp(w_mid[k] * dt[k]))
    return np.array(Rs)


def test_integrated_truth_gyro_reproduces_the_trajectory_rotation():
    sess = open_sim()  # the full default arc: 20.95 s of IMU at 200 Hz
    R_cb = invert_pose(sess.rig.T_body_cam0)[:3, :3]
    imu = sess.imu_truth
    R_wb0 = sess.trajectory.pose(0.0)[:3, :3] @ R_cb
    R_wb = _integrate_gyro(imu, R_wb0)
    idx = np.searchsorted(imu.t_ns, sess.t_ns)
    assert np.array_equal(imu.t_ns[idx], sess.t_ns)  # every frame time is an IMU sample time
    errs = [rotation_angle_deg((gt[:3, :3] @ R_cb).T @ R_wb[k]) for k, gt in zip(idx, sess.groundtruth.T_world_cam)]
    assert max(errs) < 0.05
    # and the motion is substantial (so the check is meaningful)
    R0 = sess.groundtruth.T_world_cam[0][:3, :3]
    assert max(rotation_angle_deg(R0.T @ T[:3, :3]) for T in sess.groundtruth.T_world_cam) > 150


def test_integrated_truth_accelerometer_reproduces_the_body_path():
    sess = open_sim(frames=120)
    imu = sess.imu_truth
    T_cb = invert_pose(sess.rig.T_body_cam0)
    st = sess.trajectory.state(imu.t_ns * 1e-9)
    R_wb = st.R_world_cam @ T_cb[:3, :3]
    p_wb = st.p_world_cam + st.R_world_cam @ T_cb[:3, 3]
    a_w = np.einsum("nij,nj->ni", R_wb, imu.accel_m_s2) + sess.gravity_world
    dt = np.diff(imu.t_ns) * 1e-9
    v = np.concatenate([[np.zeros(3)], np.cumsum(0.5 * (a_w[1:] + a_w[:-1]) * dt[:, None], axis=0)])
    p = p_wb[0] + np.concatenate([[np.zeros(3)], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt[:, None], axis=0)])
    assert np.max(np.linalg.norm(p - p_wb, axis=1)) < 2e-3  # 6.95 s of double integration
    assert np.max(np.linalg.norm(p_wb - p_wb[0], axis=1)) > 0.3
    # at rest the accelerometer reads +g along "up"
    f0 = imu.accel_m_s2[0]
    assert np.linalg.norm(f0) == pytest.approx(9.81, abs=1e-9)
    assert np.allclose(R_wb[0] @ f0, [0, 0, 9.81], atol=1e-9)


def test_body_frame_is_forward_left_up_of_the_camera():
    R_bc = T_BODY_CAM0[:3, :3]
    assert np.allclose(R_bc @ [0, 0, 1], [1, 0, 0])   # camera forward = body x
    assert np.allclose(R_bc @ [-1, 0, 0], [0, 1, 0])  # camera left = body y
    assert np.allclose(R_bc @ [0, -1, 0], [0, 0, 1])  # camera up = body z
    assert np.allclose(invert_pose(T_BODY_CAM0)[:3, 3], [0.024, 0.015, -0.010])  # IMU position in cam0


def test_noise_statistics_match_the_datasheet_densities():
    sess = open_sim(trajectory="still", frames=1200, seed=5)  # 60 s at rest, 12000 samples
    imu, truth, rate = sess.imu, sess.imu_truth, sess.cfg.imu.rate_hz
    model = sess.imu_model
    assert len(imu) > 11000
    # first differences remove the (slowly varying) bias; quantisation adds LSB^2/12 per sample
    for meas, tru, density, lsb in (
        (imu.gyro_rad_s, truth.gyro_rad_s, np.radians(0.005), 1 / model.gyro_lsb_per_rad_s),
        (imu.accel_m_s2, truth.accel_m_s2, 400e-6 * 9.81, 1 / model.accel_lsb_per_m_s2),
    ):
        e = meas - tru
        var = np.var(np.diff(e, axis=0), axis=0) / 2 - lsb**2 / 12
        sigma = np.sqrt(var)
        expected = density * np.sqrt(rate)
        assert np.all(np.abs(sigma / expected - 1) < 0.10), (sigma, expected)
    # the biases are there, constant plus a slow walk
    gb = sess.imu_biases.gyro_rad_s
    assert np.allclose(np.mean(imu.gyro_rad_s - truth.gyro_rad_s, axis=0), gb.mean(axis=0), atol=3e-5)
    assert np.max(np.abs(gb[-1] - gb[0])) < 0.01


def test_quantisation_scales_and_clipping():
    t = np.arange(5, dtype=np.int64) * 5_000_000
    gyro = np.array([[0.0, 0.0, 0.0], [np.radians(1.0), 0, 0], [np.radians(600.0), 0, 0], [-np.radians(600.0), 0, 0],
                     [0, 0, 0]])
    acc = np.array([[0, 0, G_M_S2], [G_M_S2, 0, 0], [5 * G_M_S2, 0, 0], [-5 * G_M_S2, 0, 0], [0, 0, 0]])
    truth = ImuSamples(t, gyro, acc)
    meas, raw, _ = measure(truth, ImuNoiseModel(gyro_fs_dps=500, accel_fs_g=4), noise=False, rate_hz=200.0)
    assert raw.gyro.dtype == np.int16 and raw.accel.dtype == np.int16
    assert raw.gyro[1, 0] == round(GYRO_LSB_PER_DPS[500])  # 65.5 -> 66 counts for 1 deg/s
    assert raw.accel[0, 2] == ACCEL_LSB_PER_G[4] and raw.accel[1, 0] == 8192
    assert raw.gyro[2, 0] == 32767 and raw.gyro[3, 0] == -32768  # beyond +-500 deg/s: clipped
    assert raw.accel[2, 0] == 32767 and raw.accel[3, 0] == -32768
    back = counts_to_si(raw)
    assert np.array_equal(back.gyro_rad_s, meas.gyro_rad_s) and np.array_equal(back.accel_m_s2, meas.accel_m_s2)
    assert np.max(np.abs(meas.gyro_rad_s[:2] - gyro[:2])) <= 0.5 / (65.5 * 180 / np.pi) + 1e-12
    with pytest.raises(ConfigError, match="gyro_fs_dps"):
        ImuNoiseModel(gyro_fs_dps=300)


def test_session_imu_is_the_raw_counts_and_covers_one_second_before_the_first_frame():
    sess = open_sim(frames=40, imu={"gyro_fs_dps": 1000, "accel_fs_g": 8})
    assert sess.imu.t_ns[0] == sess.t_ns[0] - 1_000_000_000 == 0
    assert sess.imu.t_ns[-1] == sess.t_ns[-1]
    assert np.all(np.diff(sess.imu.t_ns) == 5_000_000)
    assert np.array_equal(sess.imu.t_ns, sess.imu_truth.t_ns)
    assert sess.imu_raw.gyro_lsb_per_dps == 32.8 and sess.imu_raw.accel_lsb_per_g == 4096
    assert np.array_equal(counts_to_si(sess.imu_raw).gyro_rad_s, sess.imu.gyro_rad_s)
    assert np.allclose(sess.gravity_world, [0, 0, -9.81])
