"""Helpers shared by the capture-service tests (no tests here): a notify socket, fakes, config files."""

from __future__ import annotations

import os
import secrets
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from stereopath.device.estimation.base import PoseEstimate
from stereopath.device.settings import SimSettings
from stereopath.device.capture.sources.sim import SimSource

REPO = Path(__file__).resolve().parents[2]


class NotifyListener:
    """A datagram socket standing in for systemd's notify socket; records (monotonic time, fields)."""

    def __init__(self, tmp: Path | None = None, abstract: bool = False) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        if abstract:
            name = f"stereopath-test-{os.getpid()}-{secrets.token_hex(4)}"
            self.sock.bind("\0" + name)
            self.address = "@" + name
        else:
            path = Path(tmp) / "notify.sock"
            self.sock.bind(str(path))
            self.address = str(path)
        self.sock.settimeout(0.05)
        self.messages: list[tuple[float, dict[str, str]]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except socket.timeout:
                continue
            except OSError:
                return
            fields = dict(line.split("=", 1) for line in data.decode().split("\n") if "=" in line)
            with self._lock:
                self.messages.append((time.monotonic(), fields))

    def times(self, key: str, value: str | None = None) -> list[float]:
        with self._lock:
            return [t for t, f in self.messages if key in f and (value is None or f[key] == value)]

    def keys_in_order(self) -> list[str]:
        """Every assignment except STATUS, in arrival order (e.g. ['READY=1', 'WATCHDOG=1', ...])."""
        with self._lock:
            return [f"{k}={v}" for _, f in self.messages for k, v in f.items() if k != "STATUS"]

    def statuses(self) -> list[str]:
        with self._lock:
            return [f["STATUS"] for _, f in self.messages if "STATUS" in f]

    def wait_for(self, key: str, value: str | None = None, timeout_s: float = 30.0, count: int = 1) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if len(self.times(key, value)) >= count:
                return True
            time.sleep(0.02)
        return False

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()


class _SilentImu:
    """The simulator's IMU that stops delivering samples after ``after`` non-empty reads."""

    def __init__(self, imu: Any, after: int) -> None:
        self._imu, self.after, self.reads = imu, after, 0
        self.name, self.gaps = "silent-imu", []
        self.silent_at: float | None = None

    def __getattr__(self, name: str) -> Any:  # advance(), finish() of the simulator's IMU
        return getattr(self._imu, name)

    def open(self) -> None:
        self._imu.open()

    def close(self) -> None:
        self._imu.close()

    def read(self):
        block = self._imu.read()
        if self.reads >= self.after:
            if self.silent_at is None:
                self.silent_at = time.monotonic()
            return block.slice(0, 0)
        self.reads += int(len(block) > 0)
        return block


class HangingSimSource(SimSource):
    """The simulator source whose camera "hangs" after ``hang_after`` frames until closed,
    or whose IMU falls silent after ``imu_silent_after`` reads (frames keep coming)."""

    def __init__(self, frames: int = 400, hang_after: int | None = None, rate_hz: float = 0.0,
                 imu_silent_after: int | None = None) -> None:
        super().__init__(SimSettings(frames=frames, seed=3, rate_hz=rate_hz))
        self.hang_after = hang_after
        self.imu_silent_after = imu_silent_after
        self.opened_at: float | None = None
        self.first_frame_at: float | None = None
        self.hang_started_at: float | None = None
        self.delivered = 0
        self._released = threading.Event()

    def _open(self) -> None:
        super()._open()
        if self.imu_silent_after is not None:
            self._imu = _SilentImu(self._imu, self.imu_silent_after)
        self.opened_at = time.monotonic()

    @property
    def fault_started_at(self) -> float | None:
        """When the camera hung or the IMU fell silent."""
        if self.imu_silent_after is not None:
            return self._imu.silent_at if self._imu is not None else None
        return self.hang_started_at

    def _frames(self):
        for frame in super()._frames():
            if self.hang_after is not None and self.delivered >= self.hang_after:
                self.hang_started_at = time.monotonic()
                self._released.wait()  # the driver blocks until someone closes the camera
                return
            if self.first_frame_at is None:
                self.first_frame_at = time.monotonic()
            self.delivered += 1
            yield frame

    def _close(self) -> None:
        self._released.set()


class FakeEstimator:
    """Identity poses moving 1 cm per frame, a keyframe every ``kf_every`` frames (fast, deterministic)."""

    name = "fake"
    world_frame = "first_camera"

    def __init__(self, kf_every: int = 5) -> None:
        self.kf_every = kf_every
        self.frames: list[int] = []
        self.imu_blocks: list[int] = []
        self.closed = False

    def process(self, frame, imu) -> PoseEstimate:
        self.frames.append(frame.seq)
        self.imu_blocks.append(0 if imu is None else len(imu))
        T = np.eye(4)
        T[0, 3] = 0.01 * len(self.frames)
        return PoseEstimate(frame.seq, frame.t_ns, T, "ok", inliers=100,
                            keyframe=(len(self.frames) - 1) % self.kf_every == 0)

    def close(self) -> None:
        self.closed = True


def write_toml(path: Path, tables: dict[str, dict[str, Any]]) -> Path:
    """A small TOML writer for test configuration files (tables may nest one level: 'source.sim')."""
    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    lines = []
    for table, items in tables.items():
        lines.append(f"[{table}]")
        lines += [f"{k} = {value(v)}" for k, v in items.items()]
        lines.append("")
    path.write_text("\n".join(lines))
    return path


def sim_tables(tmp: Path, frames: int = 200, rate_hz: float = 0.0, stream: dict[str, Any] | None = None,
               **service: Any) -> dict[str, dict[str, Any]]:
    """Configuration tables for a sim run recording under ``tmp`` (streaming off unless ``stream`` given)."""
    tables: dict[str, dict[str, Any]] = {
        "source": {"backend": "sim"},
        "source.sim": {"frames": frames, "seed": 1, "rate_hz": rate_hz},
        "imu": {"backend": "source"},
        "stream": {"enabled": False, **(stream or {})},
        "recorder": {"dir": str(tmp / "sessions"), "reserve_mb": 1.0},
        "service": {"status_file": str(tmp / "status.json"), "status_interval_s": 0.2, **service},
    }
    if stream:
        tables["stream"]["enabled"] = True
    return tables


def device_run(args: list[str], env_extra: dict[str, str] | None = None, **popen: Any) -> subprocess.Popen:
    """``stereopath device run ARGS`` as a child process (stdout/stderr captured)."""
    env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID",
                                                           "CREDENTIALS_DIRECTORY", "JOURNAL_STREAM")}
    env.update(env_extra or {})
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.Popen([sys.executable, "-m", "stereopath.host", "device", "run", *args], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **popen)


def wait_until(cond: Callable[[], bool], timeout_s: float, step_s: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(step_s)
    return cond()
