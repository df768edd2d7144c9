"""Issue 15 device faults: a taken port (item 5)."""

from __future__ import annotations

import socket
import subprocess

import pytest

from tests.test_service_support import device_run, sim_tables, write_toml

pytestmark = pytest.mark.timeout(120)


@pytest.mark.parametrize("which", ["pose", "keyframe"])
def test_port_taken_exits_with_config_code_and_leaves_no_folder(tmp_path, which):
    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen()
    taken = blocker.getsockname()[1]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    ports = {"pose": taken, "keyframe": free} if which == "pose" else {"pose": free, "keyframe": taken}
    stream = {"insecure": True, "pose_endpoint": f"tcp://127.0.0.1:{ports['pose']}",
              "keyframe_endpoint": f"tcp://127.0.0.1:{ports['keyframe']}"}
    cfg = write_toml(tmp_path / "device.toml", sim_tables(tmp_path, frames=20, stream=stream))
    proc = device_run(["--config", str(cfg)])
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        pytest.fail("device run hung with a port taken:\n" + err[-2000:])
    finally:
        blocker.close()
    assert proc.returncode == 78, err[-2000:]
    assert "Address already in use" in err and "Traceback" not in err
    sessions = tmp_path / "sessions"
    assert not sessions.exists() or list(sessions.iterdir()) == []
