"""The demo: device and host as two processes over loopback TCP with fresh CURVE keys.

1. fresh key pairs (device + one authorised host) in a temporary folder;
2. ``stereopath device run`` on the simulated rig (capture -> estimate -> record -> stream),
   waiting for a host before it starts capturing;
3. ``stereopath host live`` receives the live poses and keyframes;
4. when the device has finished (every keyframe acknowledged), the host is stopped, and the
   received live path is evaluated against the simulator's ground truth;
5. the dense model is built from the recorded session (when the host mapping stage exists).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from stereopath.device.errors import StereopathError

log = logging.getLogger(__name__)

DEVICE_CONFIG = """\
# written by stereopath demo
[source]
backend = "sim"
[source.sim]
frames = {frames}
seed = {seed}
[imu]
backend = "source"
[stream]
pose_endpoint = "tcp://127.0.0.1:*"
keyframe_endpoint = "tcp://127.0.0.1:*"
drain_s = 30.0
[keys]
server_secret = "{server_secret}"
clients_dir = "{clients_dir}"
[recorder]
reserve_mb = 50.0
[service]
status_file = "{status_file}"
"""


@dataclass
class DemoResult:
    out: Path
    session_dir: Path
    live_dir: Path
    report: dict
    wall_s: float
    timings_s: dict = field(default_factory=dict)


def _tail(path: Path, n: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


def _wait_for_endpoints(status_file: Path, proc: subprocess.Popen, log_path: Path, timeout_s: float) -> tuple[str, str]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise StereopathError(f"the device process exited early (code {proc.returncode}):\n{_tail(log_path)}")
        try:
            st = json.loads(status_file.read_text())
            pose, kf = st.get("pose_endpoint"), st.get("keyframe_endpoint")
            if pose and kf and not pose.endswith("*"):
                return pose, kf
        except (OSError, ValueError):
            pass
        time.sleep(0.1)
    raise StereopathError(f"the device did not report its endpoints within {timeout_s:.0f} s:\n{_tail(log_path)}")


def _port(endpoint: str) -> int:
    return int(endpoint.rsplit(":", 1)[1])


def run_demo(out: str | Path, frames: int | None = None, seed: int = 0, timeout_s: float = 1800.0,
             with_model: bool = True) -> DemoResult:
    from stereopath.device.sim.session import SimConfig
    from stereopath.device.wire.security import make_demo_keys

    start = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    session_dir, live_dir, logs = out / "session", out / "live", out / "logs"
    for d in (session_dir, live_dir):
        if d.exists():
            shutil.rmtree(d)
    logs.mkdir(exist_ok=True)
    n_frames = SimConfig().frames if frames is None else frames
    py = [sys.executable, "-m", "stereopath.host"]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    timings: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="stereopath-demo-") as tmp:
        keys = make_demo_keys(Path(tmp) / "keys")
        status_file = Path(tmp) / "status.json"
        cfg = Path(tmp) / "device.toml"
        cfg.write_text(DEVICE_CONFIG.format(frames=n_frames, seed=seed, server_secret=keys.device_secret,
                                            clients_dir=keys.clients_dir, status_file=status_file))
        dev_log, host_log = logs / "device.log", logs / "host.log"
        with dev_log.open("w") as dl, host_log.open("w") as hl:
            dev = subprocess.Popen(py + ["device", "run", "--config", str(cfg), "--out", str(session_dir),
                                        "--wait-for-host", "120"], stdout=dl, stderr=subprocess.STDOUT, env=env)
            host = None
            try:
                pose_ep, kf_ep = _wait_for_endpoints(status_file, dev, dev_log, 120.0)
                log.info("device up: poses %s, keyframes %s", pose_ep, kf_ep)
                host = subprocess.Popen(
                    py + ["host", "live", "--device", f"127.0.0.1:{_port(pose_ep)}", "--keyframe-port",
                          str(_port(kf_ep)), "--keys", str(keys.host_keys_dir), "--out", str(live_dir),
                          "--duration", str(int(timeout_s))],
                    stdout=hl, stderr=subprocess.STDOUT, env=env)
                t0 = time.perf_counter()
                try:
                    code = dev.wait(timeout=timeout_s)
                except subprocess.TimeoutExpired:
                    raise StereopathError(f"the device did not finish within {timeout_s:.0f} s") from None
                timings["device_run_s"] = time.perf_counter() - t0
                if code != 0:
                    raise StereopathError(f"the device process failed (code {code}):\n{_tail(dev_log)}")
                _wait_for_poses(session_dir, live_dir, 10.0)
            finally:
                if dev.poll() is None:
                    dev.send_signal(signal.SIGTERM)
                    try:
                        dev.wait(timeout=30)
                    except subprocess.TimeoutExpired:
                        dev.kill()
                if host is not None and host.poll() is None:
                    host.send_signal(signal.SIGTERM)
                    try:
                        host.wait(timeout=30)
                    except subprocess.TimeoutExpired:
                        host.kill()
    report = _evaluate(out, session_dir, live_dir, f"sim:{seed}")
    if with_model:
        from stereopath.host.evaluation.report import write_report

        t0 = time.perf_counter()
        model = model_or_error(session_dir, out)
        timings["model_s"] = time.perf_counter() - t0
        report.setdefault("extra", {})["model"] = model
        write_report(out / "report.json", report)
    return DemoResult(out, session_dir, live_dir, report, time.perf_counter() - start, timings)


def _wait_for_poses(session_dir: Path, live_dir: Path, timeout_s: float) -> None:
    """Give the host up to ``timeout_s`` to write the poses the device recorded (its last ones may still
    be on their way when the device exits); the report counts whatever arrived."""
    def lines(paths) -> int:
        n = 0
        for p in paths:
            try:
                n += sum(1 for line in p.read_text().splitlines() if line and not line.startswith("#"))
            except OSError:
                pass
        return n

    want = lines([session_dir / "trajectory.tum"])
    deadline = time.monotonic() + timeout_s
    while lines(live_dir.glob("*/poses.tum")) < want and time.monotonic() < deadline:
        time.sleep(0.1)


def _evaluate(out: Path, session_dir: Path, live_dir: Path, source: str) -> dict:
    from stereopath.device.formats.tum import read_tum, write_tum
    from stereopath.host.evaluation.evaluate import evaluate
    from stereopath.host.live.store import list_sessions
    from stereopath.host.evaluation.plots import plot_path
    from stereopath.host.evaluation.report import make_report, write_report

    sessions = list_sessions(live_dir)
    if len(sessions) != 1:
        raise StereopathError(f"expected one device session in {live_dir}, found {len(sessions)}")
    live = live_dir / sessions[0]
    est = read_tum(live / "poses.tum")
    gt = read_tum(session_dir / "groundtruth.tum")
    onboard = read_tum(session_dir / "trajectory.tum")
    summary = json.loads((session_dir / "estimator.json").read_text())
    receiver = json.loads((live_dir / "receiver.json").read_text())
    metrics = evaluate(gt, est)
    report = make_report(source=source, estimator=summary["estimator"], frames=summary["frames"],
                         frames_tracked=summary["frames_tracked"], metrics=metrics, frame_ms=summary["frame_ms"],
                         world_frame=summary["world_frame"])
    received = receiver.get("received", {})
    report.setdefault("extra", {}).update({
        "trajectory": "poses received live by the host over CURVE-encrypted ZeroMQ",
        "poses_received": len(est), "poses_recorded_on_device": len(onboard),
        "keyframes_received": received.get("keyframe"), "pose_seq_gaps": receiver.get("pose_seq_gaps"),
        "duplicates": receiver.get("duplicates"), "rejected": receiver.get("rejected", {}).get("total"),
        "estimator_stats": summary.get("stats", {}), "session": str(session_dir), "live_store": str(live),
    })
    write_tum(out / "trajectory.tum", est)
    write_tum(out / "groundtruth.tum", gt)
    write_report(out / "report.json", report)
    plot_path(out / "path.png", gt, est, world_frame=summary["world_frame"])
    return report


def model_or_error(session_dir: Path, out: Path) -> dict:
    """:func:`_build_model`'s statistics, or ``{"error": why}`` when no model can be built (too little
    depth in a short scan): the path and its evaluation stand, and the report says why there is no model."""
    try:
        return _build_model(session_dir, out)
    except StereopathError as exc:
        log.warning("no dense model: %s", exc)
        return {"error": str(exc)}


def _build_model(session_dir: Path, out: Path) -> dict:
    """Dense model of the recorded session at the on-board poses: OUT/mesh.ply, cloud.ply, model.png."""
    from stereopath.host.mapping.mapper import AUTO, map_path

    result = map_path(session_dir, out, AUTO, progress=False)  # the preset chosen from the stereo depth
    st = result.stats
    keep = ("keyframes", "keyframes_used", "voxel_size_m", "vertices", "triangles", "points", "seconds",
            "preset_choice")
    return {k: v for k, v in st.items() if k in keep or not isinstance(v, (list, dict))}
