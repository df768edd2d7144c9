"""Issue 39: numbers that parse but cannot be physical, configuration files the system cannot read, output
folders that are the root or a recorded session, and key files others may read or write."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from stereopath.device.errors import CalibrationError, ConfigError, DatasetError

from tests.device.test_faults_input import FRAMES, _copy, session  # noqa: F401  (a 12-frame simulated recording)

ROOT = Path(__file__).resolve().parents[2]


def _cli(argv: list[str]) -> int:
    from stereopath.host.cli import main

    return main(argv)




def _huge_tum(src: Path, dst: Path, line: int = 2) -> Path:
    """``src`` with the x of its ``line``-th data line set to 1e308 (a value that parses and overflows)."""
    rows = [r for r in src.read_text().splitlines() if r.strip() and not r.startswith("#")]
    parts = rows[line - 1].split()
    parts[1] = "1e308"
    rows[line - 1] = " ".join(parts)
    dst.write_text("\n".join(rows) + "\n")
    return dst


# item 3: pose files ---------------------------------------------------------------------------------

def test_pose_files_refuse_values_beyond_physical_bounds(tmp_path):
    from stereopath.device.formats.tum import read_kitti_poses, read_tum

    ok = "0.0 0 0 0 0 0 0 1\n"
    cases = {
        "far.tum": (ok + "0.1 1e308 0 0 0 0 0 1\n", r"far\.tum:2: position 1e\+308 m"),
        "unit.tum": (ok + "0.1 2e6 0 0 0 0 0 1\n", r"unit\.tum:2: position 2e\+06 m .* wrong unit"),
        "quat.tum": (ok + "0.1 0 0 0 0 0 0 1e308\n", r"quat\.tum:2: quaternion of length 1e\+308"),
        "half.tum": ("0.0 0 0 0 0 0 0 0.5\n", r"half\.tum:1: quaternion of length 0\.5"),
    }
    for name, (text, pattern) in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(DatasetError, match=pattern):
            read_tum(tmp_path / name)
    (tmp_path / "ok.tum").write_text(ok + "0.1 999999 0 0 0.0 0.0 0.7071 0.7071\n")
    assert len(read_tum(tmp_path / "ok.tum")) == 2
    eye = "1 0 0 0 0 1 0 0 0 0 1 0\n"
    (tmp_path / "k_far.txt").write_text(eye + "1 0 0 1e308 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match=r"k_far\.txt:2: position"):
        read_kitti_poses(tmp_path / "k_far.txt")
    (tmp_path / "k_rot.txt").write_text(eye + "1e308 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match=r"k_rot\.txt:2: rotation"):
        read_kitti_poses(tmp_path / "k_rot.txt")
    (tmp_path / "k_skew.txt").write_text("1 0.5 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match=r"k_skew\.txt:1: not a rotation matrix"):
        read_kitti_poses(tmp_path / "k_skew.txt")


def test_euroc_csv_groundtruth_is_bounded_too(tmp_path):
    from stereopath.device.formats.asl import _read_euroc_state_csv

    p = tmp_path / "data.csv"
    p.write_text("#t,x,y,z,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n10,0,1e308,0,1,0,0,0\n")
    with pytest.raises(DatasetError, match=r"data\.csv:3: position"):
        _read_euroc_state_csv(p)


def test_eval_stops_with_one_line_on_a_huge_groundtruth(session, tmp_path, capsys):
    bad = _huge_tum(session / "groundtruth.tum", tmp_path / "gt.tum")
    assert _cli(["eval", "--gt", str(bad), "--est", str(session / "groundtruth.tum")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "LinAlgError" not in err and f"{bad}:2: position" in err


def test_a_bad_optional_groundtruth_only_drops_the_errors(session, tmp_path, capsys):
    """odometry: the path and its files are written, the report says why there are no errors against the
    ground truth; host reprocess's reader sees the ground truth as unusable instead of overflowing."""
    from stereopath.device.formats.asl import open_session
    from stereopath.host.reprocess.outputs import groundtruth

    d = _copy(session, tmp_path)
    _huge_tum(session / "groundtruth.tum", d / "groundtruth.tum", line=3)
    out = tmp_path / "odo"
    assert _cli(["odometry", f"session:{d}", "--out", str(out)]) == 0
    assert (out / "trajectory.tum").is_file() and (out / "path.png").is_file()
    rep = json.loads((out / "report.json").read_text())
    assert "groundtruth.tum:3: position" in rep["extra"]["groundtruth_error"]
    assert rep.get("metrics") in (None, {}) or rep["metrics"].get("ate_rmse_m") is None
    gt, why = groundtruth(open_session(d))
    assert gt is None and "groundtruth.tum:3: position" in why


def test_host_map_refuses_huge_poses(session, tmp_path, capsys):
    bad = _huge_tum(session / "groundtruth.tum", tmp_path / "poses.tum", line=4)
    assert _cli(["host", "map", str(session), "--poses", str(bad), "--out", str(tmp_path / "map"),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"{bad}:4: position" in err and "Traceback" not in err
    assert not (tmp_path / "map" / "mesh.ply").exists()


# item 4: rig plausibility ---------------------------------------------------------------------------

def _paper_yaml() -> dict:
    return yaml.safe_load((ROOT / "firmware_cfg" / "rig_paper.yaml").read_text())


@pytest.mark.parametrize("change, pattern", [
    (lambda d: d["cam0"]["intrinsics"].__setitem__(0, 1e308), r"cam0\.K: fx = 1e\+308 px is implausible"),
    (lambda d: d["cam1"]["intrinsics"].__setitem__(1, 5.0), r"cam1\.K: fy = 5 px is implausible .* 480 px"),
    (lambda d: d["cam0"]["intrinsics"].__setitem__(2, 6400.0), r"cam0\.K: principal point cx = 6400 px lies outside"),
    (lambda d: d["cam0"]["intrinsics"].__setitem__(3, -1.0), r"cam0\.K: principal point cy = -1 px"),
    (lambda d: d.__setitem__("T_cam1_cam0_m", [-47.917, -0.142, -13.373]), r"T: baseline 49\.7\d* m is implausible"),
    (lambda d: d.__setitem__("T_cam1_cam0_m", [-0.0005, 0.0, 0.0]), r"T: baseline 0\.0005 m is implausible"),
    (lambda d: d["cam0"].__setitem__("distortion", [1e300, 0, 0, 0, 0]), r"cam0\.distortion: a coefficient beyond"),
])
def test_rig_yaml_refuses_implausible_values(tmp_path, change, pattern):
    from stereopath.device.formats.rig_files import load_rig_file, load_rig_yaml

    d = _paper_yaml()
    change(d)
    p = tmp_path / "rig.yaml"
    p.write_text(yaml.safe_dump(d))
    for load in (load_rig_yaml, load_rig_file):
        with pytest.raises(CalibrationError, match=pattern) as info:
            load(p)
        assert str(info.value).startswith(str(p)) and "\n" not in str(info.value)


def test_kitti_calib_names_file_and_matrix(tmp_path):
    from stereopath.device.formats.rig_files import load_kitti_calib

    p = tmp_path / "calib.txt"
    p.write_text("P0: 1e308 0 600 0 0 700 180 0 0 0 1 0\nP1: 700 0 600 -380 0 700 180 0 0 0 1 0\n")
    with pytest.raises(CalibrationError, match=rf"^{p}: P0\.K: fx = 1e\+308"):
        load_kitti_calib(p, (1241, 376))


def test_every_shipped_and_shared_rig_still_loads(data_dir):
    """The bounds leave every real calibration alone: the shipped rig, the simulator's, KITTI, EuRoC,
    Middlebury's cameras and a chessboard calibration of the shared images."""
    from stereopath.device.core.rig import make_camera, paper_rig
    from stereopath.device.formats.rig_files import load_euroc_calibration, load_kitti_calib, load_rig_yaml
    from stereopath.device.sim.session import SimConfig, open_sim

    rigs = [load_rig_yaml(ROOT / "firmware_cfg" / "rig_paper.yaml"), paper_rig(), open_sim(SimConfig(frames=2)).rig]
    seq = data_dir / "kitti_odometry" / "sequences" / "06"
    if seq.is_dir():
        rigs.append(load_kitti_calib(seq / "calib.txt", (1226, 370)))
    mav0 = data_dir / "euroc_v1_01_head" / "mav0"
    if mav0.is_dir():
        rigs.append(load_euroc_calibration(mav0).rig)
    assert all(0.001 <= r.baseline_m <= 10 for r in rigs)
    # the TUM VI-like rig of the README and a 1/10-scale preview camera
    make_camera("cam0", np.array([[190.0, 0, 255.5], [0, 190.0, 255.5], [0, 0, 1]]), None, (512, 512))
    make_camera("cam0", np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]]), None, (64, 48))


def test_device_run_refuses_a_rig_with_a_huge_focal_length(tmp_path):
    from stereopath.device.service.main import run_service
    from stereopath.device.service.options import RunOptions
    from stereopath.device.service.service import EXIT_CONFIG

    d = _paper_yaml()
    d["cam0"]["intrinsics"][0] = 1e308
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(d))
    (tmp_path / "device.toml").write_text(f'[source]\nrig_file = "{tmp_path / "rig.yaml"}"\n')
    opts = RunOptions(source="sim", frames=2, stream=False, status_file="", out=str(tmp_path / "s"))
    assert run_service(tmp_path / "device.toml", opts) == EXIT_CONFIG
    assert not (tmp_path / "s" / "mav0").exists()


# item 5: device.toml that the system or the parser cannot read ------------------------------------------

def _device_toml_cases(tmp_path: Path) -> dict[str, Path]:
    cases = {
        "long_rig_file": '[source]\nbackend = "sim"\nrig_file = "' + "a" * 300 + '"\n',
        "nested_arrays": "x = " + "[" * 2000 + "]" * 2000 + "\n",
        "nested_tables": "x = " + "{a=" * 5000 + "1" + "}" * 5000 + "\n",
    }
    out = {}
    for name, text in cases.items():
        out[name] = tmp_path / f"{name}.toml"
        out[name].write_text(text)
    out["binary"] = tmp_path / "binary.toml"
    out["binary"].write_bytes(b"\xff\xfe[source]\n")
    out["folder"] = tmp_path / "folder.toml"
    out["folder"].mkdir()
    out["long_name"] = tmp_path / ("c" * 300 + ".toml")
    return out


def test_device_toml_errors_are_configuration_errors(tmp_path, capsys):
    from stereopath.device.service.main import run_service
    from stereopath.device.service.options import RunOptions
    from stereopath.device.service.service import EXIT_CONFIG

    for name, path in _device_toml_cases(tmp_path).items():
        opts = RunOptions(source="sim", frames=2, stream=False, status_file="", out=str(tmp_path / f"s_{name}"))
        assert run_service(path, opts) == EXIT_CONFIG, name
        assert _cli(["device", "selftest", "--config", str(path), "--source", "sim", "--frames", "3"]) == EXIT_CONFIG, name
        err = capsys.readouterr().err
        assert "Traceback" not in err and "configuration error" in err, (name, err[-500:])


def test_a_fifo_as_device_toml_is_refused_without_blocking(tmp_path):
    import threading

    from stereopath.device.core.config import load_toml

    fifo = tmp_path / "device.toml"
    os.mkfifo(fifo)
    got: list[BaseException] = []

    def load() -> None:
        try:
            load_toml(fifo)
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            got.append(exc)

    t = threading.Thread(target=load, daemon=True)
    t.start()
    t.join(5.0)
    if t.is_alive():  # blocked in open(): a writer releases it
        fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        os.close(fd)
        t.join(5.0)
    assert got and isinstance(got[0], ConfigError) and "not a regular file" in str(got[0])


# item 7: --out ----------------------------------------------------------------------------------------

def test_out_refuses_root_and_recorded_sessions_for_every_command(session, tmp_path, capsys):
    from stereopath.device.formats.fileio import check_out_file, check_out_folder

    d = _copy(session, tmp_path)
    before = sorted(str(p.relative_to(d)) for p in d.rglob("*"))
    inside = d / "mav0" / "cam0"
    commands = {
        "reprocess": lambda out: ["host", "reprocess", str(session), "--out", out, "--no-progress"],
        "map": lambda out: ["host", "map", str(session), "--out", out, "--no-progress"],
        "odometry": lambda out: ["odometry", "sim", "--frames", "3", "--out", out],
        "sim": lambda out: ["sim", "--frames", "2", "--out", out],
        "demo": lambda out: ["demo", "--out", out],
        "live": lambda out: ["host", "live", "--device", "127.0.0.1", "--insecure", "--out", out, "--duration", "1"],
        "keys": lambda out: ["keys", "generate", out, "--name", "x"],
        "calibrate-stereo": lambda out: ["device", "calibrate-stereo", str(tmp_path), "--board", "9x6",
                                         "--square-mm", "25", "--out", str(Path(out) / "rig.yaml")],
        "calibrate-imu": lambda out: ["device", "calibrate-imu", f"session:{session}",
                                      "--out", str(Path(out) / "imu.yaml")],
    }
    for name, argv in commands.items():
        for out, rule in ((str(inside), "is inside the recorded session"), (str(d / "new"), "is inside the recorded "
                          "session"), (str(d), "holds a recorded session")):
            assert _cli(argv(out)) == 2, (name, out)
            err = capsys.readouterr().err
            assert rule in err and "the rule" in err and "Traceback" not in err, (name, out, err[-400:])
    assert sorted(str(p.relative_to(d)) for p in d.rglob("*")) == before
    # the root: with inputs that do not exist, so that a command without the rule stops before writing in /
    missing = tmp_path / "missing"
    for argv in (["host", "reprocess", str(missing), "--out", "/"], ["host", "map", str(missing), "--out", "/"],
                 ["odometry", f"session:{missing}", "--out", "/"]):
        assert _cli(argv) == 2
        err = capsys.readouterr().err
        assert "/: is the file system root; the rule" in err, err[-300:]
    for out in ("/", "/tmp/..", "//"):
        with pytest.raises(ConfigError, match="is the file system root"):
            check_out_folder(out)
    with pytest.raises(ConfigError, match="is inside the recorded session"):
        check_out_file(inside / "x.yaml")
    link = tmp_path / "link"
    link.symlink_to(inside)
    with pytest.raises(ConfigError, match="is inside the recorded session"):
        check_out_folder(link)
    check_out_folder(tmp_path / "fresh")  # beside the session: fine


def test_device_run_refuses_an_out_inside_a_session(session, tmp_path):
    from stereopath.device.service.main import run_service
    from stereopath.device.service.options import RunOptions
    from stereopath.device.service.service import EXIT_CONFIG

    d = _copy(session, tmp_path)
    opts = RunOptions(source="sim", frames=2, stream=False, status_file="", out=str(d / "mav0" / "again"))
    assert run_service(None, opts) == EXIT_CONFIG
    assert not (d / "mav0" / "again").exists()


# item 8: key files --------------------------------------------------------------------------------------

def test_secret_keys_and_clients_dir_are_refused_when_others_may_use_them(tmp_path):
    pytest.importorskip("zmq.auth")
    from stereopath.device.wire.security import authorized_keys, load_secret_keypair, make_demo_keys

    keys = make_demo_keys(tmp_path / "k")
    load_secret_keypair(keys.device_secret)
    authorized_keys(keys.clients_dir)
    os.chmod(keys.device_secret, 0o644)
    with pytest.raises(ConfigError, match=rf"mode 0644.*chmod 600 {keys.device_secret}$"):
        load_secret_keypair(keys.device_secret)
    os.chmod(keys.device_secret, 0o600)
    link = tmp_path / "link.key_secret"
    link.symlink_to(keys.device_secret)
    os.chmod(link, 0o600)
    load_secret_keypair(link)
    os.chmod(keys.device_secret, 0o640)  # through the link: the target's mode guards the key
    with pytest.raises(ConfigError, match=rf"through the link {link}.*chmod 600 {keys.device_secret}$"):
        load_secret_keypair(link)
    os.chmod(keys.clients_dir, 0o777)
    with pytest.raises(ConfigError, match=rf"folder {keys.clients_dir} is writable by group/others .*"
                                          rf"chmod go-w {keys.clients_dir}$"):
        authorized_keys(keys.clients_dir)
    os.chmod(keys.clients_dir, 0o755)
    os.chmod(keys.clients_dir / "host.key", 0o666)
    with pytest.raises(ConfigError, match=r"chmod go-w .*host\.key$"):
        authorized_keys(keys.clients_dir)


# item 9: recorder.dir that is a file ----------------------------------------------------------------------

def test_recorder_dir_that_is_a_file(tmp_path, capsys):
    from stereopath.device.service.main import run_service
    from stereopath.device.service.options import RunOptions
    from stereopath.device.service.service import EXIT_CONFIG

    afile = tmp_path / "afile"
    afile.write_text("keep")
    cfg = tmp_path / "device.toml"
    cfg.write_text(f'[recorder]\ndir = "{afile}"\n')
    assert run_service(cfg, RunOptions(source="sim", frames=2, stream=False, status_file="")) == EXIT_CONFIG
    assert _cli(["device", "selftest", "--config", str(cfg), "--source", "sim", "--frames", "3"]) == 1
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("free disk"))
    assert "FAIL" in row and f"{afile} is not a folder" in row
    cfg.write_text(f'[recorder]\ndir = "{afile / "below"}"\n')
    assert run_service(cfg, RunOptions(source="sim", frames=2, stream=False, status_file="")) == EXIT_CONFIG
    assert afile.read_text() == "keep"


# found by benchmarks/bench_fuzz.py ------------------------------------------------------------------------

def test_fuzz_findings_end_in_one_line(session, tmp_path, capsys):
    """An integer beyond any float in a rig, YAML and JSON nested too deeply, and poses none of which is near a
    frame's time: each was a traceback (OverflowError, RecursionError, ValueError)."""
    from stereopath.device.formats.asl import open_session
    from stereopath.device.formats.rig_files import load_rig_file, load_rig_yaml

    d = _paper_yaml()
    d["cam0"]["intrinsics"][0] = int("9" * 400)
    (tmp_path / "int.yaml").write_text(yaml.safe_dump(d))
    with pytest.raises(CalibrationError, match=r"int\.yaml: cam0\.intrinsics must be numbers"):
        load_rig_yaml(tmp_path / "int.yaml")
    d = _paper_yaml()
    d["cam0"]["image_size"] = [int("9" * 400), 480]
    (tmp_path / "size.yaml").write_text(yaml.safe_dump(d))
    with pytest.raises(CalibrationError, match=r"cam0\.image_size"):
        load_rig_yaml(tmp_path / "size.yaml")
    (tmp_path / "deep.yaml").write_text("cam0: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(CalibrationError, match=r"deep\.yaml: invalid YAML: collections nested too deeply"):
        load_rig_file(tmp_path / "deep.yaml")
    s = _copy(session, tmp_path)
    (s / "manifest.json").write_text('{"a": ' + "[" * 100000 + "]" * 100000 + "}")
    assert len(open_session(s)) == FRAMES  # the manifest only describes the recording: ignored, with a warning
    late = tmp_path / "late.tum"
    late.write_text("".join(f"{1000 + i}.0 0 0 0 0 0 0 1\n" for i in range(5)))  # no pose near any frame
    assert _cli(["host", "map", str(session), "--poses", str(late), "--out", str(tmp_path / "m"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "stereopath: error:" in err


def test_a_rounded_kitti_rotation_is_projected_not_a_traceback(tmp_path, capsys):
    """A KITTI rotation within the reader's 1e-2 of orthonormal but beyond evo's 1e-6 (a LieAlgebraException)."""
    rows = []
    for i in range(10):
        a = 0.05 * i
        c, s = np.cos(a), np.sin(a)
        rows.append([c, -s, 0, 0.1 * i, s, c, 0, 0.02 * i * i, 0, 0, 1, 0.01 * i])
    (tmp_path / "est.txt").write_text("".join(" ".join(f"{v:.9f}" for v in r) + "\n" for r in rows))
    rows[3][1] += 0.002
    (tmp_path / "gt.txt").write_text("".join(" ".join(f"{v:.9f}" for v in r) + "\n" for r in rows))
    assert _cli(["eval", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt")]) == 0
    assert "Traceback" not in capsys.readouterr().err
