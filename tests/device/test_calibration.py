"""Calibration math and tools: stereo from chessboards (synthetic and OpenCV's set), IMU still period."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.core.calibration import (board_points, calibrate_stereo, detect_still_window, gravity_alignment,
                                imu_still_calibration, implied_gyro_bias, parse_board)
from stereopath.device.errors import CalibrationError
from stereopath.device.core.frames import ImuSamples
from stereopath.device.core.geometry import so3_exp

pytestmark = pytest.mark.timeout(120)


def test_parse_board():
    assert parse_board("9x6") == (9, 6) and parse_board("7X5") == (7, 5)
    for bad in ("9by6", "1x6", "x"):
        with pytest.raises(CalibrationError, match="board"):
            parse_board(bad)


def test_synthetic_views_recover_the_rig_in_our_convention():
    import cv2

    rng = np.random.default_rng(3)
    K = np.array([[520.0, 0, 322.0], [0, 518.0, 241.0], [0, 0, 1]])
    d0 = np.array([-0.12, 0.05, 0.0005, -0.0003, 0.0])
    R_true = so3_exp(np.array([0.01, -0.02, 0.005]))
    T_true = np.array([-0.06, 0.001, -0.002])          # right camera 6 cm to the right
    obj = board_points((9, 6), 0.03)
    center = obj.mean(axis=0)
    L, Rr = [], []
    for _ in range(14):
        rvec = rng.uniform(-0.5, 0.5, 3)
        Rb = so3_exp(rvec)
        tvec = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.08, 0.08), rng.uniform(0.45, 0.8)]) - Rb @ center
        p0 = (Rb @ obj.T).T + tvec
        p1 = (R_true @ p0.T).T + T_true
        for pts, out in ((p0, L), (p1, Rr)):
            uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, d0)
            out.append((uv + rng.normal(0, 0.1, uv.shape)).astype(np.float32))
    res = calibrate_stereo(L, Rr, (640, 480), (9, 6), 0.03)
    assert res.rms_px < 0.2
    assert np.allclose(res.rig.R, R_true, atol=2e-3)
    assert np.allclose(res.rig.T, T_true, atol=2e-3) and res.rig.T[0] < 0
    assert np.allclose(res.rig.cam0.K, K, rtol=1e-2, atol=2.0)


def test_too_few_views():
    with pytest.raises(CalibrationError, match="at least 3 pairs"):
        calibrate_stereo([np.zeros((54, 1, 2), np.float32)] * 2, [np.zeros((54, 1, 2), np.float32)] * 2,
                         (640, 480), (9, 6), 0.03)


@pytest.mark.realdata
def test_calibrate_stereo_cli_on_the_opencv_chessboards(data_dir, tmp_path, capsys):
    from stereopath.device.formats.rig_files import load_rig_yaml
    from stereopath.host.cli import main

    out = tmp_path / "rig.yaml"
    rc = main(["device", "calibrate-stereo", str(data_dir / "stereo_calib_chessboard"), "--board", "9x6",
               "--square-mm", "25", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0
    rms = float(text.split("RMS reprojection error:")[1].split("px")[0])
    assert rms < 1.0
    assert "baseline:" in text and "pairs used: 13 of 13" in text
    rig = load_rig_yaml(out)
    assert rig.T[0] < 0 and 0.05 < rig.baseline_m < 0.12       # ~3.3 squares of 25 mm
    assert rig.cam0.size == (640, 480)


def test_calibrate_stereo_cli_errors(tmp_path):
    from stereopath.host.cli import main

    assert main(["device", "calibrate-stereo", str(tmp_path), "--square-mm", "25"]) == 2   # no pairs
    assert main(["device", "calibrate-stereo", str(tmp_path / "nope"), "--square-mm", "25"]) == 2


def still_imu(n=2000, rate=200.0, bias=(0.01, -0.02, 0.005), tilt=(0.3, -0.2, 0.0), seed=0, turn_after=None):
    rng = np.random.default_rng(seed)
    t = (np.arange(n) * 1e9 / rate).astype(np.int64)
    R = so3_exp(np.array(tilt))                       # R_world_imu
    g_imu = R.T @ np.array([0, 0, 9.80665])
    gyro = np.array(bias) + rng.normal(0, 0.003, (n, 3))
    accel = g_imu + rng.normal(0, 0.05, (n, 3))
    if turn_after is not None:
        gyro[turn_after:, 2] += 0.5
    return ImuSamples(t, gyro, accel), R


def test_still_calibration_and_gravity_alignment():
    s, R = still_imu()
    res = imu_still_calibration(s)
    assert np.allclose(res.gyro_bias_rad_s, [0.01, -0.02, 0.005], atol=3e-4)
    assert res.gravity_m_s2 == pytest.approx(9.80665, abs=0.01)
    up = res.R_world_imu @ res.accel_mean_m_s2
    assert np.allclose(up / np.linalg.norm(up), [0, 0, 1], atol=1e-9)
    # same tilt as the truth up to a yaw about the vertical
    assert np.allclose(res.R_world_imu[2], R[2], atol=5e-3)
    for a in ([0, 0, -9.8], [0, 0, 9.8], [1.0, 0, 0]):
        Rg = gravity_alignment(np.array(a))
        assert np.allclose(Rg @ np.array(a) / np.linalg.norm(a), [0, 0, 1]) and np.isclose(np.linalg.det(Rg), 1)
    with pytest.raises(CalibrationError, match="zero"):
        gravity_alignment(np.zeros(3))


def test_still_window_stops_where_the_unit_starts_turning():
    s, _ = still_imu(n=2000, turn_after=1000)          # still for 5 s, then a 0.5 rad/s turn
    t0, t1 = detect_still_window(s, min_duration_s=2.0)
    assert t0 == s.t_ns[0] and 4.4e9 <= t1 <= 5.0e9
    moving, _ = still_imu(n=2000, turn_after=0)
    moving.gyro_rad_s[:, 2] += np.linspace(0, 2, 2000)  # accelerating turn: never still
    with pytest.raises(CalibrationError, match="no still period"):
        detect_still_window(moving, min_duration_s=2.0)


def _euroc_body_rotation(data_dir, t_ns):
    from stereopath.device.core.geometry import quat_xyzw_to_matrix

    gt = np.loadtxt(data_dir / "euroc_v1_01_head" / "groundtruth_tum.txt")
    i = int(np.argmin(np.abs(gt[:, 0] - t_ns / 1e9)))
    assert abs(gt[i, 0] - t_ns / 1e9) < 0.01
    return quat_xyzw_to_matrix(gt[i, 4:8]), gt[i, 0]


@pytest.mark.realdata
@pytest.mark.parametrize("window", ["frames", "auto"])
def test_euroc_still_head_gyro_bias_matches_the_ground_truth(data_dir, window):
    from stereopath.device.formats import open_source

    seq = open_source(f"euroc:{data_dir / 'euroc_v1_01_head'}")
    imu = seq.imu
    if window == "frames":
        t0, t1 = int(seq.t_ns[0]), int(seq.t_ns[-1])
    else:
        t0, t1 = detect_still_window(imu, min_duration_s=2.0)
        assert (t1 - t0) / 1e9 >= 4.0 and t1 - imu.t_ns[0] < 6e9   # the rotors-idle start of the flight
    still = imu.between(t0 - 1, t1)
    res = imu_still_calibration(still)
    R0, s0 = _euroc_body_rotation(data_dir, t0)
    R1, s1 = _euroc_body_rotation(data_dir, t1)
    implied = implied_gyro_bias(still, R0, R1, s1 - s0)
    assert np.all(np.abs(res.gyro_bias_rad_s - implied) < 1e-3)
    assert np.allclose(res.gyro_bias_rad_s, [-0.002, 0.021, 0.078], atol=2e-3)   # the well-known V1_01 bias
    assert res.gravity_m_s2 == pytest.approx(9.80665, abs=0.1)


@pytest.mark.slow
@pytest.mark.realdata
def test_euroc_gyro_bias_is_measured_by_the_estimator_from_vision(data_dir):
    """EuRoC's IMU starts with the cameras: no still block before the first frame, so the estimator
    starts without a bias (0.08 rad/s about z here) and measures it from its tracked rotation."""
    from stereopath.device.estimation.base import run_estimator
    from stereopath.device.estimation.registry import make_estimator
    from stereopath.device.formats import open_source

    seq = open_source(f"euroc:{data_dir / 'euroc_v1_01_head'}")
    frames = list(seq.frames())
    t0, t1 = frames[0].t_ns, frames[-1].t_ns
    R0, s0 = _euroc_body_rotation(data_dir, t0)
    R1, s1 = _euroc_body_rotation(data_dir, t1)
    implied = implied_gyro_bias(seq.imu.between(t0 - 1, t1), R0, R1, s1 - s0)
    est = make_estimator("stereo", seq.rig)
    run = run_estimator(est, iter(frames), seq.imu)
    assert run.world_frame == "gravity_aligned"  # not still before the first frame: solved from the path
    assert est.stats()["gyro_bias_updates"] >= 3
    assert np.all(np.abs(est.gyro_bias_rad_s - implied) < 1.5e-3)  # 0.09 deg/s, from 4.5 deg/s unknown
    off = make_estimator("stereo", seq.rig, options={"gyro": {"estimate_bias": False}})
    run_estimator(off, iter(frames), seq.imu)
    assert np.allclose(off.gyro_bias_rad_s, 0.0)


@pytest.mark.realdata
def test_calibrate_imu_cli(data_dir, tmp_path, capsys):
    import yaml

    from stereopath.host.cli import main

    out = tmp_path / "imu.yaml"
    rc = main(["device", "calibrate-imu", f"euroc:{data_dir / 'euroc_v1_01_head'}", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0 and "941 samples" in text and "gyro bias" in text
    data = yaml.safe_load(out.read_text())
    assert np.allclose(data["gyro_bias_rad_s"], [-0.00201, 0.02092, 0.07815], atol=1e-4)
    assert main(["device", "calibrate-imu", f"euroc:{data_dir / 'euroc_v1_01_head'}", "--window", "5:3"]) == 2


def test_calibrate_imu_refuses_a_window_in_which_the_unit_moved(tmp_path, capsys, caplog):
    """The frames of a hand-held scan move: no bias or gravity from them; the still start before them gives both."""
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim
    from stereopath.host.cli import main

    sim = open_sim(SimConfig(frames=20))
    record_sequence(sim, tmp_path / "s", config_dict={"source": "sim"})
    src = f"session:{tmp_path / 's'}"
    # the default window (the frames) moved; the still stretch before them is 1 s, shorter than --min-still-s
    assert main(["device", "calibrate-imu", src, "--out", str(tmp_path / "imu.yaml")]) == 2
    err = capsys.readouterr().err
    assert "the window frames (0.95 s): the unit was not still" in err
    assert "and --window auto: no still period of at least 2.0 s found (longest 1.0 s)" in err
    assert not (tmp_path / "imu.yaml").exists()
    # with a shorter minimum the default falls back on that still stretch, and says so
    assert main(["device", "calibrate-imu", src, "--min-still-s", "0.9", "--out", str(tmp_path / "imu.yaml")]) == 0
    out = capsys.readouterr()
    assert "using the still stretch --window auto found instead" in caplog.text and "window: auto" in out.out
    import yaml

    bias = yaml.safe_load((tmp_path / "imu.yaml").read_text())["gyro_bias_rad_s"]
    assert np.allclose(bias, sim.imu_biases.gyro_rad_s[0], atol=3e-4)  # the gyro's noise over 1 s: ~1e-4 rad/s
    # a window the user names is not replaced
    assert main(["device", "calibrate-imu", src, "--window", "frames", "--min-still-s", "0.9"]) == 2
    assert "give a still stretch with --window auto" in capsys.readouterr().err
    # the same check on explicit times that take in the first moves
    assert main(["device", "calibrate-imu", src, "--window", "0.2:1.9"]) == 2
    assert "the unit was not still" in capsys.readouterr().err


def test_check_still_passes_vibration_and_refuses_a_turn():
    from stereopath.device.core.calibration import check_still

    rng = np.random.default_rng(0)
    t = np.arange(0, 3_000_000_000, 5_000_000)
    g = np.array([0.01, -0.02, 0.005]) + rng.normal(0, 0.025, (len(t), 3))  # a bias, vibration (EuRoC: 0.02-0.04)
    a = np.array([0.0, 0.0, 9.81]) + rng.normal(0, 1.0, (len(t), 3))
    check_still(ImuSamples(t, g, a), "vibrating")
    turning = g.copy()
    turning[len(t) // 2:, 2] += 0.05  # a slow turn (3 deg/s) in the second half
    with pytest.raises(CalibrationError, match="turning: the unit was not still"):
        check_still(ImuSamples(t, turning, a), "turning")
    # a window ending 25 ms after a block's start: those 5 samples join the block (alone, their noisy mean
    # refused still data)
    for end in range(2_500_000_000 + 5_000_000, 2_500_000_000 + 50_000_000, 5_000_000):
        m = t <= end
        check_still(ImuSamples(t[m], g[m], a[m]), "tail")
    # a window shorter than a block is cut into four: a turn speeding up within 0.45 s shows
    m = t < 450_000_000
    speeding = g[m].copy()
    speeding[:, 2] += np.linspace(0.0, 0.3, m.sum())
    with pytest.raises(CalibrationError, match="short: the unit was not still"):
        check_still(ImuSamples(t[m], speeding, a[m]), "short")
    check_still(ImuSamples(t[m], g[m], a[m]), "short and still")
    with pytest.raises(CalibrationError, match="12 IMU samples are too few"):
        check_still(ImuSamples(t[:12], g[:12], a[:12]), "tiny")


@pytest.mark.realdata
def test_euroc_rests_in_every_window_of_its_head(data_dir):
    """EuRoC V1_01's first 4.7 s (on the ground, rotors turning): still whatever the window's end."""
    from stereopath.device.core.calibration import check_still
    from stereopath.device.formats import open_source

    seq = open_source(f"euroc:{data_dir / 'euroc_v1_01_head'}")
    t0 = int(seq.t_ns[0])
    for end_s in np.arange(0.3, 4.7, 0.0125):
        check_still(seq.imu.between(t0 - 1, t0 + int(end_s * 1e9)), f"{end_s:.4f} s")


def test_calibrate_imu_cli_live_emulated(capsys):
    from stereopath.host.cli import main

    rc = main(["device", "calibrate-imu", "live", "--imu", "emulated", "--seconds", "2"])
    text = capsys.readouterr().out
    assert rc == 0
    bias_dps = [float(v) for v in text.split("rad/s  (")[1].split(" deg/s")[0].split(",")]
    assert np.allclose(bias_dps, [0.8, -0.5, 0.3], atol=0.05)     # the emulator's configured bias


def test_calibrate_imu_out_is_checked_before_the_work(tmp_path, capsys):
    from stereopath.host.cli import main

    missing = f"session:{tmp_path / 'no-such-session'}"  # would fail too, but only after the --out check
    assert main(["device", "calibrate-imu", missing, "--out", str(tmp_path)]) == 2
    assert f"--out {tmp_path}: is a folder" in capsys.readouterr().err
    (tmp_path / "afile").write_text("x")
    assert main(["device", "calibrate-imu", missing, "--out", str(tmp_path / "afile" / "imu.yaml")]) == 2
    assert "afile: exists and is not a folder" in capsys.readouterr().err


def test_calibrate_imu_writes_into_a_new_folder_atomically(tmp_path, capsys):
    import yaml

    from stereopath.host.cli import main

    out = tmp_path / "new" / "sub" / "imu.yaml"
    assert main(["device", "calibrate-imu", "live", "--imu", "emulated", "--seconds", "0.5", "--out", str(out)]) == 0
    assert "gyro_bias_rad_s" in yaml.safe_load(out.read_text())
    # the calibration and its plot, no temporary file left
    assert sorted(p.name for p in out.parent.iterdir()) == ["imu.yaml", "imu_still_window.png"]


@pytest.mark.parametrize("window", ["nan:nan", "0:inf", "-inf:1", "0:1e300"])
def test_calibrate_imu_window_must_be_finite(window, capsys):
    from stereopath.host.cli import main

    assert main(["device", "calibrate-imu", "live", "--imu", "emulated", "--seconds", "0.2", f"--window={window}"]) == 2
    assert "must be finite times" in capsys.readouterr().err


@pytest.mark.parametrize("option, value", [("--seconds", "nan"), ("--seconds", "-1"), ("--min-still-s", "inf")])
def test_calibrate_imu_durations_must_be_finite_and_positive(option, value, capsys):
    from stereopath.host.cli import main

    with pytest.raises(SystemExit) as info:
        main(["device", "calibrate-imu", "live", "--imu", "emulated", option, value])
    assert info.value.code == 2
    assert f"argument {option}: must be a finite number of seconds above 0" in capsys.readouterr().err


def test_calibrate_stereo_out_is_checked_before_the_work(tmp_path, capsys):
    from stereopath.host.cli import main

    missing = str(tmp_path / "no-such-images")  # would fail too, but only after the --out check
    assert main(["device", "calibrate-stereo", missing, "--square-mm", "25", "--out", str(tmp_path)]) == 2
    assert f"--out {tmp_path}: is a folder; give the file to write, e.g. {tmp_path / 'rig.yaml'}" in \
        capsys.readouterr().err
    (tmp_path / "afile").write_text("x")
    assert main(["device", "calibrate-stereo", missing, "--square-mm", "25",
                 "--out", str(tmp_path / "afile" / "rig.yaml")]) == 2
    assert "afile: exists and is not a folder" in capsys.readouterr().err
