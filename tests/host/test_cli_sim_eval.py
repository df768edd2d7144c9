"""CLI smoke: ``stereopath eval`` and ``stereopath sim`` (round trip sim -> recorder -> reader)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from stereopath.host.cli import main


def test_eval_table_and_json(data_dir, capsys):
    d = data_dir / "trajectories"
    assert main(["eval", "--gt", str(d / "V101_gt.txt"), "--est", str(d / "V101_openvins.txt")]) == 0
    out = capsys.readouterr().out
    assert "ATE RMSE" in out and "accuracy (paper)" in out and "2760" in out
    assert main(["eval", "--gt", str(d / "V101_gt.txt"), "--est", str(d / "V101_openvins.txt"), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["n_associated"] == 2760 and 0.01 < res["ate_rmse_m"] < 0.2
    assert main(["eval", "--gt", str(d / "V101_gt.txt"), "--est", str(d / "V101_openvins.txt"),
                 "--max-diff", "0"]) == 2
    assert "--max-diff must be positive" in capsys.readouterr().err


def test_eval_kitti_files_with_times(data_dir, tmp_path, capsys):
    seq = data_dir / "kitti_odometry" / "sequences" / "06"
    gt = data_dir / "kitti_odometry" / "poses" / "06.txt"
    assert main(["eval", "--gt", str(gt), "--est", str(gt), "--times", str(seq / "times.txt"), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["n_associated"] == 51 and res["ate_rmse_m"] < 1e-9
    assert res["duration_s"] == pytest.approx(5.196, abs=0.01)  # the real times, not 10 Hz (5.0 s)


def test_eval_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.txt"
    bad.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 zero 0 0 0 1\n")
    assert main(["eval", "--gt", str(bad), "--est", str(bad)]) == 2
    assert "bad.txt:2" in capsys.readouterr().err
    assert main(["eval", "--gt", str(tmp_path / "missing.txt"), "--est", str(bad)]) == 2
    assert "not found" in capsys.readouterr().err


def test_sim_writes_a_session_that_reads_back_identically(tmp_path, capsys):
    from stereopath.device.sim import session as sim

    out = tmp_path / "sess"
    assert main(["sim", "--out", str(out), "--frames", "4", "--seed", "3"]) == 0
    assert "4 stereo frames" in capsys.readouterr().out
    assert (out / "groundtruth.tum").is_file() and (out / "manifest.json").is_file()

    from stereopath.device.formats import open_source

    back = open_source(f"session:{out}")
    ref = sim.open_sim(sim.SimConfig(frames=4, seed=3))
    assert len(back) == 4
    np.testing.assert_array_equal(back.t_ns, np.asarray(ref.t_ns)[:4])
    for a, b in zip(ref.frames(), back.frames()):
        assert a.t_ns == b.t_ns
        assert b.left.shape == (480, 640) and b.left.dtype == np.uint8
        np.testing.assert_array_equal(a.left, b.left)
        np.testing.assert_array_equal(a.right, b.right)
    np.testing.assert_array_equal(back.imu.t_ns, ref.imu.t_ns)
    np.testing.assert_array_equal(back.imu.gyro_rad_s, ref.imu.gyro_rad_s)
    np.testing.assert_array_equal(back.imu.accel_m_s2, ref.imu.accel_m_s2)
    gt = ref.groundtruth
    np.testing.assert_array_equal(back.groundtruth.t_ns, gt.t_ns)
    np.testing.assert_allclose(back.groundtruth.T_world_cam, gt.T_world_cam, atol=1e-8)
    np.testing.assert_allclose(back.rig.T, ref.rig.T, atol=1e-12)
    if ref.rig.T_body_cam0 is not None:
        np.testing.assert_allclose(back.rig.T_body_cam0, ref.rig.T_body_cam0, atol=1e-12)
    assert back.manifest["status"] == "closed" and back.manifest["configuration"]["source"] == "sim"
    again = open_source("sim:seed=3,frames=4")  # the same session straight from the simulator
    np.testing.assert_array_equal(again.t_ns, back.t_ns)


def test_sim_refuses_an_existing_session(tmp_path, capsys):
    (tmp_path / "x").write_text("keep me")
    assert main(["sim", "--out", str(tmp_path), "--frames", "1"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert (tmp_path / "x").read_text() == "keep me"


def test_eval_pose_file_mistakes_are_one_line(tmp_path, capsys):
    good = tmp_path / "good.txt"
    good.write_text("1 0 0 0.0 0 1 0 0 0 0 1 0\n1 0 0 0.1 0 1 0 0 0 0 1 0\n")
    nan = tmp_path / "nan.txt"
    nan.write_text("1 0 0 0.0 0 1 0 0 0 0 1 0\n1 0 0 nan 0 1 0 0 0 0 1 0\n")
    assert main(["eval", "--gt", str(good), "--est", str(nan)]) == 2
    assert "nan.txt:2: non-finite value" in capsys.readouterr().err
    assert main(["eval", "--gt", str(tmp_path), "--est", str(good)]) == 2
    assert "is a directory, expected a file" in capsys.readouterr().err
    (tmp_path / "bin.tum").write_bytes(b"\xff\xfe\x00\x01" * 16)
    assert main(["eval", "--gt", str(good), "--est", str(tmp_path / "bin.tum")]) == 2
    assert "not a UTF-8 text file" in capsys.readouterr().err
    assert main(["eval", "--gt", str(good), "--est", str(good), "--max-diff", "nan"]) == 2
    assert "--max-diff must be positive, got nan" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["nan", "inf", "-1"])
def test_sim_reserve_mb_must_be_finite_and_not_negative(tmp_path, capsys, value):
    with pytest.raises(SystemExit) as info:
        main(["sim", "--out", str(tmp_path / "s"), "--frames", "1", f"--reserve-mb={value}"])
    assert info.value.code == 2
    assert "argument --reserve-mb: must be a finite number of megabytes" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("argv, ours, root_at_most", [
    ([], logging.INFO, logging.INFO), (["-v"], logging.DEBUG, logging.INFO), (["-vv"], logging.DEBUG, logging.DEBUG),
    (["-q"], logging.WARNING, logging.WARNING),
])
def test_verbosity_options(argv, ours, root_at_most):
    """-v shows stereopath's debug messages, -vv everyone's, -q only warnings; the default is info."""
    import subprocess
    import sys

    code = ("import logging, sys; from stereopath.host.cli import build_parser, setup_logging; "
            "a = build_parser().parse_args(sys.argv[1:] + ['sim', '--out', 'x']); setup_logging(a.verbose, a.quiet); "
            "print(logging.getLogger('stereopath.device.core.rig').getEffectiveLevel(), logging.getLogger().level)")
    out = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, check=True).stdout.split()
    assert int(out[0]) == ours and int(out[1]) == root_at_most


def test_help_shows_each_options_default_once(capsys):
    """A default is shown after the option's help unless the help names it; none for empty lists or flags."""
    with pytest.raises(SystemExit):
        main(["demo", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "simulation seed (default: 0)" in text  # a default of 0 is still a default
    assert "(default: the full 5.12 m scan)" in text and "(default: the full 5.12 m scan) (default" not in text
    assert "skip the dense 3D model (default" not in text  # a flag
    with pytest.raises(SystemExit):
        main(["device", "install", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(repeatable)" in text and "(default: [])" not in text
    assert "(default: /usr/bin/python3)" in text
