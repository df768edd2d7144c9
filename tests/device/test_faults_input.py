"""Issue 15: bad input never discards finished work, and one bad frame does not abort a run."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from stereopath.device.errors import DatasetError

FRAMES = 12
BAD = 5


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim

    d = tmp_path_factory.mktemp("faults") / "session"
    record_sequence(open_sim(SimConfig(frames=FRAMES)), d, config_dict={"source": "sim"})
    return d


def _copy(session: Path, tmp_path: Path) -> Path:
    d = tmp_path / "session"
    shutil.copytree(session, d)
    return d


def _break_frame(d: Path, i: int = BAD) -> Path:
    img = sorted((d / "mav0" / "cam0" / "data").glob("*.png"))[i]
    img.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)  # a torn image file
    return img


def _cli(argv):
    from stereopath.host.cli import main

    return main(argv)


# item 9 -----------------------------------------------------------------------------------------

def test_reprocess_with_bad_groundtruth_warns_and_writes_results(session, tmp_path, capsys):
    d = _copy(session, tmp_path)
    (d / "groundtruth.tum").write_text("1 2 3\nnot a pose\n")
    out = tmp_path / "out"
    rc = _cli(["host", "reprocess", str(d), "--out", str(out), "--preset", "quick", "--no-map", "--no-progress"])
    assert rc == 0
    assert (out / "trajectory.tum").is_file() and (out / "report.html").is_file()
    rep = json.loads((out / "report.json").read_text())
    assert "groundtruth.tum:1" in rep["extra"]["groundtruth_error"]
    out = capsys.readouterr()
    assert "warning: ground truth not used" in out.err and "ground truth" not in out.out


def test_reprocess_with_a_damaged_onboard_path_and_manifest_warns_and_writes_results(session, tmp_path, caplog):
    """The on-board path (before figures only) and the manifest (a description) damaged: the images and the
    IMU are reprocessed as ever, each damage named in a warning."""
    import logging

    d = _copy(session, tmp_path)
    (d / "trajectory.tum").write_text("0.0 0 0 0 0 0 0 1\ngarbage line\n0.1 0 0 0 0 0 0 1\n")
    (d / "manifest.json").write_text('{"status": "closed", ')
    out = tmp_path / "out"
    caplog.set_level(logging.WARNING)
    rc = _cli(["host", "reprocess", str(d), "--out", str(out), "--preset", "quick", "--no-map", "--no-progress"])
    assert rc == 0
    assert (out / "trajectory.tum").is_file() and (out / "report.html").is_file()
    assert "on-board path not used" in caplog.text and "trajectory.tum:2" in caplog.text
    assert "manifest.json: invalid JSON, ignored" in caplog.text


# item 10 ----------------------------------------------------------------------------------------

def test_odometry_skips_and_counts_a_bad_frame_and_strict_stops(session, tmp_path, capsys):
    d = _copy(session, tmp_path)
    _break_frame(d)
    out = tmp_path / "odo"
    assert _cli(["odometry", f"session:{d}", "--out", str(out)]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["extra"]["frames_skipped"] == 1 and rep["extra"]["skipped_frame_indexes"] == [BAD]
    assert "skipped 1 unreadable frame" in capsys.readouterr().err
    assert _cli(["odometry", f"session:{d}", "--out", str(tmp_path / "strict"), "--strict"]) == 2
    err = capsys.readouterr().err
    assert "cannot be decoded" in err and f"frame {BAD}" in err


def test_reprocess_skips_a_bad_frame(session, tmp_path):
    from stereopath.host.reprocess.pipeline import RunChoices, reprocess_session

    d = _copy(session, tmp_path)
    _break_frame(d)
    res = reprocess_session(d, tmp_path / "out", preset="quick", run=RunChoices(do_map=False, progress=False))
    assert res.report["extra"]["frames_skipped"] == 1
    assert (tmp_path / "out" / "trajectory.tum").is_file()
    with pytest.raises(DatasetError, match="cannot be decoded"):
        reprocess_session(d, tmp_path / "out2", preset="quick", run=RunChoices(do_map=False, progress=False), strict=True)


def test_map_skips_a_bad_keyframe_image(session, tmp_path):
    from stereopath.host.mapping.mapper import KeyframeSelection, build_map, map_preset, open_map_input

    d = _copy(session, tmp_path)
    _break_frame(d)
    cfg = map_preset("object")
    gt = d / "groundtruth.tum"
    inp = open_map_input(d, KeyframeSelection(stride=1), poses=gt)
    n = len(inp.keyframes)
    res = build_map(inp, cfg, progress=False)
    assert res.stats["keyframes_skipped"] == 1 and res.stats["keyframes"] == n - 1
    with pytest.raises(DatasetError, match="cannot be decoded"):
        build_map(open_map_input(d, KeyframeSelection(stride=1), poses=gt), cfg, progress=False, strict=True)


def test_replay_skips_a_bad_frame(session, tmp_path):
    from stereopath.device.capture.sources import create_source
    from stereopath.device.core.config import from_mapping
    from stereopath.device.settings import SourceSettings

    d = _copy(session, tmp_path)
    _break_frame(d)
    src = create_source(from_mapping(SourceSettings, {"backend": "replay", "replay": {"path": f"session:{d}"}}))
    with src:
        got = [f.meta["index"] for f in src]
    assert got == [i for i in range(FRAMES) if i != BAD]
    assert src.stats.dropped_sensor == 1


# item 11: map --max-keyframes on stored keyframes -------------------------------------------------

def test_map_max_keyframes_applies_to_keyframe_folders(session, tmp_path):
    from stereopath.device.formats.rig_files import save_rig_yaml
    from stereopath.device.formats import open_source
    from stereopath.device.wire.protocol import encode_keyframe, make_keyframe, rig_reference
    from stereopath.host.live.store import KeyframeStore
    from stereopath.host.mapping.mapper import KeyframeSelection, open_map_input

    seq = open_source(f"session:{session}")
    store = KeyframeStore(tmp_path / "live", fsync=False)
    for k in range(6):
        fr = seq.frame(k)
        T = np.eye(4)
        T[0, 3] = 0.01 * k
        kf = make_keyframe("sessX", k, k, int(seq.t_ns[k]), T, (fr.left, fr.right), rig_reference(seq.rig), "png")
        store.put(kf, encode_keyframe(kf))
    store.close()
    kdir = tmp_path / "live" / "sessX" / "keyframes"
    save_rig_yaml(seq.rig, kdir / "rig.yaml")
    assert len(open_map_input(kdir, KeyframeSelection()).keyframes) == 6
    assert len(open_map_input(kdir, KeyframeSelection(max_keyframes=3)).keyframes) == 3


# item 7: bad rigs, exchanged images, degenerate evaluations --------------------------------------

def test_rig_with_cam1_left_of_cam0_is_refused(tmp_path):
    import yaml

    from stereopath.device.formats.rig_files import load_rig_yaml
    from stereopath.device.errors import CalibrationError

    src = Path(__file__).resolve().parents[2] / "firmware_cfg" / "rig_paper.yaml"
    data = yaml.safe_load(src.read_text())
    load_rig_yaml(src)  # the shipped rig is fine
    flipped = dict(data, T_cam1_cam0_m=[-v for v in data["T_cam1_cam0_m"]])  # a negative baseline
    (tmp_path / "neg.yaml").write_text(yaml.safe_dump(flipped))
    with pytest.raises(CalibrationError, match="LEFT of cam0"):
        load_rig_yaml(tmp_path / "neg.yaml")
    R = np.array(data["R_cam1_cam0"], float)
    T = np.array(data["T_cam1_cam0_m"], float)
    inv = dict(data, R_cam1_cam0=R.T.tolist(), T_cam1_cam0_m=(-R.T @ T).tolist())  # T_cam0_cam1 given instead
    (tmp_path / "inv.yaml").write_text(yaml.safe_dump(inv))
    with pytest.raises(CalibrationError, match="exchanged"):
        load_rig_yaml(tmp_path / "inv.yaml")


def test_swapped_image_folders_are_detected(session, tmp_path, capsys):
    d = _copy(session, tmp_path)
    m = d / "mav0"
    (m / "cam0").rename(m / "tmp")
    (m / "cam1").rename(m / "cam0")
    (m / "tmp").rename(m / "cam1")
    for f in ("sensor.yaml",):  # keep each camera's calibration with its folder name
        a, b = (m / "cam0" / f), (m / "cam1" / f)
        if a.exists() and b.exists():
            ta, tb = a.read_bytes(), b.read_bytes()
            a.write_bytes(tb)
            b.write_bytes(ta)
    assert _cli(["odometry", f"session:{d}", "--out", str(tmp_path / "o")]) == 2
    assert "left and right images look swapped" in capsys.readouterr().err
    assert _cli(["odometry", f"session:{session}", "--out", str(tmp_path / "ok")]) == 0


def test_eval_on_a_path_that_never_moves_is_a_clear_error(session, tmp_path, capsys):
    from stereopath.device.formats.tum import Trajectory, read_tum, write_tum

    gt = read_tum(session / "groundtruth.tum")
    still = Trajectory(gt.t_ns, np.repeat(np.eye(4)[None], len(gt), axis=0))
    write_tum(tmp_path / "still.tum", still)
    rc = _cli(["eval", "--gt", str(session / "groundtruth.tum"), "--est", str(tmp_path / "still.tum")])
    err = capsys.readouterr().err
    assert rc == 2 and "estimated path does not move" in err and "Traceback" not in err
    line = Trajectory(gt.t_ns, gt.T_world_cam.copy())
    line.T_world_cam[:, :3, 3] = np.outer(np.linspace(0, 1, len(gt)), [1.0, 0.0, 0.0])  # a straight line
    write_tum(tmp_path / "line.tum", line)
    rc = _cli(["eval", "--gt", str(session / "groundtruth.tum"), "--est", str(tmp_path / "line.tum")])
    assert rc in (0, 2) and "Traceback" not in capsys.readouterr().err


def test_outputs_never_replace_the_recording(session, tmp_path, capsys):
    """--out naming the session itself would replace its on-board trajectory.tum (which no rerun can give back)
    and, for the odometry, estimator.json: refused before any work, for one session, the fleet (DIR/<id>/ is the
    session when DIR holds it) and the library call."""
    from stereopath.device.errors import ConfigError
    from stereopath.host.fleet.sessions import session_id
    from stereopath.host.reprocess.pipeline import reprocess_session

    d = tmp_path / session_id(session)  # a folder named as the fleet names its output folders
    shutil.copytree(session, d)
    (d / "trajectory.tum").write_text("0.0 0 0 0 0 0 0 1\n")
    before = {p.name: p.read_bytes() for p in d.iterdir() if p.is_file()}
    for argv in (["host", "reprocess", str(d), "--out", str(d)], ["odometry", f"session:{d}", "--out", str(d)]):
        assert _cli(argv) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and f"is the input folder {d}" in err
    assert _cli(["host", "reprocess", str(d), str(d), "--out", str(tmp_path), "--cpus", "1"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and f"output folder {d}: is the input folder {d}" in err
    assert f"e.g. {tmp_path.parent / 'reprocessed'}" in err  # another folder, not one inside the sessions'
    with pytest.raises(ConfigError, match="is the input folder"):
        reprocess_session(d, d / ".." / d.name)
    assert {p.name: p.read_bytes() for p in d.iterdir() if p.is_file()} == before


def test_host_sessions_on_a_recorded_session_says_what_it_is(session, capsys):
    """A device session folder is not a `host live` store: its mav0/ used to be listed as a session (exit 0)."""
    assert _cli(["host", "sessions", str(session)]) == 2
    err = capsys.readouterr().err
    assert "is a session the device recorded, not the --out folder of `host live`" in err


def test_an_out_holding_a_recorded_session_is_refused(session, tmp_path, capsys):
    """`odometry euroc:S/mav0 --out S` names the session by its mav0: the folder holding mav0/ is refused too."""
    d = _copy(session, tmp_path)
    before = {p.name: p.read_bytes() for p in d.iterdir() if p.is_file()}
    for argv in (["odometry", f"euroc:{d / 'mav0'}", "--out", str(d)],
                 ["host", "reprocess", str(session), "--out", str(d)]):
        assert _cli(argv) == 2
        err = capsys.readouterr().err
        assert f"--out {d}: holds a recorded session (mav0/)" in err and f"{d}-out" in err
    assert {p.name: p.read_bytes() for p in d.iterdir() if p.is_file()} == before
