"""CLI smoke: the main job, device and host as two processes over loopback with CURVE."""

import json
import subprocess
import sys

from stereopath.device.formats.tum import read_tum
from stereopath.host.evaluation.report import REPORT_KEYS


def test_demo_runs_device_and_host_and_reports(tmp_path, repo_root):
    out = tmp_path / "demo"
    proc = subprocess.run([sys.executable, "-m", "stereopath.host", "demo", "--out", str(out), "--frames", "40"],
                          cwd=repo_root, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for name in ("trajectory.tum", "groundtruth.tum", "report.json", "path.png", "mesh.ply", "cloud.ply", "model.png"):
        assert (out / name).stat().st_size > 0
    report = json.loads((out / "report.json").read_text())
    assert set(REPORT_KEYS) <= set(report)
    assert report["frames"] == 40 and report["frames_tracked"] == 40
    assert report["world_frame"] == "gravity_aligned"
    assert report["extra"]["poses_received"] == 40  # every pose crossed the wire
    assert report["extra"]["keyframes_received"] >= 2
    assert report["ate_rmse_m"] < 0.005
    assert report["median_frame_ms"] > 0
    assert len(read_tum(out / "trajectory.tum")) == 40
    assert "CURVE" in proc.stdout
    assert report["extra"]["model"]["mesh_vertices"] > 1000  # the dense model of the simulated scan
