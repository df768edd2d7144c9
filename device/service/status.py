"""The service's health report: rates, CPU, the last problem logged, the one-line summary, the status file."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, Callable, Mapping

from stereopath.device.formats.fileio import write_json_atomic

STATUS_FORMAT_VERSION = 1


class RateWindow:
    """Events per second over the last few seconds (by arrival on the supervisor's clock)."""

    def __init__(self, span_s: float = 3.0) -> None:
        self.span_s = span_s
        self._marks: list[tuple[float, int]] = []

    def rate(self, now: float, total: int) -> float:
        self._marks.append((now, total))
        while len(self._marks) > 2 and now - self._marks[1][0] >= self.span_s:
            self._marks.pop(0)
        t0, n0 = self._marks[0]
        return (total - n0) / (now - t0) if now > t0 else 0.0


def _cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system


class CpuMeter:
    """This process's CPU use (all threads) in % of one core since the previous call."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self._last = self._start = (clock(), _cpu_seconds())

    def restart(self) -> None:
        self._last = self._start = (self._clock(), _cpu_seconds())

    def average_pct(self) -> float:
        """Since :meth:`restart` (or construction)."""
        now, cpu = self._clock(), _cpu_seconds()
        return 100.0 * (cpu - self._start[1]) / (now - self._start[0]) if now > self._start[0] else 0.0

    def pct(self) -> float:
        now, cpu = self._clock(), _cpu_seconds()
        wall0, cpu0 = self._last
        self._last = (now, cpu)
        return 100.0 * (cpu - cpu0) / (now - wall0) if now > wall0 else 0.0


class LastProblem(logging.Handler):
    """Remembers the latest warning or error logged anywhere (for the status report)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.text: str | None = None
        self.t_unix: float | None = None

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.text = f"{record.levelname} {record.name}: {record.getMessage()}"
            self.t_unix = record.created
        except Exception:  # never let reporting break logging
            pass


def _bytes_text(n: int | None) -> str:
    if n is None:
        return "? free"
    return f"{n / 1e9:.1f} GB free" if n >= 1e9 else f"{n / 1e6:.0f} MB free"


def status_line(s: Mapping[str, Any]) -> str:
    """The one-line health summary (systemd ``STATUS=``, ``device status``)."""
    temp = s.get("temperature_c")
    parts = [
        f"{s.get('frame_rate_hz', 0.0):.1f} fps",
        f"IMU {s.get('imu_rate_hz', 0.0):.0f} Hz",
        f"{s.get('dropped_frames', 0)} dropped",
        f"{s.get('imu_gaps', 0)} IMU gaps",
        f"tracking {s.get('tracking') or '-'}",
        f"CPU {s.get('cpu_process_pct', 0.0):.0f}%",
        f"{temp:.1f} C" if isinstance(temp, (int, float)) else "temp ?",
        _bytes_text(s.get("disk_free_bytes")),
        f"recorder {s.get('recorder_state', '-')}",
        *(["DISK FULL: keyframes in memory until a host has them "
           f"({s.get('keyframes_in_memory', 0)} waiting, {s.get('keyframes_failed', 0)} lost)"]
          if s.get("spool_disk_full") or s.get("recorder_state") == "stopped_low_disk" else []),
        f"{s.get('hosts', 0)} host(s)",
    ]
    head = f"{s.get('state', '?')} {s.get('session_id', '')}".strip()
    return f"{head}: " + ", ".join(parts)


def write_status_file(path: Path, data: Mapping[str, Any]) -> None:
    """Replace ``path`` atomically with ``data`` as JSON, readable by every user (0644 whatever the UMask)."""
    write_json_atomic(path, dict(data), indent=1, fsync=False, mode=0o644)


def existing_parent(path: Path) -> Path:
    """``path`` or its nearest existing ancestor (where free disk is measured)."""
    while not path.exists() and path != path.parent:
        path = path.parent
    return path
