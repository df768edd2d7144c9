"""Fault benchmark (issue 15): every scenario on loopback, bounded in time, and what it cost.

Per scenario it prints keyframes (and poses where they matter) sent / stored / lost, the exit
code and the message a user saw.  "lost" counts keyframes the device produced that are on no
host disk at the end (a keyframe still only on the device's disk is counted as "device only").
Full disks are real size-limited tmpfs mounts when this runs as root (``mount -t tmpfs -o
size=...``); otherwise an injected ``ENOSPC`` at the write helper.

    .venv/bin/python benchmarks/bench_faults.py [--only NAME,NAME] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("STEREOPATH_DATA", str(ROOT.parent / "shared" / "data"))

from tests.device.test_streaming_support import free_ports, kill_9_once_spooled, loopback_stream, make_device, small_images, stored_seqs, \
    wait_for, write_or_enospc  # noqa: E402

TIME_LIMIT_S = 90.0  # per scenario: a scenario that takes longer counts as a hang


def _cli(argv: list[str], timeout: float = TIME_LIMIT_S, pick: str = "") -> tuple[int | str, str]:
    """``python -m stereopath.host ARGV``: (exit code or 'HANG', the last error/warning line, or the
    last line holding ``pick``)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    try:
        p = subprocess.run([sys.executable, "-m", "stereopath.host", *argv], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return "HANG", ""
    picked = [ln for ln in (p.stderr + p.stdout).splitlines() if pick and pick in ln]
    return p.returncode, picked[-1][:400] if picked else _user_line(p.stderr + p.stdout)


def _user_line(text: str) -> str:
    if "Traceback" in text:
        return "TRACEBACK: " + text.strip().splitlines()[-1][:160]
    keys = ("stereopath: error", "warning:", "ERROR", "skipped")
    lines = [ln for ln in text.splitlines() if any(k in ln for k in keys)]
    return (lines[-1] if lines else (text.strip().splitlines() or [""])[-1])[:200]


def _can_mount() -> bool:
    if os.geteuid() != 0:
        return False
    d = tempfile.mkdtemp(prefix="bench-faults-probe-")
    try:
        ok = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", d], capture_output=True).returncode == 0
        if ok:
            subprocess.run(["umount", d], capture_output=True)
        return ok
    finally:
        os.rmdir(d)


@contextmanager
def _small_fs(size: str):
    """A size-limited tmpfs (root) yielding (path, grow) where grow(size) makes room again."""
    d = Path(tempfile.mkdtemp(prefix="bench-faults-fs-"))
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(d)], check=True)

    def grow(new_size: str) -> None:
        subprocess.run(["mount", "-o", f"remount,size={new_size}", str(d)], check=True)
    try:
        yield d, grow
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)
        shutil.rmtree(d, ignore_errors=True)


def _receiver(dev, out: Path, **kw):
    return _receiver_at(dev.pose_endpoint, dev.keyframe_endpoint, out, **kw)


def _receiver_at(pose_endpoint: str, keyframe_endpoint: str, out: Path, **kw):
    from stereopath.host.live.receiver import Receiver, ReceiverConfig
    from stereopath.host.live.receiver_config import SocketTiming

    cfg = ReceiverConfig(pose_endpoint, keyframe_endpoint, insecure=True, fsync=False,
                         sockets=SocketTiming(heartbeat_ivl_ms=250, heartbeat_timeout_ms=1500, reconnect_ivl_ms=50,
                                              reconnect_ivl_max_ms=400),
                         stall_timeout_s=1.0, **kw)
    return Receiver(cfg, out)


def _sim_device(tmp: Path, stream: dict):
    """``run(frames, *args)``: a `device run` child on the simulated rig streaming on ``stream``."""
    from tests.device.test_service_support import device_run, sim_tables, write_toml

    def run(frames: int, *args: str) -> subprocess.Popen:
        cfg = write_toml(tmp / "device.toml", sim_tables(tmp, frames=frames, rate_hz=20.0, stream=stream))
        return device_run(["--config", str(cfg), *args])
    return run


def _receive_until_exit(proc: subprocess.Popen, stream: dict, out: Path) -> str:
    """A host receiving into ``out`` until the ``device run`` child ``proc`` ends; its stderr."""
    rx = _receiver_at(stream["pose_endpoint"], stream["keyframe_endpoint"], out)
    try:
        wait_for(lambda: proc.poll() is not None, TIME_LIMIT_S - 10, between=lambda: rx.poll(0.05))
        for _ in range(20):
            rx.poll(0.02)
    finally:
        rx.close()
        if proc.poll() is None:
            proc.kill()
    return proc.communicate()[1]


def _offer(dev, i: int, **image_size) -> None:
    """Offer keyframe ``i``, waiting while the device's spool queue is full (a burst faster than its
    writer is refused by design; these scenarios measure what happens after the device took it)."""
    t_end = time.monotonic() + 10
    while not dev.offer_keyframe(i, i, np.eye(4), *small_images(i, **image_size)):
        if time.monotonic() > t_end:
            raise RuntimeError(f"the device refused keyframe {i} for 10 s")
        time.sleep(0.01)


@contextmanager
def _log_messages(logger: str, level: int):
    """The messages ``logger`` (and its children) emit at ``level`` or above while the block runs."""
    import logging

    msgs: list[str] = []
    handler = logging.Handler(level)
    handler.emit = lambda r: msgs.append(r.getMessage())
    log = logging.getLogger(logger)
    old_level = log.level
    log.addHandler(handler)
    log.setLevel(min(level, logging.WARNING))
    try:
        yield msgs
    finally:
        log.removeHandler(handler)
        log.setLevel(old_level)


def _row(name: str, **kw) -> dict:
    base = {"scenario": name, "kf_sent": "-", "kf_stored": "-", "kf_lost": "-", "kf_dup": "-", "poses_sent": "-",
            "poses_stored": "-", "rc": "-", "tracebacks": 0, "message": ""}
    base.update(kw)
    return base


# ------------------------------------------------------------------------------------------ scenarios

def sc_torn_index(tmp: Path, mount: bool) -> dict:
    """Host restarted after a power cut tore index.csv mid-append; the device then sends more."""
    import logging

    from stereopath.host.live.store import read_index

    with _log_messages("stereopath.host.live.store", logging.WARNING) as msgs:
        dev = make_device(tmp, None, "sessI")
        out = tmp / "host"
        rx = _receiver(dev, out)
        for i in range(5):
            _offer(dev, i)
        wait_for(lambda: len(stored_seqs(out, "sessI")) == 5, 20, between=lambda: rx.poll(0.02))
        rx.close()
        idx = out / "sessI" / "keyframes" / "index.csv"
        idx.write_bytes(idx.read_bytes()[:-25])  # the power cut
        rx = _receiver(dev, out)
        for i in range(5, 10):
            _offer(dev, i)
        wait_for(lambda: len(stored_seqs(out, "sessI")) == 10, 20, between=lambda: rx.poll(0.02))
        rx.close()
        dev.close()
        rows = sorted(r["seq"] for r in read_index(out / "sessI"))
        stored = len(stored_seqs(out, "sessI"))
        return _row("4 torn index.csv", kf_sent=10, kf_stored=stored, kf_lost=10 - stored, rc="n/a (restarted)",
                    message=(msgs[0][:150] if msgs else "") + f" | index rows {len(rows)}")


def sc_host_disk_full(tmp: Path, mount: bool) -> dict:
    """The host's disk fills while keyframes arrive; space returns later (same host process)."""
    import logging

    from stereopath.host.live import store as store_mod

    n = 20
    with _log_messages("stereopath.host.live", logging.ERROR) as msgs:
        dev = make_device(tmp, None, "sessH")
        if mount:
            ctx = _small_fs("48k")
            out_root, grow = ctx.__enter__()
        else:
            ctx, out_root = None, tmp
            full = {"on": False}
            real = store_mod.write_atomic
            store_mod.write_atomic = write_or_enospc(real, full)
        try:
            out = out_root / "host"
            rx = _receiver(dev, out)
            if not mount:
                full["on"] = True
            for i in range(n):
                _offer(dev, i, h=192, w=256)
            dev.wait_spooled(n, 20)
            t_end = time.monotonic() + 4
            while time.monotonic() < t_end:
                rx.poll(0.02)
            during = len(stored_seqs(out, "sessH"))
            failures = rx.stats.link.store_failures
            if mount:
                grow("8m")
            else:
                full["on"] = False
            wait_for(lambda: len(stored_seqs(out, "sessH")) == n, 30, between=lambda: rx.poll(0.02))
            stored = len(stored_seqs(out, "sessH"))
            leftovers = [p.name for p in out.rglob("*") if p.name.endswith(".tmp")]
            rx.close()
        finally:
            if ctx is not None:
                ctx.__exit__(None, None, None)
            else:
                store_mod.write_atomic = real
        dev.close()
        how = "tmpfs 48k -> 8m" if mount else "injected ENOSPC"
        return _row("3 host disk full", kf_sent=n, kf_stored=stored, kf_lost=n - stored, rc="n/a (kept running)",
                    message=f"[{how}] stored {during} while full, {failures} store failures, "
                            f"{len(leftovers)} temp files; " + (msgs[0][:110] if msgs else ""))


def sc_device_disk_full(tmp: Path, mount: bool) -> dict:
    """The device's disk fills mid-scan (recorder + spool) with a host connected."""
    from stereopath.device.service.components import RunSeams
    from stereopath.device.service.options import RunOptions, load_config
    from stereopath.device.service.service import CaptureService
    from stereopath.host.live.receiver import Receiver, ReceiverConfig
    from tests.device.test_service_support import FakeEstimator, sim_tables, write_toml

    stream = loopback_stream(drain_s=5.0)
    if not mount:
        return _row("2 device disk full", message="skipped: needs root for a size-limited tmpfs (the test injects it)")
    with _small_fs("6m") as (dev_root, _grow):
        tables = sim_tables(dev_root, frames=60, rate_hz=20.0, stream=stream)
        tables["recorder"]["reserve_mb"] = 1.0
        cfg_path = write_toml(tmp / "device.toml", tables)
        opts = RunOptions(out=str(dev_root / "s"), wait_for_host_s=10.0)
        service = CaptureService(load_config(cfg_path, opts), opts, cfg_path, environ={},
                                 seams=RunSeams(estimator=FakeEstimator(kf_every=2)))
        rx = Receiver(ReceiverConfig(stream["pose_endpoint"], stream["keyframe_endpoint"], insecure=True,
                                     fsync=False, stall_timeout_s=0.5), tmp / "host")
        res: dict = {}
        th = threading.Thread(target=lambda: res.setdefault("code", service.run()), daemon=True)
        th.start()
        t_end = time.monotonic() + TIME_LIMIT_S
        while th.is_alive() and time.monotonic() < t_end:
            rx.poll(0.02)
        for _ in range(25):
            rx.poll(0.02)
        hung = th.is_alive()
        poses_stored = sum(s.poses for s in rx.stats.sessions.values())
        rx.close()
        th.join(10)
        status = json.loads((dev_root / "status.json").read_text())
        spooled = status.get("keyframes_spooled", 0)
        stored = len(stored_seqs(tmp / "host", service.session_id))
        on_device = len(list((dev_root / "s" / "keyframes").glob("*.kf")))
    return _row("2 device disk full", kf_sent=spooled, kf_stored=stored, kf_lost=spooled - stored,
                poses_sent=status.get("poses_sent", "-"), poses_stored=poses_stored,
                rc="HANG" if hung else res.get("code"),
                message=f"[tmpfs 6m, reserve 1 MB] recorder {status.get('recorder_state')}, {on_device} keyframes on "
                        f"device disk, {status.get('keyframes_failed')} refused; STATUS: "
                        + service.stop_reason[:40] + " / " + ("DISK FULL" if status.get("spool_disk_full") else "?"))


def sc_two_hosts(tmp: Path, mount: bool) -> dict:
    """`host live` twice with one key (here: two receivers, CURVE, the same key pair)."""
    from stereopath.device.wire.security import make_demo_keys
    from stereopath.host.live.receiver import Receiver, ReceiverConfig
    from stereopath.host.live.receiver_config import SocketTiming

    keys = make_demo_keys(tmp / "keys")
    dev = make_device(tmp, keys, "sessT")

    def rx(out):
        return Receiver(ReceiverConfig(dev.pose_endpoint, dev.keyframe_endpoint, keys_dir=str(keys.host_keys_dir),
                                       fsync=False, stall_timeout_s=1.0,
                                       sockets=SocketTiming(reconnect_ivl_ms=50)), out)
    a = rx(tmp / "a")
    for i in range(5):
        _offer(dev, i)
    wait_for(lambda: len(stored_seqs(tmp / "a", "sessT")) == 5, 20, between=lambda: a.poll(0.02))
    b = rx(tmp / "b")
    for i in range(5, 15):
        _offer(dev, i)
        a.poll(0.01)
        b.poll(0.01)
    wait_for(lambda: all(len(stored_seqs(tmp / d, "sessT")) == 15 for d in "ab"), 20,
             between=lambda: (a.poll(0.01), b.poll(0.01)))
    sa, sb = len(stored_seqs(tmp / "a", "sessT")), len(stored_seqs(tmp / "b", "sessT"))
    a.close()
    b.close()
    peers = dev.stats()["peers"]
    dev.close()
    return _row("1 two hosts, one key", kf_sent=15, kf_stored=f"{sa} + {sb}", kf_lost=(15 - sa) + (15 - sb),
                rc="n/a", message=f"device peers: {len(peers)}, acked {[p['acked'] for p in peers]}")


def sc_port_taken(tmp: Path, mount: bool) -> dict:
    from tests.device.test_service_support import sim_tables, write_toml

    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen()
    free = free_ports(1)[0]
    stream = {"insecure": True, "pose_endpoint": f"tcp://127.0.0.1:{blocker.getsockname()[1]}",
              "keyframe_endpoint": f"tcp://127.0.0.1:{free}"}
    cfg = write_toml(tmp / "device.toml", sim_tables(tmp, frames=20, stream=stream))
    t0 = time.monotonic()
    rc, msg = _cli(["device", "run", "--config", str(cfg)])
    blocker.close()
    left = list((tmp / "sessions").iterdir()) if (tmp / "sessions").exists() else []
    return _row("5 port taken", rc=rc, message=f"{time.monotonic() - t0:.1f} s, {len(left)} folders left; {msg}")


def _session(tmp: Path, frames: int = 12) -> Path:
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim

    d = tmp / "session"
    record_sequence(open_sim(SimConfig(frames=frames)), d, config_dict={"source": "sim"})
    return d


def sc_bad_groundtruth(tmp: Path, mount: bool) -> dict:
    d = _session(tmp)
    (d / "groundtruth.tum").write_text("1 2 3\n")
    rc, msg = _cli(["host", "reprocess", str(d), "--out", str(tmp / "out"), "--preset", "quick", "--no-map",
                    "--no-progress"])
    ok = (tmp / "out" / "trajectory.tum").is_file()
    return _row("9 reprocess, bad ground truth", rc=rc, message=f"trajectory written: {ok}; {msg}")


def sc_bad_frame(tmp: Path, mount: bool) -> dict:
    d = _session(tmp)
    img = sorted((d / "mav0" / "cam0" / "data").glob("*.png"))[5]
    img.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)
    rc, msg = _cli(["odometry", f"session:{d}", "--out", str(tmp / "o")])
    rc2, msg2 = _cli(["odometry", f"session:{d}", "--out", str(tmp / "o2"), "--strict"])
    rep = json.loads((tmp / "o" / "report.json").read_text()) if (tmp / "o" / "report.json").is_file() else {}
    return _row("10 one bad frame (odometry)", rc=f"{rc} / --strict {rc2}",
                message=f"frames {rep.get('frames')} skipped {rep.get('extra', {}).get('frames_skipped')}; {msg} | "
                        f"strict: {msg2[:90]}")


def sc_bad_rigs(tmp: Path, mount: bool) -> dict:
    import yaml

    data = yaml.safe_load((ROOT / "firmware_cfg" / "rig_paper.yaml").read_text())
    data["T_cam1_cam0_m"] = [-v for v in data["T_cam1_cam0_m"]]
    (tmp / "neg.yaml").write_text(yaml.safe_dump(data))
    d = _session(tmp)
    rc1, m1 = _cli(["device", "run", "--source", f"replay:session:{d}", "--insecure", "--no-stream", "--frames", "3",
                    "--status-file", "", "--out", str(tmp / "r"), "--config", str(_rig_cfg(tmp, tmp / "neg.yaml"))],
                   pick="configuration error")
    m = d / "mav0"
    (m / "cam0").rename(m / "x")
    (m / "cam1").rename(m / "cam0")
    (m / "x").rename(m / "cam1")
    rc2, m2 = _cli(["odometry", f"session:{d}", "--out", str(tmp / "o")])
    from stereopath.device.formats.tum import Trajectory, read_tum, write_tum

    gt = read_tum(d / "groundtruth.tum")
    write_tum(tmp / "still.tum", Trajectory(gt.t_ns, np.repeat(np.eye(4)[None], len(gt), 0)))
    rc3, m3 = _cli(["eval", "--gt", str(d / "groundtruth.tum"), "--est", str(tmp / "still.tum")])
    return _row("7 bad rig / swapped / still", rc=f"{rc1} / {rc2} / {rc3}",
                message=f"neg. baseline: {m1[m1.find('configuration error'):][:50]} ... "
                        f"{m1[m1.find('cam1 sits'):][:45]} | swapped: {m2[-60:]} | still: {m3[-60:]}")


def _rig_cfg(tmp: Path, rig: Path) -> Path:
    from tests.device.test_service_support import write_toml

    return write_toml(tmp / "rigdev.toml", {"source": {"rig_file": str(rig)}, "recorder": {"dir": str(tmp / "rec")},
                                            "service": {"status_file": ""}})


def sc_killed_device_spool(tmp: Path, mount: bool) -> dict:
    """`device run` killed (-9) mid-session before any host acknowledged its keyframes; a new run
    (waiting for a host) and a host: the earlier session's keyframes reach the host, the device deletes them."""
    from stereopath.host.live.receiver_sessions import session_states
    stream = loopback_stream(spool_fsync=False)

    run = _sim_device(tmp, stream)
    sessions = tmp / "sessions"
    first = run(400)
    old = kill_9_once_spooled(first, sessions, 8)
    killed = len(list((old / "keyframes").glob("*.kf")))
    second = run(40, "--wait-for-host", "60")
    out = tmp / "host"
    err = _receive_until_exit(second, stream, out)
    stored = len(stored_seqs(out, old.name))
    left = len(list((old / "keyframes").glob("*.kf")))
    states = {st.session_id: st.state for st in session_states(out)}
    offer = next((ln for ln in err.splitlines() if "no host acknowledged" in ln), "")
    return _row("6 killed device's spool", kf_sent=killed, kf_stored=stored, kf_lost=killed - stored,
                rc=f"kill -9 / restart {second.returncode}",
                message=f"{left} left on the device, earlier session {states.get(old.name)} on the host "
                        f"(rig.yaml {(out / old.name / 'rig.yaml').is_file()}); device: {offer.split(': ', 1)[-1][:110]}")


def sc_live_map_shipped_rig(tmp: Path, mount: bool) -> dict:
    """`host live --map --rig firmware_cfg/rig_paper.yaml` against a device on another rig (the simulator's)."""
    from stereopath.device.formats.source import open_source
    from stereopath.device.streaming import DeviceStreamer, KeyframeSpool
    from tests.device.test_streaming_support import device_config, port_of

    seq = open_source("sim:0", frames=60)
    dev = DeviceStreamer(device_config(None), KeyframeSpool(tmp / "spool", fsync=False), "sessM", rig=seq.rig,
                         status_interval_s=0.2)
    n = 6
    for i in range(30, 30 + 4 * n, 4):
        f = seq.render(i)
        _offer_frame(dev, i, f)
    dev.wait_spooled(n, 20)
    out = tmp / "host"
    rc, msg = _cli(["host", "live", "--device", f"127.0.0.1:{port_of(dev.pose_endpoint)}", "--keyframe-port",
                    str(port_of(dev.keyframe_endpoint)), "--insecure", "--out", str(out), "--no-fsync", "--map",
                    "--map-every", "2", "--rig", str(ROOT / "firmware_cfg" / "rig_paper.yaml"), "--duration", "5"],
                   pick="is not the rig")
    dev.close()
    mesh = out / "sessM" / "model" / "mesh.ply"
    rc2, msg2 = _cli(["host", "map", str(out / "sessM"), "--out", str(tmp / "map")])
    return _row("8 live map, shipped rig", kf_sent=n, kf_stored=len(stored_seqs(out, "sessM")),
                kf_lost=n - len(stored_seqs(out, "sessM")), rc=f"{rc} / host map {rc2}",
                message=f"mesh {mesh.stat().st_size if mesh.is_file() else 0} bytes, rig.yaml "
                        f"{(out / 'sessM' / 'rig.yaml').is_file()}; {msg.split(': ', 1)[-1][:150]} | host map "
                        f"(no --rig): {msg2[:70]}")


class _Proxy:
    """A TCP forwarder on loopback that can cut every connection (``drop``) or black-hole traffic for a
    while (``partition``: nothing is forwarded and new connections wait) -- a flaky Wi-Fi link."""

    def __init__(self, target_port: int) -> None:
        import select

        self._select = select
        self.target = target_port
        self.srv = socket.socket()
        self.srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.srv.bind(("127.0.0.1", 0))
        self.srv.listen(64)
        self.port = self.srv.getsockname()[1]
        self.blackhole = threading.Event()
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self._lock = threading.Lock()
        self._closed = False
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self._closed:
            try:
                client, _ = self.srv.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        while self.blackhole.is_set() and not self._closed:  # a new connection waits out the partition
            time.sleep(0.05)
        try:
            upstream = socket.create_connection(("127.0.0.1", self.target), timeout=2)
        except OSError:
            client.close()
            return
        with self._lock:
            self._pairs.append((client, upstream))
        socks = [client, upstream]
        try:
            while not self._closed:
                if self.blackhole.is_set():
                    time.sleep(0.05)
                    continue
                ready, _, _ = self._select.select(socks, [], [], 0.1)
                for s in ready:
                    data = s.recv(65536)
                    if not data:
                        return
                    (upstream if s is client else client).sendall(data)
        except OSError:
            return
        finally:
            for s in socks:
                s.close()
            with self._lock:
                if (client, upstream) in self._pairs:
                    self._pairs.remove((client, upstream))

    def drop(self) -> None:
        with self._lock:
            pairs = list(self._pairs)
        for a, b in pairs:
            for s in (a, b):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def close(self) -> None:
        self._closed = True
        self.drop()
        self.srv.close()


def _exactly_once(out: Path, session: str, produced: int) -> tuple[int, int]:
    """(keyframes of 0..produced-1 on no host, keyframes indexed more than once) in the host store."""
    from stereopath.host.live.store import read_index

    held = set(stored_seqs(out, session))
    rows = [r["seq"] for r in read_index(out / session)] if (out / session).is_dir() else []
    return len(set(range(produced)) - held), len(rows) - len(set(rows))


def sc_partition(tmp: Path, mount: bool) -> dict:
    """A 20 s network partition and 3 connection drops between host and device while keyframes flow."""
    dev = make_device(tmp, None, "sessN")
    proxies = [_Proxy(int(dev.pose_endpoint.rsplit(":", 1)[1])), _Proxy(int(dev.keyframe_endpoint.rsplit(":", 1)[1]))]
    out = tmp / "host"
    rx = _receiver_at(f"tcp://127.0.0.1:{proxies[0].port}", f"tcp://127.0.0.1:{proxies[1].port}", out)
    n = 0
    try:
        def tick(k: int) -> None:
            nonlocal n
            for _ in range(k):
                _offer(dev, n)
                n += 1
                rx.poll(0.05)
        tick(5)
        for _ in range(3):  # connections cut (a reset), keyframes keep coming
            for p in proxies:
                p.drop()
            tick(5)
        for p in proxies:
            p.blackhole.set()
        t_end = time.monotonic() + 20.0
        while time.monotonic() < t_end:  # the partition: the scan goes on, nothing gets through
            tick(1)
            time.sleep(0.2)
        for p in proxies:
            p.blackhole.clear()
        tick(5)
        wait_for(lambda: len(stored_seqs(out, "sessN")) >= n, 40, between=lambda: rx.poll(0.05))
        link = rx.stats.link.to_json()
    finally:
        rx.close()
        for p in proxies:
            p.close()
        dev.close()
    lost, dup = _exactly_once(out, "sessN", n)
    return _row("11 partition 20 s + 3 drops", kf_sent=n, kf_stored=len(stored_seqs(out, "sessN")), kf_lost=lost,
                kf_dup=dup, rc="-", message=f"host link: {link.get('connects', 0)} connects, "
                                            f"{link.get('disconnects', 0)} disconnects, {link.get('hellos', 0)} hellos")


def sc_host_kill_loop(tmp: Path, mount: bool) -> dict:
    """`host live` killed (-9) five times during one scan, restarted each time on the same --out."""
    import signal

    from tests.device.test_streaming_support import port_of

    dev = make_device(tmp, None, "sessK")
    out = tmp / "host"
    argv = [sys.executable, "-m", "stereopath.host", "host", "live", "--device",
            f"127.0.0.1:{port_of(dev.pose_endpoint)}", "--keyframe-port", str(port_of(dev.keyframe_endpoint)),
            "--insecure", "--out", str(out), "--no-fsync"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    n, kills, tracebacks = 0, 0, 0
    proc = None
    try:
        for _ in range(5):
            proc = subprocess.Popen(argv + ["--duration", "60"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True)
            for _ in range(6):
                _offer(dev, n)
                n += 1
                time.sleep(0.25)
            os.kill(proc.pid, signal.SIGKILL)
            _, err = proc.communicate(timeout=20)
            tracebacks += "Traceback" in err
            kills += 1
        for _ in range(4):
            _offer(dev, n)
            n += 1
        proc = subprocess.Popen(argv + ["--duration", "30"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        wait_for(lambda: len(stored_seqs(out, "sessK")) >= n, 30, step_s=0.2)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
        tracebacks += "Traceback" in err
        rc = proc.returncode
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.communicate()
        dev.close()
    lost, dup = _exactly_once(out, "sessK", n)
    return _row("12 host kill -9 x5", kf_sent=n, kf_stored=len(stored_seqs(out, "sessK")), kf_lost=lost,
                kf_dup=dup, rc=f"{kills} x -9, last {rc}", tracebacks=tracebacks,
                message=f"{kills} kills, then a clean stop (rc {rc})")


def sc_rogue_hello_device_kill(tmp: Path, mount: bool) -> dict:
    """An authorised peer says hello claiming every keyframe (acked 2^32-1) without receiving any; the
    device is then killed (-9) and restarted; an honest host connects."""
    import zmq

    from stereopath.device.streaming.spool import read_acked
    from stereopath.device.wire.protocol import Hello, encode_hello
    stream = loopback_stream(spool_fsync=False)

    run = _sim_device(tmp, stream)
    sessions = tmp / "sessions"
    first = run(400)
    ctx = zmq.Context()
    rogue = ctx.socket(zmq.DEALER)
    rogue.setsockopt(zmq.LINGER, 0)
    rogue.connect(stream["keyframe_endpoint"])
    try:
        wait_for(lambda: sessions.is_dir() and any(len(list(d.glob("keyframes/*.kf"))) >= 6
                                                   for d in sessions.iterdir()), 60, step_s=0.1)
        for _ in range(3):
            rogue.send(encode_hello(Hello(next(sessions.iterdir()).name, 2**32 - 1, 16)))
            time.sleep(0.3)
        old = kill_9_once_spooled(first, sessions, 8)
    finally:
        rogue.close(0)
        ctx.term()
    killed = len(list((old / "keyframes").glob("*.kf")))
    recorded_acked = read_acked(old / "keyframes")
    second = run(40, "--wait-for-host", "60")
    out = tmp / "host"
    err = _receive_until_exit(second, stream, out)
    lost, dup = _exactly_once(out, old.name, killed)
    return _row("13 rogue hello, device kill -9", kf_sent=killed, kf_stored=len(stored_seqs(out, old.name)),
                kf_lost=lost, kf_dup=dup, rc=f"kill -9 / restart {second.returncode}",
                tracebacks=int("Traceback" in err),
                message=f"acked.json after the rogue hello: {recorded_acked} (of {killed} spooled)")


def _offer_frame(dev, i: int, f) -> None:
    t_end = time.monotonic() + 10
    while not dev.offer_keyframe(i, f.t_ns, f.meta["T_world_cam0"], f.left, f.right):
        if time.monotonic() > t_end:
            raise RuntimeError(f"the device refused keyframe {i} for 10 s")
        time.sleep(0.01)


SCENARIOS = {
    "torn_index": sc_torn_index, "host_disk_full": sc_host_disk_full, "device_disk_full": sc_device_disk_full,
    "two_hosts": sc_two_hosts, "port_taken": sc_port_taken, "bad_groundtruth": sc_bad_groundtruth,
    "bad_frame": sc_bad_frame, "bad_rigs": sc_bad_rigs, "killed_device_spool": sc_killed_device_spool,
    "live_map_shipped_rig": sc_live_map_shipped_rig, "partition": sc_partition, "host_kill_loop": sc_host_kill_loop,
    "rogue_hello_device_kill": sc_rogue_hello_device_kill,
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default=None, help="comma-separated scenario names: " + ", ".join(SCENARIOS))
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    import logging

    logging.basicConfig(level=logging.CRITICAL)
    mount = _can_mount()
    names = args.only.split(",") if args.only else list(SCENARIOS)
    rows = []
    for name in names:
        tmp = Path(tempfile.mkdtemp(prefix=f"bench-faults-{name}-"))
        t0 = time.monotonic()
        try:
            row = SCENARIOS[name](tmp, mount)
        except Exception as exc:  # a benchmark row, not a crash: say what failed
            row = _row(name, rc="ERROR", message=f"{type(exc).__name__}: {exc}"[:200])
        row["seconds"] = round(time.monotonic() - t0, 1)
        if "TRACEBACK" in str(row.get("message", "")):
            row["tracebacks"] = max(1, int(row.get("tracebacks") or 0))
        if row["seconds"] > TIME_LIMIT_S:
            row["rc"] = f"HANG? {row['rc']}"
        rows.append(row)
        shutil.rmtree(tmp, ignore_errors=True)
        print(f"... {name}: {row['seconds']} s", file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(rows, indent=1, default=str))
        return 0
    print(f"full disks: {'size-limited tmpfs (root)' if mount else 'injected ENOSPC'}")
    cols = ("scenario", "kf_sent", "kf_stored", "kf_lost", "kf_dup", "poses_sent", "poses_stored", "rc", "tracebacks",
            "seconds")
    widths = [max(len(c), *(len(str(r[c])) for r in rows)) for c in cols]
    print(" | ".join(c.ljust(w) for c, w in zip(cols, widths)))
    print("-+-".join("-" * w for w in widths))
    for r in rows:
        print(" | ".join(str(r[c]).ljust(w) for c, w in zip(cols, widths)))
    print()
    for r in rows:
        print(f"{r['scenario']}: {r['message']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
