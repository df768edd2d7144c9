"""The device path runs BLAS at one thread, set before numpy is loaded."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from stereopath.device.commands.blas_threads import BLAS_THREAD_VARIABLES, command_words, runs_device_path


@pytest.mark.parametrize("argv, expected", [
    (["odometry", "kitti:/x", "--out", "o"], True),
    (["-v", "odometry", "sim"], True),
    (["sim", "--out", "o"], True),
    (["device", "run", "--source", "sim"], True),
    (["device", "status"], False),
    (["host", "map", "session:/x"], False),
    (["host", "reprocess", "session:/x"], False),
    (["demo"], False),
    ([], False),
])
def test_device_path_commands(argv, expected):
    assert runs_device_path(argv) is expected


def test_command_words_stop_at_the_first_option():
    assert command_words(["-q", "device", "run", "--source", "sim", "extra"]) == ("device", "run")


_PROBE = """
import json, sys
from stereopath.host.cli import main
code = main(sys.argv[1:])
from threadpoolctl import threadpool_info
print(json.dumps({"code": code, "blas": [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]}))
"""


def _probe(tmp_path, argv):
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    r = subprocess.run([sys.executable, "-c", _PROBE, *argv], capture_output=True, text=True, env=env,
                       cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_odometry_runs_one_blas_thread(tmp_path):
    out = _probe(tmp_path, ["-q", "odometry", "sim:frames=12", "--out", str(tmp_path / "o")])
    assert out["code"] == 0
    assert out["blas"] and all(n == 1 for n in out["blas"])
    # the report counts the frame loop's CPU with and without producing the frames (rendering here)
    cpu = json.loads((tmp_path / "o" / "report.json").read_text())["extra"]["cpu_ms_per_frame"]
    assert 0 < cpu["live_frames"] < cpu["frame_loop"]
    assert 0 < cpu["live_median"] <= cpu["live_p95"]


def test_host_commands_keep_the_library_default(monkeypatch, capsys):
    """Only the device path is limited: a host command leaves the BLAS variables alone."""
    from stereopath.host.cli import main

    for name in BLAS_THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    assert main(["host"]) == 2  # the group's help
    assert not any(name in os.environ for name in BLAS_THREAD_VARIABLES)
