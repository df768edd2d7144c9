"""CLI smoke: the main job, device and host as two processes over loopback with CURVE."""

import json
import subprocess
import sys

import pytest

from stereopath.device.formats.tum import read_tum
from stereopath.host.evaluation.report import REPORT_KEYS


@pytest.mark.slow
def test_demo_runs_device_and_host_and_reports(tmp_path, repo_root):
    out = tmp_path / "demo"
    proc = subprocess.run([sys.executable, "-m", "stereopath.host", "demo", "--out", str(out), "--frames", "20"],
                          cwd=repo_root, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    # a short scan (1 s, a quarter of it the still start) still gives a model: at least 8 keyframes fused
    for name in ("trajectory.tum", "groundtruth.tum", "report.json", "path.png", "mesh.ply", "cloud.ply", "model.png",
                 "map.json"):
        assert (out / name).stat().st_size > 0
    report = json.loads((out / "report.json").read_text())
    assert set(REPORT_KEYS) <= set(report)
    assert report["frames"] == 20 and report["frames_tracked"] == 20
    assert report["world_frame"] == "gravity_aligned"
    assert report["extra"]["poses_received"] == 20  # every pose crossed the wire
    assert report["extra"]["keyframes_received"] >= 1
    assert report["ate_rmse_m"] < 0.005
    assert report["median_frame_ms"] > 0
    assert len(read_tum(out / "trajectory.tum")) == 20
    assert "CURVE" in proc.stdout
    assert report["extra"]["model"]["mesh_vertices"] > 1000  # the dense model of the simulated scan
    assert report["extra"]["model"]["keyframes"] >= 8


@pytest.mark.slow
def test_a_model_that_cannot_be_built_leaves_the_path_results(tmp_path, monkeypatch, capsys, caplog):
    """The shortest demo (the still start and two moving frames), its model failing: exit 0, the path's
    results and the report say why there is no model."""
    from stereopath.device.errors import StereopathError
    from stereopath.host import demo
    from stereopath.host.cli import main

    def no_surface(session_dir, out):
        raise StereopathError(f"{session_dir}: the fused volume holds no surface")

    monkeypatch.setattr(demo, "_build_model", no_surface)
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--frames", "8"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["frames_tracked"] == 8 and report["ate_rmse_m"] < 0.005
    assert report["extra"]["model"] == {"error": f"{out / 'session'}: the fused volume holds no surface"}
    assert "no dense model" in caplog.text
    printed = capsys.readouterr().out
    assert "wrote" in printed and "mesh.ply" not in printed and not (out / "mesh.ply").exists()
