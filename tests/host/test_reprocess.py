"""`stereopath host reprocess`: outputs, improvement over the re-estimate, resume, bad input."""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from stereopath.device.errors import CalibrationError, ConfigError, DatasetError
from stereopath.host.reprocess.pipeline import REPROCESS_PRESETS, RunChoices, reprocess_session
from stereopath.host.evaluation.report import REPORT_KEYS

FRAMES = 60
OUTPUTS = ("trajectory.tum", "report.json", "path.png", "errors.png", "mesh.ply", "cloud.ply", "model.png",
           "map.json", "report.html")


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    """A short simulated session (what `stereopath sim --out DIR --frames 60` writes)."""
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim

    d = tmp_path_factory.mktemp("reprocess") / "session"
    man = record_sequence(open_sim(SimConfig(frames=FRAMES)), d, config_dict={"source": "sim"})
    assert man["status"] == "closed"
    return d


@pytest.fixture(scope="module")
def session_with_onboard(session, tmp_path_factory) -> Path:
    """The same session with an on-board path in trajectory.tum (a coarse one: every other frame)."""
    from stereopath.device.formats.tum import write_tum
    from stereopath.host.evaluation.odometry import estimate_sequence
    from stereopath.device.formats.source import open_source

    d = tmp_path_factory.mktemp("reprocess") / "with_onboard"
    shutil.copytree(session, d)
    run = estimate_sequence(open_source(f"session:{d}"), "stereo", options={"asift": {"enabled": False}},
                            progress=False)
    write_tum(d / "trajectory.tum", run.trajectory)
    return d


@pytest.fixture(scope="module")
def full_run(session, tmp_path_factory):
    """One uninterrupted reprocessing of the session (the reference for the other tests)."""
    out = tmp_path_factory.mktemp("reprocess") / "full"
    seen: list[str] = []
    res = reprocess_session(session, out, run=RunChoices(progress=False, after_stage=seen.append))
    return out, res, seen


def _mtimes(stages: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in sorted(stages.glob("*.npz"))}


def _no_temp_files(root: Path) -> None:
    leftovers = [p for p in root.rglob("*") if ".tmp" in p.name]
    assert leftovers == []


@pytest.mark.slow

def _stopped_after_tracks(done: Path, stages: Path) -> Path:
    """``stages`` holding ``done``'s estimate and tracks stages only, as a run stopped after them leaves it."""
    stages.mkdir(parents=True)
    for name in ("estimate.npz", "tracks.npz"):
        shutil.copy2(done / name, stages / name)
    man = json.loads((done / "manifest.json").read_text())
    man["stages"] = {k: v for k, v in man["stages"].items() if k in ("estimate", "tracks")}
    (stages / "manifest.json").write_text(json.dumps(man))
    return stages

def test_reprocess_writes_every_output_and_improves_the_path(full_run):
    out, res, seen = full_run
    assert seen == ["estimate", "tracks", "ba", "map"]
    assert res.stages == {"estimate": "computed", "tracks": "computed", "ba": "computed", "map": "computed"}
    for name in OUTPUTS:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    _no_temp_files(out)
    rep = json.loads((out / "report.json").read_text())
    assert all(k in rep for k in REPORT_KEYS)
    assert rep["estimator"] == "stereo+ba" and rep["frames"] == FRAMES
    ba = rep["extra"]["before_after"]
    assert ba["onboard"] is None  # a simulated session carries no on-board path
    before, after = ba["reestimated"]["ate_rmse_m"], ba["bundle_adjusted"]["ate_rmse_m"]
    assert after == pytest.approx(rep["ate_rmse_m"])
    assert after <= before  # bundle adjustment improves (or keeps) the path
    assert ba["ate_ratio_vs_reestimated"] == pytest.approx(after / before)
    assert rep["extra"]["bundle_adjustment"]["rms_after_px"] < rep["extra"]["bundle_adjustment"]["rms_before_px"]
    # a refined rig for the device exactly when the adjustment applied a disparity offset
    applied = rep["extra"]["bundle_adjustment"]["disparity_offset_px"] != 0.0
    assert (rep["extra"]["rig_refined"] is not None) == applied == (out / "rig_refined.yaml").is_file()
    # a 60-frame arc never comes back: no loop, but the loop entry says so with the end-to-start figures
    imu = rep["extra"]["bundle_adjustment"]["imu"]  # the simulated session's IMU is in the adjustment
    assert imu["factors"] >= 1 and len(imu["biases"]["accel_m_s2"]) == len(imu["biases"]["t_ns"]) >= 2
    assert imu["noise"]["accel_random_walk"] == pytest.approx(1e-3)  # what the simulator records (and draws)
    loops = rep["extra"]["loops"]
    assert loops["accepted"] == []
    gap = loops["end_to_start"]["bundle_adjusted"]["distance_m"]
    assert gap > 0.1 and loops["end_to_start_error_m"]["bundle_adjusted"] < 0.01
    from stereopath.device.formats.tum import read_tum

    traj = read_tum(out / "trajectory.tum")
    assert len(traj) == FRAMES and np.all(np.isfinite(traj.T_world_cam))
    html = (out / "report.html").read_text()
    for img in ("path.png", "errors.png", "model.png"):
        assert f"src='{img}'" in html
    assert "bundle adjusted" in html
    man = json.loads((out / "stages" / "manifest.json").read_text())
    assert set(man["stages"]) == {"estimate", "tracks", "ba", "map"}
    for name, st in man["stages"].items():  # each stage's CPU time (all threads) beside its wall time
        assert 0 < st["cpu_seconds"] <= st["seconds"] * (os.cpu_count() or 1) + 1.0, name
    steps = {name: st.get("cpu_steps", {}) for name, st in man["stages"].items()}
    assert set(steps["tracks"]) == {"keyframe_features", "track_matching", "loops"}
    assert set(steps["ba"]) == {"bundle_adjustment", "frame_refinement"}
    for name in ("tracks", "ba"):  # the named steps are parts of the stage's CPU time
        assert all(v >= 0 for v in steps[name].values())
        assert sum(steps[name].values()) <= man["stages"][name]["cpu_seconds"] + 0.01, name


def test_rerun_reuses_every_stage_and_gives_identical_outputs(full_run, session):
    out, _, _ = full_run
    traj_before = (out / "trajectory.tum").read_bytes()
    mt = _mtimes(out / "stages")
    seen: list[str] = []
    res = reprocess_session(session, out, run=RunChoices(progress=False, after_stage=seen.append))
    assert seen == [] and set(res.stages.values()) == {"reused"}
    assert _mtimes(out / "stages") == mt
    assert (out / "trajectory.tum").read_bytes() == traj_before


@pytest.mark.slow
@pytest.mark.parametrize("min_px", [0.0, 1.0])
def test_the_refined_rig_is_written_only_when_a_disparity_offset_was_applied(full_run, session, tmp_path, min_px,
                                                                            monkeypatch):
    """Threshold 0 (and no significance test): any offset is applied -> rig_refined.yaml, the session's
    rig with cam1.cx moved by it; threshold 1 px: none is -> no file (an earlier run's is removed) and
    ``rig_refined: null``."""
    import dataclasses

    from stereopath.host.backend import gtsam_ba

    monkeypatch.setattr(gtsam_ba, "OFFSET_SIGNIFICANCE", 0.0)
    from stereopath.device.formats.rig_files import load_rig_yaml
    from stereopath.device.formats.source import open_source

    out, _, _ = full_run
    shutil.copytree(out / "stages", tmp_path / "stages")  # the estimate and tracks stages are reused
    (tmp_path / "rig_refined.yaml").write_text("# an earlier run's\n")
    preset = dataclasses.replace(REPROCESS_PRESETS["standard"],
                                 ba=dataclasses.replace(REPROCESS_PRESETS["standard"].ba, disparity_offset_min_px=min_px),
                                 refine_frames=False)
    res = reprocess_session(session, tmp_path, preset=preset, run=RunChoices(do_map=False, progress=False))
    assert res.stages["estimate"] == res.stages["tracks"] == "reused" and res.stages["ba"] == "computed"
    off = res.report["extra"]["bundle_adjustment"]["disparity_offset_px"]
    entry = json.loads((tmp_path / "report.json").read_text())["extra"]["rig_refined"]
    if min_px > 0:
        assert off == 0.0 and entry is None
        assert not (tmp_path / "rig_refined.yaml").exists() and "rig_refined.yaml" not in res.files
        return
    assert off != 0.0 and entry["disparity_offset_px"] == off and "rig_refined.yaml" in res.files
    rig, refined = open_source(f"session:{session}").rig, load_rig_yaml(tmp_path / "rig_refined.yaml")
    assert refined.cam1.cx == pytest.approx(rig.cam1.cx + off, abs=1e-9)
    assert np.array_equal(refined.cam0.K, rig.cam0.K) and np.array_equal(refined.cam1.dist, rig.cam1.dist)
    assert np.allclose(refined.T_body_cam0, rig.T_body_cam0) and np.allclose(refined.R, rig.R)
    assert str(session) in (tmp_path / "rig_refined.yaml").read_text()
    assert "href='rig_refined.yaml'" in (tmp_path / "report.html").read_text()


@pytest.mark.slow
def test_resume_after_an_interruption(full_run, session, tmp_path):
    ref_out, ref, _ = full_run
    out = tmp_path / "out"
    seen: list[str] = []

    def stop_after_ba(name: str) -> None:
        seen.append(name)
        if name == "ba":
            raise KeyboardInterrupt

    # the uninterrupted run's first two stages, as if an earlier run had stopped after them; this
    # run computes the bundle adjustment and is stopped as it finishes
    stages = _stopped_after_tracks(ref_out / "stages", out / "stages")
    with pytest.raises(KeyboardInterrupt):
        reprocess_session(session, out, run=RunChoices(progress=False, after_stage=stop_after_ba))
    assert seen == ["ba"]
    assert sorted(p.name for p in stages.iterdir()) == ["ba.npz", "estimate.npz", "manifest.json", "tracks.npz"]
    assert not (out / "trajectory.tum").exists()
    _no_temp_files(out)
    mt = _mtimes(stages)
    seen.clear()
    res = reprocess_session(session, out, run=RunChoices(progress=False, after_stage=seen.append))
    assert seen == ["map"]  # the earlier stages were not recomputed
    assert res.stages == {"estimate": "reused", "tracks": "reused", "ba": "reused", "map": "computed"}
    assert _mtimes(stages) == mt
    # the resumed run gives the same path as the uninterrupted one
    assert (out / "trajectory.tum").read_bytes() == (ref_out / "trajectory.tum").read_bytes()
    assert res.report["ate_rmse_m"] == ref.report["ate_rmse_m"]
    for name in OUTPUTS:
        assert (out / name).is_file()

    # a corrupted stage file is recomputed (and only it), with the same result
    (stages / "ba.npz").write_bytes(b"not an npz")
    seen.clear()
    res = reprocess_session(session, out, run=RunChoices(progress=False, after_stage=seen.append))
    assert seen == ["ba"]
    assert (out / "trajectory.tum").read_bytes() == (ref_out / "trajectory.tum").read_bytes()

    # a deleted stage is recomputed too; later stages keyed on its settings are reused
    (stages / "tracks.npz").unlink()
    seen.clear()
    reprocess_session(session, out, run=RunChoices(progress=False, after_stage=seen.append))
    assert seen == ["tracks"]
    _no_temp_files(out)


def test_the_session_named_another_way_reuses_the_stored_stages(full_run, session, tmp_path, monkeypatch):
    """A relative path, a link and ``..`` name the same session (its id): nothing is recomputed."""
    ref_out = full_run[0]
    (tmp_path / "link").symlink_to(session)
    monkeypatch.chdir(session.parent)
    for i, name in enumerate([Path(session.name), tmp_path / "link", session / "mav0" / ".."]):
        out = tmp_path / f"out{i}"
        shutil.copytree(ref_out / "stages", out / "stages")
        res = reprocess_session(name, out, run=RunChoices(do_map=False, progress=False))
        assert res.stages == {"estimate": "reused", "tracks": "reused", "ba": "reused", "map": "skipped"}, name
        assert res.report["source"].endswith(str(name))  # messages and the report name it as it was given
        assert (out / "trajectory.tum").read_bytes() == (ref_out / "trajectory.tum").read_bytes()


@pytest.mark.slow
def test_ctrl_c_inside_a_stage_leaves_no_half_written_stage(session, tmp_path, monkeypatch):
    import stereopath.host.backend.tracks

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(stereopath.host.backend.tracks, "build_tracks", interrupted)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        reprocess_session(session, out, run=RunChoices(do_map=False, progress=False))
    stages = out / "stages"
    assert sorted(p.name for p in stages.iterdir() if p.is_file()) == ["estimate.npz", "manifest.json"]
    man = json.loads((stages / "manifest.json").read_text())
    assert list(man["stages"]) == ["estimate"]
    # what the interrupted stage had finished: every keyframe's keypoints, for the next run to read back
    parts = [p for p in (stages / "tracks.parts").rglob("kf_*.npz")]
    assert parts and all(p.stat().st_size > 0 for p in parts)


def test_bad_input_raises_and_writes_nothing(session, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match="empty"):
        reprocess_session(empty, tmp_path / "o1")
    with pytest.raises(DatasetError, match="not found"):
        reprocess_session(tmp_path / "missing", tmp_path / "o2")
    nocal = tmp_path / "nocal"
    for cam in ("cam0", "cam1"):
        shutil.copytree(session / "mav0" / cam, nocal / "mav0" / cam)
        (nocal / "mav0" / cam / "sensor.yaml").unlink()
    with pytest.raises(CalibrationError, match="sensor.yaml"):
        reprocess_session(nocal, tmp_path / "o3")
    with pytest.raises(ConfigError, match="unknown reprocess preset"):
        reprocess_session(session, tmp_path / "o4", preset="nonsense")
    for name in ("o1", "o2", "o3", "o4"):
        assert not (tmp_path / name).exists()


def test_cli_reprocess(full_run, session, capsys):
    from stereopath.host.cli import main

    out, _, _ = full_run
    assert main(["-q", "host", "reprocess", str(session), "--out", str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "estimate reused" in text and "bundle adjusted" in text and "report.html" in text
    assert main(["-q", "host", "reprocess", str(out / "nowhere"), "--out", str(out / "x")]) == 2
    assert not (out / "x").exists()


@pytest.mark.slow
def test_onboard_path_of_the_session_is_the_before_figure(session_with_onboard, tmp_path):
    res = reprocess_session(session_with_onboard, tmp_path / "out", run=RunChoices(do_map=False, progress=False))
    ba = res.report["extra"]["before_after"]
    assert ba["onboard"]["frames"] == FRAMES and ba["onboard"]["ate_rmse_m"] > 0
    after, onboard = ba["bundle_adjusted"]["ate_rmse_m"], ba["onboard"]["ate_rmse_m"]
    assert ba["ate_ratio_vs_onboard"] == pytest.approx(after / onboard)
    assert res.stages["map"] == "skipped" and not (tmp_path / "out" / "mesh.ply").exists()
    assert "on-board (recorded)" in (tmp_path / "out" / "report.html").read_text()


@pytest.mark.slow
def test_a_tiny_session_still_gives_a_path(tmp_path):
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim

    d = tmp_path / "tiny"
    record_sequence(open_sim(SimConfig(frames=3)), d, config_dict={"source": "sim"})
    res = reprocess_session(d, tmp_path / "out", run=RunChoices(do_map=False, progress=False))
    assert len(res.trajectory) == 3 and np.all(np.isfinite(res.trajectory.T_world_cam))
    assert (tmp_path / "out" / "report.html").is_file()


def test_the_re_estimate_leaves_the_disparity_offset_to_the_bundle_adjustment():
    from stereopath.device.core.rig import paper_rig
    from stereopath.device.estimation.registry import make_estimator

    opts = REPROCESS_PRESETS["standard"].estimator_options
    assert opts.disparity_offset.estimate is False and opts.keyframes.background is False
    est = make_estimator("stereo", paper_rig(), options=opts)
    try:
        assert est.cfg.disparity_offset.estimate is False
    finally:
        est.close()


def test_cli_preset_names_match_the_library():
    from stereopath.host.commands import reprocess as cmd
    from stereopath.host.reprocess.pipeline import DEFAULT_PRESET

    assert tuple(cmd.PRESET_NAMES) == tuple(REPROCESS_PRESETS)
    assert cmd.DEFAULT_PRESET == DEFAULT_PRESET


def test_html_report_without_ground_truth_says_so(tmp_path):
    from stereopath.host.reprocess.report_html import render_html

    rep = {"source": "s", "frames": 3, "frames_tracked": 3, "world_frame": "first_camera",
           "extra": {"before_after": {"onboard": None, "reestimated": {"frames": 3},
                                      "bundle_adjusted": {"frames": 3}, "ate_ratio_vs_onboard": None,
                                      "ate_ratio_vs_reestimated": None}}}
    html = render_html(rep, [])
    assert "No ground truth" in html and "not in the session" in html


def test_a_stage_manifest_of_another_pipeline_version_is_started_afresh(tmp_path):
    """Stages stored by an older pipeline are never reused (their keys hold the old version), so an
    older manifest does not list them either, and the rewritten one carries today's version."""
    import json

    from stereopath.host.reprocess.store import MANIFEST, PIPELINE_VERSION, StageStore

    entry = {"key": "k", "files": [], "seconds": 1.0, "settings": {}}
    (tmp_path / MANIFEST).write_text(json.dumps({"format": "stereopath-reprocess", "version": PIPELINE_VERSION - 1,
                                                 "stages": {"estimate": entry}}))
    store = StageStore(tmp_path)
    assert store.data["stages"] == {} and not store.done("estimate", "k")
    store.finish("tracks", "t", [], 2.0, {})
    assert json.loads((tmp_path / MANIFEST).read_text())["version"] == PIPELINE_VERSION
    assert StageStore(tmp_path).done("tracks", "t")


@pytest.mark.parametrize("damage", ["cut", "member", "directory"])
def test_a_damaged_stage_file_reads_as_missing(tmp_path, damage, caplog):
    """A stage file damaged on disk is recomputed (None, logged), never an exception that stops every resume."""
    from stereopath.host.reprocess.store import json_array, load_npz, save_npz, stored_stats

    path = tmp_path / "ba.npz"
    save_npz(path, T=np.arange(4000.0).reshape(-1, 4), stats=json_array({"keyframes": 3}))
    assert stored_stats(path) == {"keyframes": 3} and load_npz(path)["T"].shape == (1000, 4)
    data = bytearray(path.read_bytes())
    if damage == "cut":  # a copy cut short: the zip directory at the end is gone
        data = data[:1000]
    elif damage == "member":  # bytes flipped inside the first member's data: its CRC fails
        start = data.index(b"\x93NUMPY") + 200
        data[start:start + 64] = bytes(64)
    else:  # the end of the central directory damaged
        at = data.rindex(b"PK\x05\x06")
        data[at:at + 4] = b"\xff" * 4
    path.write_bytes(bytes(data))
    caplog.set_level(logging.WARNING)
    assert load_npz(path) is None
    assert "unreadable" in caplog.text
    # the stats are another member: they still read when only the first member is damaged
    assert stored_stats(path) == ({"keyframes": 3} if damage == "member" else {})


@pytest.mark.slow
def test_bundle_adjustment_windows_interrupted_resume_from_the_last_stored_one(session, tmp_path, monkeypatch):
    """With windows (made small here), an adjustment stopped in its second window leaves the first one
    stored in ``ba.parts``; the next run solves only the windows after it and writes the path an
    uninterrupted run writes."""
    from stereopath.host.backend import gtsam_ba, windowed_ba

    for name, value in (("BATCH_KEYFRAMES", 2), ("WINDOW", 3), ("OVERLAP", 2), ("HELD", 1)):
        monkeypatch.setattr(windowed_ba, name, value)
    run = RunChoices(do_map=False, progress=False)
    whole = tmp_path / "whole"
    reprocess_session(session, whole, run=run)
    n_windows = len(windowed_ba.window_starts(len(np.load(whole / "stages" / "tracks.npz")["kf_index"])))
    assert n_windows >= 3
    # the uninterrupted run's first two stages, as if an earlier run had stopped after them
    stages = _stopped_after_tracks(whole / "stages", tmp_path / "out" / "stages")
    solve, calls = gtsam_ba.bundle_adjust, []

    def stopping(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return solve(*args, **kwargs)

    monkeypatch.setattr(gtsam_ba, "bundle_adjust", stopping)
    with pytest.raises(KeyboardInterrupt):
        reprocess_session(session, tmp_path / "out", run=run)
    stored = list((stages / "ba.parts").rglob(windowed_ba.WindowCheckpoint.FILE))
    assert len(stored) == 1 and int(np.load(stored[0])["done"]) == 1
    res = reprocess_session(session, tmp_path / "out", run=run)
    assert res.stages["ba"] == "computed" and len(calls) - 2 == n_windows - 1
    assert not (stages / "ba.parts").exists()  # the stage is stored whole: its partial results are gone
    assert (tmp_path / "out" / "trajectory.tum").read_bytes() == (whole / "trajectory.tum").read_bytes()
