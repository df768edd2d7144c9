"""IMU preintegration in the GTSAM back end: the simulator's biases recovered, the path no worse than vision only."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.core.geometry import invert_pose, make_pose, so3_exp
from stereopath.device.core.stereo import project
from stereopath.device.errors import EstimationError, ImuMismatchError
from stereopath.host.backend.imu_factors import ImuNoise, imu_terms
from tests.backend.ba_support import adjust


@pytest.fixture(scope="module")
def sim():
    """The default simulated scan's IMU and path (400 frames, 20 s; nothing is rendered)."""
    from stereopath.device.sim.session import SimConfig, open_sim

    return open_sim(SimConfig())


def _ate(T: np.ndarray, T_true: np.ndarray) -> float:
    """Position RMS after the best rigid alignment (Kabsch, no scale)."""
    P, Q = T[:, :3, 3], T_true[:, :3, 3]
    mp, mq = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((Q - mq).T @ (P - mp))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return float(np.sqrt(np.mean(np.sum(((P - mp) @ (U @ D @ Vt).T - (Q - mq)) ** 2, axis=1))))


def _visual_problem(sim, every: int = 8, per_kf: int = 25, seed: int = 0):
    """Keyframes every ``every`` frames on the true path (world = the first camera), points seen from
    them with 0.5 px noise, and the poses and points perturbed (a few mm, a few mrad)."""
    rng = np.random.default_rng(seed)
    rig = sim.rig
    kf = np.arange(0, len(sim), every)
    T0inv = invert_pose(sim.groundtruth.T_world_cam[0])
    T_true = np.array([T0inv @ T for T in sim.groundtruth.T_world_cam[kf]])
    pts = {}
    for T in T_true:
        for _ in range(per_kf):
            Xc = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.4, 0.4), rng.uniform(0.8, 1.6)])
            pts[len(pts)] = T[:3, :3] @ Xc + T[:3, 3]
    obs = []
    for k, T in enumerate(T_true):
        Tcw = invert_pose(T)
        for i, X in pts.items():
            Xc = Tcw[:3, :3] @ X + Tcw[:3, 3]
            if Xc[2] < 0.3:
                continue
            uv0, _ = project(rig.cam0.K, Xc[None])
            uv1, _ = project(rig.cam1.K, (rig.R @ Xc + rig.T)[None])
            if 0 <= uv0[0, 0] < rig.cam0.size[0] and 0 <= uv0[0, 1] < rig.cam0.size[1]:
                obs.append([k, i, 0, *(uv0[0] + rng.normal(0, 0.5, 2))])
                obs.append([k, i, 1, *(uv1[0] + rng.normal(0, 0.5, 2))])
    T_noisy = T_true.copy()
    for k in range(1, len(T_noisy)):
        T_noisy[k] = T_noisy[k] @ make_pose(so3_exp(rng.normal(0, 0.003, 3)), rng.normal(0, 0.005, 3))
    pts_noisy = {i: X + rng.normal(0, 0.005, 3) for i, X in pts.items()}
    return rig, sim.t_ns[kf], T_true, T_noisy, pts_noisy, np.array(obs)


@pytest.fixture(scope="module")
def visual(sim):
    """``_visual_problem(sim)`` (its arrays read-only: the tests share it) and its vision-only adjustment."""
    rig, t_kf, T_true, T_noisy, pts, obs = _visual_problem(sim)
    for a in (t_kf, T_true, T_noisy, obs, *pts.values()):
        a.setflags(write=False)
    vision = adjust(rig, T_noisy, pts, obs, outlier_rounds=0)
    return (rig, t_kf, T_true, T_noisy, pts, obs), vision


@pytest.mark.slow
def test_imu_factors_recover_the_simulated_biases_and_keep_the_path(sim, visual):
    (rig, t_kf, T_true, T_noisy, pts, obs), vision = visual
    terms = imu_terms(sim, t_kf, T_noisy)
    assert terms.noise == ImuNoise.of(sim) and terms.noise.accel_random_walk == sim.imu_model.accel_bias_walk_m_s3_rthz
    fused = adjust(rig, T_noisy, pts, obs, outlier_rounds=0, imu=terms)
    assert vision.imu_biases is None and fused.imu_biases.shape == (len(t_kf), 6)
    # the path: no worse than vision only, and the first pose stays where it was held
    assert _ate(fused.T_world_cam, T_true) <= _ate(vision.T_world_cam, T_true) * 1.001
    assert np.allclose(fused.T_world_cam[0], T_noisy[0], atol=1e-5)
    # the biases at the keyframes: within 10 % of the simulator's (constant part + random walk)
    t_imu = sim.imu.t_ns
    for est, true in ((fused.imu_biases[:, :3], sim.imu_biases.accel_m_s2), (fused.imu_biases[:, 3:], sim.imu_biases.gyro_rad_s)):
        tr = np.column_stack([np.interp(t_kf, t_imu, true[:, a]) for a in range(3)])
        err = np.linalg.norm(est - tr, axis=1) / np.linalg.norm(tr, axis=1)
        assert np.median(err) < 0.10, (est.mean(0), tr.mean(0))


def _moving(sim, gyro_scale: float = 1.0, accel_scale: float = 1.0):
    """The simulated session with its IMU cut at the first frame: no still block before it (EuRoC's
    layout, or a box switched on in the hand); the samples optionally scaled (a miscalibrated IMU)."""
    from stereopath.device.core.frames import ImuSamples

    m = sim.imu.t_ns >= sim.t_ns[0]

    class Moving:
        rig, t_ns, groundtruth, imu_model = sim.rig, sim.t_ns, sim.groundtruth, sim.imu_model
        imu_noise_figures = getattr(sim, "imu_noise_figures", None)
        imu = ImuSamples(sim.imu.t_ns[m], sim.imu.gyro_rad_s[m] * gyro_scale, sim.imu.accel_m_s2[m] * accel_scale)

    return Moving()


def test_imu_terms_need_an_imu_extrinsics_and_a_path_that_agrees_with_them(sim, monkeypatch):
    from dataclasses import replace

    t_kf = sim.t_ns[::10]
    T = sim.groundtruth.T_world_cam[::10]

    class NoImu:
        rig, t_ns, imu = sim.rig, sim.t_ns, None

    with pytest.raises(EstimationError, match="IMU stream"):
        imu_terms(NoImu(), t_kf, T)

    # no still block: the gyro bias and gravity come from the path, which needs two intervals at least for the
    # gyro and three for gravity (with two, the solve is exactly determined: nothing would say it is wrong)
    with pytest.raises(EstimationError, match="two keyframe intervals"):
        imu_terms(_moving(sim), np.array([sim.t_ns[1], sim.t_ns[20]]), T[:2])
    with pytest.raises(EstimationError, match="three keyframe intervals"):
        imu_terms(_moving(sim), sim.t_ns[[1, 20, 40]], sim.groundtruth.T_world_cam[[1, 20, 40]])
    assert len(imu_terms(_moving(sim), sim.t_ns[[1, 20, 40, 60]], sim.groundtruth.T_world_cam[[1, 20, 40, 60]]).pims) == 3

    # readings that do not fit the path are refused, not used: an accelerometer reading 1.3 g at rest,
    # a gyro 1.3x too sensitive, an IMU mounted 20 deg off what T_body_cam0 says
    with pytest.raises(ImuMismatchError, match=r"disagree.*12\.8"):
        imu_terms(_moving(sim, accel_scale=1.3), t_kf, T)
    with pytest.raises(ImuMismatchError, match="disagree: the gyro"):
        imu_terms(_moving(sim, gyro_scale=1.3), t_kf, T)
    turned = _moving(sim)
    turned.rig = replace(sim.rig, T_body_cam0=make_pose(so3_exp(np.array([0.0, 0.0, np.radians(20)])), np.zeros(3))
                         @ sim.rig.T_body_cam0)
    with pytest.raises(ImuMismatchError, match="disagree"):
        imu_terms(turned, t_kf, T)
    # the velocity residual is a test of its own: held to 0.1 mm/s it refuses even the true readings (the
    # simulated scan leaves 0.01-0.03 m/s per interval)
    from stereopath.host.backend import imu_factors

    monkeypatch.setattr(imu_factors, "MAX_GRAVITY_FIT_RMS_M_S", 1e-4)
    with pytest.raises(EstimationError, match=r"velocity residual 0\.0[1-3]"):
        imu_terms(_moving(sim), t_kf, T)
    monkeypatch.undo()

    class NoExtrinsics:
        rig, t_ns, imu = replace(sim.rig, T_body_cam0=None), sim.t_ns, sim.imu

    with pytest.raises(EstimationError, match="T_body_cam0"):
        imu_terms(NoExtrinsics(), t_kf, T)


@pytest.mark.slow
def test_without_a_still_start_gravity_and_the_gyro_bias_come_from_the_path(sim, visual):
    """The IMU starts with the first frame: the gyro bias from the path's rotations, gravity and the
    velocities from its positions, and the bundle adjustment then does what it does with a still start."""
    moving = _moving(sim)
    t_kf, T_true = sim.t_ns[::8], sim.groundtruth.T_world_cam[::8]
    terms = imu_terms(moving, t_kf, T_true)  # the simulator's world: z up
    tilt = np.arccos(-terms.gravity_world[2] / np.linalg.norm(terms.gravity_world))
    assert tilt < 2e-3  # the accelerometer bias (left at 0 here) tilts it by ~1 mrad
    assert np.linalg.norm(terms.gravity_world) == pytest.approx(ImuNoise.of(sim).gravity_m_s2)
    assert np.allclose(terms.bias0.gyroscope(), sim.imu_biases.gyro_rad_s.mean(axis=0), atol=1e-4)
    assert np.allclose(terms.bias0.accelerometer(), 0.0)
    # the velocities from the solve: nearer the truth than central differences of the keyframes (measured
    # median 0.009 against 0.019 m/s)
    v_true = sim.trajectory.velocity_world(t_kf * 1e-9)  # the session clock is the trajectory's
    v_diff = np.gradient(T_true[:, :3, 3], t_kf * 1e-9, axis=0)
    err = np.median(np.linalg.norm(terms.velocities - v_true, axis=1))
    assert err < 0.7 * np.median(np.linalg.norm(v_diff - v_true, axis=1)) and err < 0.013
    # in another world frame (the first camera's, as a session without a still start is estimated)
    (rig, t_kf, T_cam0, T_noisy, pts, obs), vision = visual
    terms = imu_terms(moving, t_kf, T_noisy)
    g_cam0 = sim.groundtruth.T_world_cam[0][:3, :3].T @ np.array([0.0, 0.0, -1.0])
    assert np.arccos(terms.gravity_world @ g_cam0 / np.linalg.norm(terms.gravity_world)) < 5e-3
    fused = adjust(rig, T_noisy, pts, obs, outlier_rounds=0, imu=terms)
    assert _ate(fused.T_world_cam, T_cam0) <= _ate(vision.T_world_cam, T_cam0) * 1.001
    t_imu = sim.imu.t_ns
    for est, true in ((fused.imu_biases[:, :3], sim.imu_biases.accel_m_s2), (fused.imu_biases[:, 3:], sim.imu_biases.gyro_rad_s)):
        tr = np.column_stack([np.interp(t_kf, t_imu, true[:, a]) for a in range(3)])
        err = np.linalg.norm(est - tr, axis=1) / np.linalg.norm(tr, axis=1)
        assert np.median(err) < 0.10, (est.mean(0), tr.mean(0))


def test_a_recorded_simulation_carries_the_noise_it_draws(tmp_path):
    """imu0/sensor.yaml of a simulated session holds the simulator's noise (not the MPU-6050 defaults)."""
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.formats.rig_files import MPU6050_NOISE
    from stereopath.device.formats.source import open_source
    from stereopath.device.sim.session import SimConfig, open_sim

    s = open_sim(SimConfig(frames=2))
    record_sequence(s, tmp_path / "s", config_dict={"source": "sim"})
    noise = ImuNoise.of(open_source(f"session:{tmp_path / 's'}"))
    assert noise.gyro_random_walk == pytest.approx(s.imu_model.gyro_bias_walk_rad_s2_rthz)
    assert noise.accel_random_walk == pytest.approx(s.imu_model.accel_bias_walk_m_s3_rthz)
    assert noise.accel_random_walk != MPU6050_NOISE["accelerometer_random_walk"]
    assert noise.gravity_m_s2 == pytest.approx(9.81)
    # a session without the file (or a bad entry) falls back to the MPU-6050 figures
    yaml_path = tmp_path / "s" / "mav0" / "imu0" / "sensor.yaml"
    yaml_path.write_text(yaml_path.read_text().replace("accelerometer_random_walk: 0.001",
                                                       "accelerometer_random_walk: fast"))
    noise = ImuNoise.of(open_source(f"session:{tmp_path / 's'}"))
    assert noise.accel_random_walk == MPU6050_NOISE["accelerometer_random_walk"]
    assert noise.gyro_random_walk == pytest.approx(s.imu_model.gyro_bias_walk_rad_s2_rthz)


@pytest.mark.realdata
def test_euroc_gravity_from_the_onboard_path_matches_the_ground_truth(data_dir):
    """EuRoC's IMU starts with its cameras, so there is no still block before the first frame: the
    preintegration takes the gyro bias and gravity from the on-board path (world = the first camera)."""
    from stereopath.device.core.geometry import quat_xyzw_to_matrix
    from stereopath.device.estimation.base import run_estimator
    from stereopath.device.estimation.registry import make_estimator
    from stereopath.device.formats import open_source

    seq = open_source(f"euroc:{data_dir / 'euroc_v1_01_head'}")
    run = run_estimator(make_estimator("stereo", seq.rig), iter(list(seq.frames())), seq.imu)
    assert run.world_frame == "gravity_aligned"  # solved on board from the first second's path
    idx = np.arange(0, len(run.trajectory.t_ns), 10)
    terms = imu_terms(seq, run.trajectory.t_ns[idx], run.trajectory.T_world_cam[idx])
    gt = np.loadtxt(data_dir / "euroc_v1_01_head" / "groundtruth_tum.txt")
    k = int(np.argmin(np.abs(gt[:, 0] - run.trajectory.t_ns[0] * 1e-9)))
    R_world_cam0 = quat_xyzw_to_matrix(gt[k, 4:8]) @ seq.rig.T_body_cam0[:3, :3]  # the motion capture's z is up
    g_cam0 = R_world_cam0.T @ np.array([0.0, 0.0, -1.0])
    g_est_cam0 = run.trajectory.T_world_cam[0][:3, :3].T @ terms.gravity_world  # in the first camera's frame
    angle = np.degrees(np.arccos(g_est_cam0 @ g_cam0 / np.linalg.norm(terms.gravity_world)))
    assert angle < 1.0  # measured 0.57 deg: the accelerometer bias, left at 0 here (~0.1 m/s^2)
    assert np.allclose(terms.bias0.gyroscope(), [-0.002, 0.021, 0.078], atol=2e-3)  # the well-known V1_01 bias
    assert len(terms.pims) == len(idx) - 1


def test_gyro_rotation_priors_without_a_still_start_use_the_bias_from_the_path(sim):
    from stereopath.device.core.geometry import so3_log
    from stereopath.host.reprocess.stage_ba import gyro_rotation_priors

    moving = _moving(sim)
    t_kf, T = sim.t_ns[::8], sim.groundtruth.T_world_cam[::8]
    priors = gyro_rotation_priors(moving, t_kf, 0.002, T)
    assert len(priors) == len(t_kf) - 1
    err = [np.linalg.norm(so3_log(T[p.i][:3, :3].T @ T[p.j][:3, :3] @ p.R_ci_cj.T)) for p in priors]
    # measured: median 0.21 mrad (with the still start's bias 0.32 mrad; with no bias 1.24 mrad)
    assert np.median(err) < 4e-4 and max(err) < 8e-4
    assert gyro_rotation_priors(moving, t_kf, 0.002) == []  # neither a still start nor a path: no priors


@pytest.mark.slow
def test_an_imu_that_starts_late_gives_factors_only_where_it_covers_the_keyframes(sim, visual):
    """The IMU starts after the 103rd frame, in motion: the interval it covers in part is left out (holding its
    first sample over the rest would be a wrong factor), the keyframes before it keep the path's velocities,
    and the adjustment is no worse than vision alone."""
    from stereopath.device.core.frames import ImuSamples

    (rig, t_kf, T_cam0, T_noisy, pts, obs), vision = visual
    m = sim.imu.t_ns >= sim.t_ns[103]
    late = _moving(sim)
    late.imu = ImuSamples(sim.imu.t_ns[m], sim.imu.gyro_rad_s[m], sim.imu.accel_m_s2[m])
    terms = imu_terms(late, t_kf, T_noisy)
    first = int(np.searchsorted(t_kf, sim.t_ns[103]))  # the first keyframe after the IMU's start
    assert [i for i, _, _ in terms.pims] == list(range(first, len(t_kf) - 1))
    assert np.isfinite(terms.velocities).all()  # the keyframes no interval touches: central differences
    fused = adjust(rig, T_noisy, pts, obs, outlier_rounds=0, imu=terms)
    assert _ate(fused.T_world_cam, T_cam0) <= _ate(vision.T_world_cam, T_cam0) * 1.001


def _up_in_camera(R_world_cam: np.ndarray) -> np.ndarray:
    """The world's up (+z) seen from the camera: what tilt a pose has, whatever its yaw."""
    return np.asarray(R_world_cam)[..., :3, :3].swapaxes(-1, -2) @ np.array([0.0, 0.0, 1.0])


@pytest.mark.slow
def test_a_session_without_a_still_start_is_leveled_by_the_gravity_the_adjustment_measured(sim, visual):
    """Estimated in its first camera's world (no still start), adjusted with IMU factors: the stage
    turns the poses, the points and the gravity into a z-up world, as a still start would have given."""
    import json
    from types import SimpleNamespace

    from stereopath.device.estimation.inertial import gravity_aligned_rotation, leveling_rotation
    from stereopath.host.reprocess.stage_ba import level_world

    (rig, t_kf, T_cam0, T_noisy, pts, obs), vision = visual
    g = ImuNoise.of(sim).gravity_m_s2
    g_true = sim.groundtruth.T_world_cam[0][:3, :3].T @ np.array([0.0, 0.0, -g])  # in the first camera's world
    # the adjustment starts from gravity 3 deg off and reports where it put it, in the world of its poses
    g_start = so3_exp(np.array([np.radians(3.0), 0.0, 0.0])) @ g_true
    fused = adjust(rig, T_noisy, pts, obs, outlier_rounds=0,
                                   imu=imu_terms(_moving(sim), t_kf, T_noisy, gravity_world=g_start))
    assert fused.gravity_world is not None and np.linalg.norm(fused.gravity_world) == pytest.approx(g)
    assert np.degrees(np.arccos(fused.gravity_world @ g_true / g ** 2)) < 0.1  # measured 0.011 deg
    kf = np.arange(0, len(sim), 8)
    T_true = sim.groundtruth.T_world_cam[kf]
    # before: the first camera's world (z along its optical axis: 113 deg from the truth's up here)
    before = np.degrees(np.arccos(np.clip(np.sum(_up_in_camera(fused.T_world_cam) * _up_in_camera(T_true), 1), -1, 1)))
    assert before.min() > 10
    T_before, points_before = fused.T_world_cam.copy(), dict(fused.points)
    T_frames = fused.T_world_cam.copy()
    estimate = {"meta": np.array(json.dumps({"world_frame": "first_camera"})), "t_ns": t_kf}
    turn = level_world(SimpleNamespace(seq=sim, results={"estimate": estimate}), fused, T_frames)
    assert turn["by"] == "imu_factors" and turn["deg"] >= before[0] - 0.5  # the tilt, and a yaw
    # after: every pose tilted as the truth is (measured 0.017 deg at most)
    tilt = np.degrees(np.arccos(np.clip(np.sum(_up_in_camera(T_frames) * _up_in_camera(T_true), 1), -1, 1)))
    assert tilt.max() < 0.1, tilt.max()
    assert np.allclose(fused.T_world_cam, T_frames)
    assert np.allclose(fused.gravity_world, [0.0, 0.0, -g], atol=1e-9)
    # a rigid turn about the world's origin: each point seen from each pose as before
    for k in (0, len(T_frames) - 1):
        for i in list(points_before)[:20]:
            a, b = invert_pose(T_frames[k]), invert_pose(T_before[k])
            assert np.allclose(a[:3, :3] @ fused.points[i] + a[:3, 3], b[:3, :3] @ points_before[i] + b[:3, 3])
    # the turn is the still start's world: a body at rest reading ``up`` gets gravity_aligned_rotation(up)
    R_body_cam = np.asarray(sim.rig.T_body_cam0)[:3, :3]
    R = leveling_rotation(T_before[0][:3, :3], R_body_cam, T_before[0][:3, :3] @ R_body_cam.T @ np.array([0, 0, -9.8]))
    assert np.allclose(R @ T_before[0][:3, :3] @ R_body_cam.T, gravity_aligned_rotation(np.array([0.0, 0.0, 1.0])))
    # a world already gravity aligned (a still start), or no gravity measured (the rig never rests during
    # the frames either): nothing turns
    estimate["meta"] = np.array(json.dumps({"world_frame": "gravity_aligned"}))
    assert level_world(SimpleNamespace(seq=sim, results={"estimate": estimate}), fused, T_frames) is None
    estimate["meta"] = np.array(json.dumps({"world_frame": "first_camera"}))
    T_vision = vision.T_world_cam.copy()
    assert vision.gravity_world is None
    assert level_world(SimpleNamespace(seq=sim, results={"estimate": estimate}), vision, T_vision) is None
    assert np.array_equal(T_vision, vision.T_world_cam)


def test_gravity_where_the_rig_rests_during_the_frames():
    """A rig that rests after its cameras start (EuRoC's first seconds, a box put down to start a scan):
    gravity from the IMU's mean specific force there, in the path's world; none where the path moves."""
    from stereopath.device.estimation.inertial_init import gravity_from_still_frames
    from stereopath.device.sim.session import SimConfig, open_sim

    still = _moving(open_sim(SimConfig(frames=60, trajectory="still")))
    R_bc = np.asarray(still.rig.T_body_cam0)[:3, :3]
    T0inv = invert_pose(still.groundtruth.T_world_cam[0])
    T_body = np.array([T0inv @ T for T in still.groundtruth.T_world_cam]) @ make_pose(R_bc.T, np.zeros(3))
    g = gravity_from_still_frames(still.imu, still.t_ns, T_body)
    g_true = T0inv[:3, :3] @ np.array([0.0, 0.0, -1.0])  # the first camera's world
    tilt = np.degrees(np.arccos(g @ g_true / np.linalg.norm(g)))
    assert tilt < 0.6, tilt  # the simulator's accelerometer bias (0.07 m/s^2: 0.4 deg) tilts it
    assert np.linalg.norm(g) == pytest.approx(9.81, abs=0.2)
    # a path that says the rig moves over every stretch (a 3 cm or 2 deg sawtooth of 0.15 s)
    for shift, turn in ((0.03, 0.0), (0.0, 2.0)):
        moved = T_body.copy()
        frac = np.linspace(0, 20, len(moved)) % 1.0
        moved[:, 0, 3] += shift * frac
        moved[:, :3, :3] = np.array([so3_exp(np.array([0, np.radians(turn) * f, 0])) for f in frac]) @ moved[:, :3, :3]
        assert gravity_from_still_frames(still.imu, still.t_ns, moved) is None
    # a predicted pose (an untracked frame) or a non-finite one says nothing about rest: no stretch holds one
    every_half_second = (np.arange(len(still.t_ns)) % 10) == 5
    assert gravity_from_still_frames(still.imu, still.t_ns, T_body, tracked=~every_half_second) is None
    assert np.allclose(gravity_from_still_frames(still.imu, still.t_ns, T_body, tracked=np.ones(len(T_body), bool)), g)
    nan = T_body.copy()
    nan[every_half_second] = np.nan
    assert gravity_from_still_frames(still.imu, still.t_ns, nan) is None
    # vibration (EuRoC's rotors) averages out; readings that are not 1 g (another unit) are not gravity
    rng = np.random.default_rng(1)
    ImuSamples = type(still.imu)
    shaken = ImuSamples(still.imu.t_ns, still.imu.gyro_rad_s + rng.normal(0, 0.08, still.imu.gyro_rad_s.shape),
                        still.imu.accel_m_s2 + rng.normal(0, 0.5, still.imu.accel_m_s2.shape))
    g_shaken = gravity_from_still_frames(shaken, still.t_ns, T_body)
    assert np.degrees(np.arccos(g_shaken @ g / np.linalg.norm(g_shaken) / np.linalg.norm(g))) < 1.0  # sigma 0.2 deg
    in_g = ImuSamples(still.imu.t_ns, still.imu.gyro_rad_s, still.imu.accel_m_s2 / 9.81)
    assert gravity_from_still_frames(in_g, still.t_ns, T_body) is None
    # the scan moves from its first quarter second on: never a still second
    sim = open_sim(SimConfig())
    T_arc = np.array([T0inv @ T for T in sim.groundtruth.T_world_cam]) @ make_pose(R_bc.T, np.zeros(3))
    assert gravity_from_still_frames(_moving(sim).imu, sim.t_ns, T_arc) is None


@pytest.mark.slow
def test_euroc_is_leveled_where_it_rests_after_its_cameras_start(data_dir, tmp_path):
    """The real EuRoC V1_01 head rests for its 95 frames and has no still IMU block before its first
    frame and too few keyframes for IMU factors: the on-board estimate levels its world from the tracked
    path (a start in motion), and the reprocessed path comes out z up, its tilt within a degree of the
    motion capture's (the accelerometer bias)."""
    import json

    from stereopath.device.core.geometry import quat_xyzw_to_matrix
    from stereopath.device.formats import open_source
    from stereopath.device.formats.tum import read_tum
    from stereopath.host.reprocess.pipeline import RunChoices, reprocess_session

    src = data_dir / "euroc_v1_01_head"
    reprocess_session(str(src), tmp_path, run=RunChoices(progress=False, do_map=False))
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["world_frame"] == "gravity_aligned"
    assert rep["extra"]["bundle_adjustment"]["leveled"] is None  # gravity aligned on board already
    est = read_tum(tmp_path / "trajectory.tum")
    gt = np.loadtxt(src / "groundtruth_tum.txt")
    R_bc = open_source(f"euroc:{src}").rig.T_body_cam0[:3, :3]
    tilts = []
    for t, T in zip(est.t_ns[::10], est.T_world_cam[::10]):
        k = int(np.argmin(np.abs(gt[:, 0] - t * 1e-9)))
        up_true = (quat_xyzw_to_matrix(gt[k, 4:8]) @ R_bc).T @ [0.0, 0.0, 1.0]  # the motion capture's z is up
        up_est = T[:3, :3].T @ [0.0, 0.0, 1.0]
        tilts.append(np.degrees(np.arccos(np.clip(up_est @ up_true, -1, 1))))
    assert max(tilts) < 1.0, tilts


def test_an_imu_refused_for_disagreeing_with_the_path_does_not_level_the_world(sim, monkeypatch):
    """Readings the adjustment refused (wrong axes, scale or mounting) are not used to level either; an
    IMU that fits but gives no factors (a resting session: too few keyframe intervals) may level."""
    import json
    from types import SimpleNamespace

    from dataclasses import replace

    from stereopath.device.sim.session import SimConfig, open_sim
    from stereopath.host.backend import imu_factors
    from stereopath.host.reprocess import stage_ba
    from stereopath.host.reprocess.config import REPROCESS_PRESETS

    def raising(exc):
        def f(*a, **k):
            raise exc
        return f

    inputs = SimpleNamespace(seq=sim, results={"estimate": {"t_ns": sim.t_ns[:3]},
                                               "tracks": {"kf_index": np.arange(3), "T_kf": np.repeat(np.eye(4)[None], 3, 0)}})
    config = REPROCESS_PRESETS["standard"]
    monkeypatch.setattr(imu_factors, "imu_terms", raising(ImuMismatchError("the path and the IMU disagree")))
    assert stage_ba.imu_terms_of(config, inputs) == (None, False)
    monkeypatch.setattr(imu_factors, "imu_terms", raising(EstimationError("needs at least three keyframe intervals")))
    assert stage_ba.imu_terms_of(config, inputs) == (None, True)
    assert stage_ba.imu_terms_of(replace(config, ba=replace(config.ba, imu=False)), inputs) == (None, False)

    still = _moving(open_sim(SimConfig(frames=60, trajectory="still")))
    T0inv = invert_pose(still.groundtruth.T_world_cam[0])
    T = np.array([T0inv @ X for X in still.groundtruth.T_world_cam])
    est = {"meta": np.array(json.dumps({"world_frame": "first_camera"})), "t_ns": still.t_ns,
           "status": np.zeros(len(T), np.int64)}
    res = SimpleNamespace(gravity_world=None, T_world_cam=T[::10].copy(), points={0: np.array([0.0, 0.0, 1.0])})
    frames = T.copy()
    assert stage_ba.level_world(SimpleNamespace(seq=still, results={"estimate": est}), res, frames, imu_usable=False) is None
    assert np.array_equal(frames, T)
    # frames the estimator did not track (predicted poses) every half second: no stretch is known to rest
    lost = dict(est, status=np.where(np.arange(len(T)) % 10 == 5, 2, 0))
    assert stage_ba.level_world(SimpleNamespace(seq=still, results={"estimate": lost}), res, frames, imu_usable=True) is None
    out = stage_ba.level_world(SimpleNamespace(seq=still, results={"estimate": est}), res, frames, imu_usable=True)
    assert out["by"] == "still_imu" and np.allclose(np.asarray(out["R_new_old"]) @ T[0][:3, :3], frames[0][:3, :3])
    assert np.allclose(out["gravity_world"] / np.linalg.norm(out["gravity_world"]), [0, 0, -1], atol=1e-9)
