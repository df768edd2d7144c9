"""``stereopath device run`` as a child process: systemd notifications, SIGTERM, bad configuration, streaming.

These run the real command line with the simulator and the real estimator, bounded in frames
and time; the notify socket is bound by the test (abstract and path forms).
"""

from __future__ import annotations

import json
import signal
import subprocess

import pytest

from stereopath.device.formats import open_source
from stereopath.device.wire.security import make_demo_keys
from stereopath.device.formats.tum import read_tum
from stereopath.host.live.receiver import Receiver
from stereopath.host.live.receiver_config import ReceiverConfig, SocketTiming
from tests.device.test_service_support import NotifyListener, device_run, sim_tables, wait_until, write_toml

pytestmark = pytest.mark.timeout(90)


def _finish(proc: subprocess.Popen, timeout_s: float = 40.0) -> tuple[int, str, str]:
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"device run did not end within {timeout_s} s; stderr:\n{err[-3000:]}")
    return proc.returncode, out, err


def test_sigterm_sends_stopping_and_leaves_a_complete_session(tmp_path):
    listener = NotifyListener(abstract=True)
    cfg = write_toml(tmp_path / "device.toml", sim_tables(tmp_path, frames=300))
    out = tmp_path / "session"
    proc = device_run(["--config", str(cfg), "--out", str(out)],
                      {"NOTIFY_SOCKET": listener.address, "WATCHDOG_USEC": "2000000"})
    try:
        assert listener.wait_for("READY", "1", timeout_s=60), "no READY=1"
        assert listener.wait_for("WATCHDOG", "1", timeout_s=30), "no WATCHDOG=1 while frames flow"
        assert any(s.startswith("running ") and "fps" in s for s in listener.statuses())
        proc.send_signal(signal.SIGTERM)
        code, _, err = _finish(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
        listener.close()
    assert code == 0, err[-3000:]
    order = listener.keys_in_order()
    assert order.index("READY=1") < order.index("WATCHDOG=1") < order.index("STOPPING=1") == len(order) - 1
    assert "stopping: signal SIGTERM" in err
    assert "Traceback" not in err
    seq = open_source(f"session:{out}")
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "closed" and "ended_utc" in manifest
    assert len(seq) == manifest["counts"]["frames"] >= 1
    assert len(read_tum(out / "trajectory.tum")) == manifest["counts"]["poses"] == len(seq)
    assert len(seq.imu) == manifest["counts"]["imu_samples"] > 0
    status = json.loads((tmp_path / "status.json").read_text())
    assert status["state"] == "stopped" and status["stop_reason"] == "signal SIGTERM"


@pytest.mark.parametrize("case", ["unknown_key", "out_of_range", "missing_key_file"])
def test_bad_configuration_exits_before_ready_naming_the_key(tmp_path, case):
    tables = sim_tables(tmp_path)
    if case == "unknown_key":
        tables["source"]["frame_rate"] = 30
        key = "frame_rate"
    elif case == "out_of_range":
        tables["imu"]["gyro_range_dps"] = 300
        key = "imu.gyro_range_dps"
    else:
        tables["stream"] = {"enabled": True, "insecure": False}
        tables["keys"] = {"server_secret": str(tmp_path / "missing.key_secret"), "clients_dir": str(tmp_path)}
        key = "keys.server_secret"
    cfg = write_toml(tmp_path / "device.toml", tables)
    listener = NotifyListener(tmp_path)
    try:
        code, _, err = _finish(device_run(["--config", str(cfg), "--out", str(tmp_path / "s")],
                                          {"NOTIFY_SOCKET": listener.address}), 60)
        wait_until(lambda: False, 0.2)
    finally:
        listener.close()
    assert code == 78
    errors = [line for line in err.splitlines() if line.startswith("ERROR")]
    assert len(errors) == 1 and key in errors[0] and "configuration error" in errors[0], err
    assert "Traceback" not in err
    assert listener.times("READY") == []
    assert any("configuration error" in s and key in s for s in listener.statuses())
    assert not (tmp_path / "s").exists()  # nothing opened, nothing recorded


@pytest.mark.slow
def test_device_run_streams_poses_and_keyframes_to_a_host(tmp_path):
    keys = make_demo_keys(tmp_path / "keys")
    tables = sim_tables(tmp_path, frames=24, rate_hz=8.0,
                        stream={"pose_endpoint": "tcp://127.0.0.1:*", "keyframe_endpoint": "tcp://127.0.0.1:*",
                                "drain_s": 20.0})
    tables["keys"] = {"server_secret": str(keys.device_secret), "clients_dir": str(keys.clients_dir)}
    cfg = write_toml(tmp_path / "device.toml", tables)
    out = tmp_path / "session"
    status_file = tmp_path / "status.json"
    proc = device_run(["--config", str(cfg), "--out", str(out), "--wait-for-host", "30"])
    rx = None
    try:
        def endpoints():
            try:
                st = json.loads(status_file.read_text())
            except (OSError, ValueError):
                return None
            return (st["pose_endpoint"], st["keyframe_endpoint"]) if st.get("pose_endpoint") else None

        assert wait_until(lambda: endpoints() is not None or proc.poll() is not None, 60)
        pose_ep, kf_ep = endpoints()
        rx = Receiver(ReceiverConfig(pose_ep, kf_ep, keys_dir=str(keys.host_keys_dir), fsync=False,
                                     sockets=SocketTiming(heartbeat_ivl_ms=250, heartbeat_timeout_ms=1500,
                                                          reconnect_ivl_ms=50),
                                     stall_timeout_s=1.0), tmp_path / "host")
        while proc.poll() is None:
            rx.poll(0.05)
        for _ in range(10):
            rx.poll(0.02)
        code, _, err = _finish(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
        if rx is not None:
            rx.close()
    assert code == 0, err[-3000:]
    sid = json.loads((out / "manifest.json").read_text())["session_id"]
    spooled = sorted(p.name for p in (out / "keyframes").glob("*.kf"))
    stored = sorted((tmp_path / "host" / sid / "keyframes").glob("kf_*.msgpack"))
    assert len(spooled) >= 1 and len(stored) == len(spooled), err[-2000:]
    for seq, path in enumerate(stored):  # byte-identical, exactly once
        assert path.read_bytes() == (out / "keyframes" / f"{seq:08d}.kf").read_bytes()
    assert "every keyframe" in err and "acknowledged" in err
    poses = read_tum(tmp_path / "host" / sid / "poses.tum")
    assert 1 <= len(poses) <= 24
    device_traj = read_tum(out / "trajectory.tum")
    assert set(poses.t_ns.tolist()) <= set(device_traj.t_ns.tolist())
    assert poses.t_ns[0] == device_traj.t_ns[0]  # --wait-for-host: the host saw the path from its start
    assert "a host is connected and subscribed to poses; starting capture" in err
    assert rx.stats.rejected == 0 and rx.live.status is not None and rx.live.status.session_id == sid
