"""Simulator session: pinned API, configuration checks, determinism, photometry options, scene layout."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereopath.device.core.config import from_mapping
from stereopath.device.errors import ConfigError
from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.core.rig import Rig
from stereopath.device.sim.scene import OBJECTS, TABLE_SIZE_M, TABLE_TOP_Z_M, table_top_scene
from stereopath.device.sim.session import SimConfig, SimSession, open_sim
from stereopath.device.sim.textures import STYLES, make_texture
from stereopath.device.formats.tum import Trajectory


def test_pinned_api_and_defaults():
    cfg = SimConfig()
    assert (cfg.frames, cfg.rate_hz, cfg.seed, cfg.trajectory, cfg.imu.rate_hz, cfg.noise_sigma) == (
        400, 20.0, 0, "arc", 200.0, 2.0)
    assert (cfg.exposure_drift, cfg.motion_blur, cfg.imu.gyro_fs_dps, cfg.imu.accel_fs_g, cfg.with_depth) == (
        False, False, 500, 4, False)
    s = open_sim(frames=5)
    assert isinstance(s, SimSession) and isinstance(s.rig, Rig) and s.rig.T_body_cam0 is not None
    assert s.t_ns.dtype == np.int64 and list(s.t_ns) == [1_000_000_000 + i * 50_000_000 for i in range(5)]
    assert isinstance(s.groundtruth, Trajectory) and np.array_equal(s.groundtruth.t_ns, s.t_ns)
    assert isinstance(s.imu, ImuSamples) and isinstance(s.imu_truth, ImuSamples)
    assert np.allclose(s.gravity_world, [0, 0, -9.81])
    frames = list(s.frames())
    assert [f.seq for f in frames] == list(range(5)) and len(s) == 5
    f = frames[3]
    assert isinstance(f, StereoFrame) and f.t_ns == s.t_ns[3]
    assert f.left.shape == f.right.shape == (480, 640) and f.left.dtype == f.right.dtype == np.uint8
    assert np.array_equal(f.meta["T_world_cam0"], s.groundtruth.T_world_cam[3])
    assert "depth0" not in f.meta
    assert np.array_equal(s.render(3).left, f.left)  # random access = sequential
    with pytest.raises(IndexError):
        s.render(5)


def test_config_rejects_unknown_keys_and_bad_values():
    with pytest.raises(ConfigError, match="colour"):
        open_sim(colour=True)
    with pytest.raises(ConfigError, match="colour"):
        from_mapping(SimConfig, {"frames": 10, "colour": True})
    for bad in ({"frames": 0}, {"rate_hz": -1.0}, {"trajectory": "spiral"}, {"imu": {"gyro_fs_dps": 300}},
                {"imu": {"accel_fs_g": 3}}, {"noise_sigma": -0.5}, {"seed": -1}, {"imu": {"rate_hz": 0.0}},
                {"frames": "ten"}, {"motion_blur": "yes"}, {"exposure_ms": 80.0}, {"imu": {"colour": 1}}):
        key, value = next(iter(bad.items()))
        match = f"imu.*{next(iter(value))}" if isinstance(value, dict) else key
        with pytest.raises(ConfigError, match=match):
            open_sim(**bad)
    with pytest.raises(ConfigError, match="frames"):
        open_sim(SimConfig(frames=3), frames=-2)
    assert open_sim(SimConfig(frames=3), seed=4).cfg.seed == 4


@pytest.mark.slow
def test_deterministic_for_a_seed_and_different_across_seeds():
    a, b, c = open_sim(frames=3, seed=7), open_sim(frames=3, seed=7), open_sim(frames=3, seed=8)
    fa, fb, fc = a.render(2), b.render(2), c.render(2)
    assert np.array_equal(fa.left, fb.left) and np.array_equal(fa.right, fb.right)
    assert np.array_equal(a.imu.gyro_rad_s, b.imu.gyro_rad_s) and np.array_equal(a.imu.accel_m_s2, b.imu.accel_m_s2)
    assert np.array_equal(a.groundtruth.T_world_cam, b.groundtruth.T_world_cam)
    assert np.mean(fa.left != fc.left) > 0.5  # other textures and noise
    assert not np.array_equal(a.imu.gyro_rad_s, c.imu.gyro_rad_s)
    # noise differs frame to frame and eye to eye, but is zero-mean and has the configured sigma
    clean = open_sim(frames=3, seed=7, noise_sigma=0.0).render(2)
    d = fa.left.astype(float) - clean.left
    assert abs(d.mean()) < 0.1 and np.std(d[(clean.left > 10) & (clean.left < 245)]) == pytest.approx(2.0, rel=0.1)
    d1 = a.render(1).left.astype(float) - open_sim(frames=3, seed=7, noise_sigma=0.0).render(1).left
    assert abs(np.corrcoef(d.ravel(), d1.ravel())[0, 1]) < 0.05


def test_depth_in_meta_exposure_drift_and_vignetting():
    s = open_sim(frames=120, with_depth=True, exposure_drift=True, noise_sigma=0.0)
    ref = open_sim(frames=120, noise_sigma=0.0)
    gains = [s.gains(i) for i in range(0, 120, 5)]
    assert max(g[0] for g in gains) - min(g[0] for g in gains) > 0.1  # slow gain drift
    assert any(abs(gl - gr) > 0.005 for gl, gr in gains)              # and a small left/right difference
    i = int(np.argmax([abs(g[0] - 1) for g in gains])) * 5
    f, r = s.render(i), ref.render(i)
    assert f.meta["depth0"].shape == (480, 640) and f.meta["depth0"].dtype == np.float32
    ratio = f.left.astype(float).mean() / r.left.astype(float).mean()
    assert ratio == pytest.approx(f.meta["gains"][0], rel=0.02)
    v = open_sim(frames=3, vignetting=0.4, noise_sigma=0.0).render(1).left.astype(float)
    r0 = open_sim(frames=3, noise_sigma=0.0).render(1).left.astype(float)
    assert v[:40, :40].mean() / r0[:40, :40].mean() < 0.7 and v[220:260, 300:340].mean() / r0[220:260, 300:340].mean() > 0.97


def _sharpness(img: np.ndarray) -> float:
    return float(np.mean(np.abs(cv2.Laplacian(img.astype(np.float32), cv2.CV_32F))))


def test_motion_blur_smears_fast_motion():
    # fastest rotation of the default arc
    s = open_sim(noise_sigma=0.0)
    w = np.linalg.norm(s.trajectory.state(s.t_ns * 1e-9).omega_cam, axis=1)
    i = int(np.argmax(w))
    sharp = s.render(i).left
    blurred = open_sim(noise_sigma=0.0, motion_blur=True, exposure_ms=20.0).render(i).left
    assert _sharpness(blurred) < 0.85 * _sharpness(sharp)
    assert abs(blurred.astype(float).mean() - sharp.astype(float).mean()) < 2.0


def test_scene_layout():
    scene = table_top_scene(0)
    objs = scene.objects
    assert len(objs) == len(OBJECTS) >= 5
    for b in objs:
        assert 0.1 <= max(b.size) <= 0.4
        c = b.corners_world()
        assert np.all(np.abs(c[:, 0]) <= TABLE_SIZE_M[0] / 2) and np.all(np.abs(c[:, 1]) <= TABLE_SIZE_M[1] / 2)
        assert c[:, 2].min() >= TABLE_TOP_Z_M - 1e-9
    # no two objects interpenetrate (sample points inside each box, test against the others)
    rng = np.random.default_rng(0)
    for a in objs:
        local = (rng.random((4000, 3)) - [0.5, 0.5, 0.0]) * a.size * [0.98, 0.98, 0.98] + [0, 0, 0.001 * a.size[2]]
        pts = local @ a.T_world_box[:3, :3].T + a.T_world_box[:3, 3]
        for b in objs:
            if b is not a:
                assert not np.any(b.contains(pts)), (a.name, b.name)
    # every quad faces into the room (inward normals) and is textured with an 8-bit image
    for q in scene.quads:
        tex = scene.textures[q.texture_id]
        assert tex.dtype == np.uint8 and tex.ndim == 2 and tex.std() > 10
        assert np.all(np.abs(q.corners[:, :2]) <= 2.0 + 1e-9) and np.all((q.corners[:, 2] >= -1e-9) & (q.corners[:, 2] <= 2.6 + 1e-9))


def test_textures_are_deterministic_and_detailed():
    for style in STYLES:
        a = make_texture(3, (160, 224), style, key=1, texel_px=1.0)
        assert np.array_equal(a, make_texture(3, (160, 224), style, key=1, texel_px=1.0))
        assert not np.array_equal(a, make_texture(4, (160, 224), style, key=1, texel_px=1.0))
        assert a.shape == (160, 224) and a.dtype == np.uint8 and a.std() > 10
    big = make_texture(0, (480, 640), "wall", texel_px=1.0)
    assert len(cv2.SIFT_create().detect(big, None)) > 800
    with pytest.raises(ValueError, match="marble"):
        make_texture(0, (16, 16), "marble")


def test_source_spec_parsing_and_registration():
    from stereopath.device.formats.source import open_source
    from stereopath.device.sim.source import open_sim_spec, parse_sim_spec

    assert parse_sim_spec("") == {} and parse_sim_spec("3") == {"seed": 3}
    assert parse_sim_spec("seed=2, frames=5,motion_blur=true,noise_sigma=1.5,trajectory=orbit") == {
        "seed": 2, "frames": 5, "motion_blur": True, "noise_sigma": 1.5, "trajectory": "orbit"}
    for bad in ("colour=1", "frames=ten", "x", "motion_blur=maybe"):
        with pytest.raises(ConfigError):
            parse_sim_spec(bad)
    s = open_sim_spec("seed=2,frames=4")
    assert len(s) == 4 and s.cfg.seed == 2 and s.spec == "sim:seed=2,frames=4"
    s2 = open_source("sim:seed=2,frames=4")  # registered with the dataset sources on import
    assert len(s2) == 4 and np.array_equal(s2.frame(1).left, s.frame(1).left)


# ------------------------------------------------------------------ the hand-held stand-in

def _handheld(**kw):
    from stereopath.device.sim.handheld import motion_file

    try:
        motion_file()
    except ConfigError:
        pytest.skip("the recorded flight (shared data trajectories/V101_gt.txt) is not available")
    return open_sim(trajectory="handheld", **kw)


def test_handheld_starts_in_motion():
    """No still block: the rig moves and turns from the first IMU sample on, and the measured gyro shows it."""
    s = _handheld(frames=60, seed=1)
    st = s.trajectory.state(np.array([0.0, 0.5, 1.0]))
    assert np.all(np.linalg.norm(st.v_world, axis=1) > 0.01)  # m/s
    assert np.all(np.degrees(np.linalg.norm(st.omega_cam, axis=1)) > 2.0)  # deg/s
    before = s.imu_truth.t_ns < s.t_ns[0]
    assert before.sum() >= 150  # one second of IMU data before the first frame, all of it moving
    assert np.degrees(np.linalg.norm(s.imu_truth.gyro_rad_s[before], axis=1)).min() > 1.0
    p = s.groundtruth.positions
    assert np.linalg.norm(p[1] - p[0]) > 1e-4


def test_handheld_scan_length_and_exact_derivatives():
    s = _handheld(frames=400)
    assert 1.0 <= s.groundtruth.path_length_m() <= 2.0
    tr, t, h = s.trajectory, np.linspace(2.0, 19.0, 40), 1e-4
    st = tr.state(t)
    fd = (tr.state(t + h).p_world_cam - tr.state(t - h).p_world_cam) / (2 * h)
    assert np.abs(fd - st.v_world).max() < 1e-5
    dR = tr.state(t + h).R_world_cam - tr.state(t - h).R_world_cam
    w_fd = np.einsum("nji,njk->nik", st.R_world_cam, dR / (2 * h))  # R^T dR/dt = [omega]x
    assert np.abs(w_fd[:, 2, 1] - st.omega_cam[:, 0]).max() < 1e-5


def test_handheld_has_exposure_changes_and_motion_blur():
    s = _handheld(frames=400, seed=3, noise_sigma=0.0)
    shutter = np.array([s.shutter_ms(i) for i in range(len(s))])
    gains = np.array([s.gains(i) for i in range(len(s))])
    assert shutter.max() / shutter.min() > 1.3  # the auto-exposure moves the shutter time
    assert np.abs(gains[:, 0] - 1).max() > 0.05 and not np.allclose(gains[:, 0], gains[:, 1])
    assert s.blurred and s.render(120).meta["shutter_ms"] == shutter[120]
    # blur: the same frame rendered sharp (one pose) has more gradient energy than the blurred one
    i = int(np.argmax([np.linalg.norm(s.trajectory.state(float(t) * 1e-9).omega_cam) for t in s.t_ns[:200]]))
    blurred = s.render(i).left.astype(float)
    sharp, _, _ = s.renderer.render(s.groundtruth.T_world_cam[i], key=i, gains=s.gains(i))
    energy = [np.mean(np.abs(np.diff(im.astype(float), axis=1))) for im in (blurred, sharp)]
    assert energy[0] < 0.97 * energy[1]


def test_handheld_is_deterministic_by_seed():
    a, b, c = _handheld(frames=40, seed=5), _handheld(frames=40, seed=5), _handheld(frames=40, seed=6)
    assert np.array_equal(a.render(30).left, b.render(30).left)
    assert np.array_equal(a.imu.gyro_rad_s, b.imu.gyro_rad_s)
    assert [a.shutter_ms(i) for i in range(40)] == [b.shutter_ms(i) for i in range(40)]
    assert [a.shutter_ms(i) for i in range(40)] != [c.shutter_ms(i) for i in range(40)]
    assert np.array_equal(a.groundtruth.T_world_cam, c.groundtruth.T_world_cam)  # the same recorded motion
