"""The service's health report: rates, CPU, the last problem logged, the one-line summary, the status file."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Protocol

from stereopath.device.formats.fileio import write_json_atomic

STATUS_FORMAT_VERSION = 1

if TYPE_CHECKING:
    from stereopath.device.service.components import Components
    from stereopath.device.service.pipeline import PipelineCounters
    from stereopath.device.service.watchdog import Watchdog
    from stereopath.device.settings import DeviceConfig

log = logging.getLogger(__name__)


class ServiceView(Protocol):
    """What the health report reads of the capture service (``service.CaptureService``)."""

    cfg: DeviceConfig
    counters: PipelineCounters
    parts: Components
    watchdog: Watchdog
    session_id: str
    session_dir: Path | None
    state: str
    stop_reason: str
    ready_at: float | None

    @property
    def ready(self) -> bool: ...

    def data_fresh(self, now: float) -> bool: ...


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
        *([f"{s['backlog_keyframes']} keyframe(s) of earlier sessions not yet on a host"]
          if s.get("backlog_keyframes") else []),
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


class StatusReporter:
    """The service's health report: rates, CPU, the last problem logged; written to the status file."""

    def __init__(self, clock: Callable[[], float], path: Path | None = None) -> None:
        self._clock = clock
        self.path = path
        self.cpu = CpuMeter(clock)
        self.fps, self.imu = RateWindow(), RateWindow()
        self.problem = LastProblem()
        self._warned = False

    def report(self, svc: ServiceView) -> dict[str, Any]:
        """The health report of a :class:`~stereopath.device.service.service.CaptureService` now."""
        from stereopath.device.streaming import health

        now = self._clock()
        p, c = svc.parts, svc.counters
        mon = p.monitor.report() if p.monitor is not None else None
        est = c.last_estimate
        src_stats = p.source.stats.as_dict() if p.source is not None and hasattr(p.source, "stats") else {}
        disk_path = existing_parent(svc.session_dir if svc.session_dir is not None and svc.session_dir.exists()
                                    else Path(svc.cfg.recorder.dir))
        data: dict[str, Any] = {
            "v": STATUS_FORMAT_VERSION, "state": svc.state, "pid": os.getpid(), "updated_unix": time.time(),
            "status_interval_s": svc.cfg.service.status_interval_s,
            "session_id": svc.session_id, "session_dir": str(svc.session_dir) if svc.session_dir else None,
            "source": svc.cfg.source.backend, "imu": svc.cfg.imu.backend,
            "uptime_s": round(now - svc.ready_at, 3) if svc.ready_at is not None else 0.0,
            "frames": c.frames_in, "frames_estimated": c.frames_done, "imu_samples": c.imu_samples_in,
            "frame_rate_hz": round(self.fps.rate(now, c.frames_in), 3),
            "imu_rate_hz": round(self.imu.rate(now, c.imu_samples_in), 3),
            "camera_fps_timestamps": round(mon.camera_fps, 3) if mon else 0.0,
            "dropped_frames": mon.dropped_frames if mon else 0,
            "source_drops": {k: v for k, v in src_stats.items() if k.startswith("dropped")},
            "imu_gaps": (mon.imu_gaps if mon else 0) + len(getattr(p.imu, "gaps", []) or []),
            "tracking": est.status if est is not None else None,
            "inliers": int(est.inliers) if est is not None else 0,
            "keyframes": c.keyframes, "estimation_errors": c.estimation_errors,
            "stage_ms": {k: round(v, 2) for k, v in c.stage_ms.items()},
            "cpu_process_pct": round(self.cpu.pct(), 1), "cpu_process_avg_pct": round(self.cpu.average_pct(), 1),
            "cpu_load_pct": health.cpu_load_pct(), "temperature_c": health.cpu_temperature_c(),
            "disk_free_bytes": health.disk_free_bytes(disk_path),
            **p.recording.status_fields(),
            **p.streaming.status_fields(),
            "watchdog_s": svc.watchdog.interval_s, "watchdog_pings": svc.watchdog.pings,
            "data_fresh": svc.data_fresh(now) if svc.ready else False,
            "stop_reason": svc.stop_reason or None,
            "last_error": self.problem.text, "last_error_unix": self.problem.t_unix,
        }
        data["summary"] = status_line(data)
        return data

    def write(self, data: Mapping[str, Any]) -> None:
        """The status file (when configured); a failure is logged once and the run carries on."""
        if self.path is None:
            return
        try:
            write_status_file(self.path, data)
        except OSError as exc:
            if not self._warned:
                log.warning("cannot write the status file %s (%s); `device status` will not see this run",
                            self.path, exc)
                self._warned = True
