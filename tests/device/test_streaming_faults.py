"""Fault tests with the host as a real subprocess (``python -m stereopath.host host live``): kill -9 and SIGSTOP.

The device runs in this process (its own threads), on random loopback ports, with CURVE.  Counts
are scaled down from the issue's 300-keyframe / 10-second scenarios (small images, a 3 s pause);
``benchmarks/bench_streaming.py`` runs the full-size ones.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from stereopath.device.wire.security import make_demo_keys
from tests.device.test_streaming_support import assert_exactly_once, make_device, port_of, small_images, stored_seqs, \
    wait_for

pytestmark = [pytest.mark.timeout(90), pytest.mark.skipif(sys.platform != "linux", reason="POSIX signals")]

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def keys(tmp_path_factory):
    return make_demo_keys(tmp_path_factory.mktemp("keys"))


def _start_host(dev, keys, out: Path, log: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "stereopath.host", "host", "live", "--device", f"127.0.0.1:{port_of(dev.pose_endpoint)}",
           "--keyframe-port", str(port_of(dev.keyframe_endpoint)), "--keys", str(keys.host_keys_dir),
           "--out", str(out), "--duration", "80", "--window", "4"]
    return subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=log.open("ab"))


def _stop_host(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGCONT)
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def _host_state(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


class _Producer(threading.Thread):
    """Capture + estimation stand-in: 20 Hz-ish poses and a keyframe every ``kf_every`` frames."""

    def __init__(self, dev, n_frames: int, kf_every: int, period_s: float) -> None:
        super().__init__(daemon=True)
        self.dev, self.n_frames, self.kf_every, self.period_s = dev, n_frames, kf_every, period_s
        self.max_call_s = 0.0
        self.refused = 0
        self.done = threading.Event()

    def run(self) -> None:
        for i in range(self.n_frames):
            T = np.eye(4)
            T[0, 3] = 0.01 * i
            t0 = time.perf_counter()
            self.dev.publish_pose(i, i * 50_000_000, T)
            if i % self.kf_every == 0:
                left, right = small_images(i)
                self.refused += not self.dev.offer_keyframe(i, i * 50_000_000, T, left, right)
            self.max_call_s = max(self.max_call_s, time.perf_counter() - t0)
            time.sleep(self.period_s)
        self.done.set()


def test_host_killed_and_restarted_gets_every_keyframe_once(tmp_path, keys):
    out, log = tmp_path / "out", tmp_path / "host.log"
    dev = make_device(tmp_path, keys, "sessK", max_credit=4)
    n_kf = 40
    host = _start_host(dev, keys, out, log)
    producer = _Producer(dev, n_frames=2 * n_kf, kf_every=2, period_s=0.025)
    try:
        assert wait_for(lambda: (out / "receiver.json").is_file(), 20), log.read_text()
        producer.start()
        assert wait_for(lambda: len(stored_seqs(out, "sessK")) >= n_kf // 4, 20), log.read_text()
        host.kill()  # kill -9, halfway through the run
        host.wait(5)
        at_kill = len(stored_seqs(out, "sessK"))
        assert at_kill < n_kf
        time.sleep(0.3)
        host = _start_host(dev, keys, out, log)
        assert producer.done.wait(30)
        assert dev.wait_spooled(n_kf, 20)
        assert wait_for(lambda: len(stored_seqs(out, "sessK")) == n_kf, 30), log.read_text()
    finally:
        _stop_host(host)
        dev.close()
    assert producer.refused == 0
    assert_exactly_once(out, "sessK", dev.spool)
    stats = dev.stats()
    assert stats["hellos"] >= 2


@pytest.mark.slow
def test_host_paused_device_never_blocks_and_catches_up(tmp_path, keys):
    out, log = tmp_path / "out", tmp_path / "host.log"
    dev = make_device(tmp_path, keys, "sessP", max_credit=4, heartbeat_ivl_ms=200, heartbeat_timeout_ms=1000)
    host = _start_host(dev, keys, out, log)
    warmup = _Producer(dev, n_frames=6, kf_every=2, period_s=0.02)
    producer = _Producer(dev, n_frames=60, kf_every=3, period_s=0.05)  # 3 s of 20 Hz poses, 20 keyframes
    try:
        assert wait_for(lambda: (out / "receiver.json").is_file(), 20), log.read_text()
        warmup.start()
        assert wait_for(lambda: len(stored_seqs(out, "sessP")) == 3, 20), log.read_text()
        host.send_signal(signal.SIGSTOP)
        assert wait_for(lambda: _host_state(host.pid) == "T", 5)
        producer.start()
        # the producer must finish its whole loop while the host is still stopped
        assert producer.done.wait(30), "device calls blocked while the host was paused"
        assert _host_state(host.pid) == "T"
        assert dev.wait_spooled(23, 10)
        during = dev.stats()
        host.send_signal(signal.SIGCONT)
        assert wait_for(lambda: len(stored_seqs(out, "sessP")) == 23, 40), log.read_text()
    finally:
        _stop_host(host)
        dev.close()
    assert producer.refused == 0 and during["keyframes_refused"] == 0
    # memory bounded: nothing waits in RAM (all on disk), at most max_credit keyframes in flight per host
    assert during["pending_keyframes"] == 0
    assert during["max_keyframe_queue"] <= dev.config.bounds.max_pending_keyframes
    for peer in during["peers"]:
        assert peer["max_sent"] - peer["acked"] <= dev.config.bounds.max_credit
        assert peer["credit"] <= dev.config.bounds.max_credit
    print(f"max producer call during the pause: {producer.max_call_s * 1e3:.2f} ms")  # informative only
    assert_exactly_once(out, "sessP", dev.spool)
