"""The capture service: ``source -> time align -> estimate -> (record, stream)`` with a systemd lifecycle.

One configuration file (:mod:`stereopath.device.service.settings`) describes the whole run; the same code path
serves the simulator, a replayed recording and the real cameras.  Threads:

* the **pipeline thread** pulls stereo pairs from the source, drains the IMU, attaches the
  IMU samples to each frame (:class:`~stereopath.device.capture.timealign.TimeAligner`), records the frame, runs
  the estimator, records the pose, publishes it and offers keyframes to the streamer.  The
  recorder writes in fsynced chunks; the streamer's calls never block (its own threads do the
  network), so capture and estimation never wait on a host;
* the **main thread** supervises: readiness, the systemd watchdog, the ~1 Hz health report
  (status file, ``STATUS=`` line, status message), signals, and the orderly stop.

Lifecycle (sd_notify, :mod:`stereopath.device.service.sdnotify`):

* ``READY=1`` once the first stereo pair has arrived, the IMU has delivered samples and the
  recorder is open (so a camera or IMU that never starts leaves the unit "activating" and
  systemd's start timeout fails it);
* ``WATCHDOG=1`` every half watchdog period, but only while both a frame and an IMU sample
  arrived within ``service.max_data_age_s`` (capped at half the period): a hung camera or IMU
  stops the pings and systemd restarts the service;
* ``STATUS=`` a one-line health summary each status period;
* SIGTERM/SIGINT: ``STOPPING=1``, the frame in progress finishes, keyframes are spooled (and,
  up to ``stream.drain_s``, acknowledged by a connected host), the recording is flushed and
  its manifest closed: the session on disk is complete and readable;
* SIGHUP: the configuration file is read again; settings that can change live are applied
  (time alignment, recorder reserve, status/watchdog periods, drain time), the others are
  logged as needing a restart.  A bad file is logged and the running configuration kept.

Exit status: 0 after a requested stop or a bounded run, 1 on a runtime failure (camera, IMU,
disk), :data:`EXIT_CONFIG` (78, ``EX_CONFIG``) on a bad configuration, which the unit's
``RestartPreventExitStatus=78`` keeps from restarting in a loop.  Expected faults are logged
as one line without a traceback.

Test seams: ``notifier=``, ``environ=``, ``source=`` (an unopened stereo source),
``source_inject=`` (keyword arguments for :func:`stereopath.device.capture.sources.create_source`),
``imu_inject=``, ``estimator=`` and ``clock=``.
"""

from __future__ import annotations

import collections

import dataclasses
import json
import logging
import os
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

from stereopath.device.core.config import as_dict, from_mapping, load_toml, replace
from stereopath.device.errors import ConfigError, EstimationError, StereopathError
from stereopath.device.service.sdnotify import Notifier, watchdog_interval_s
from stereopath.device.service.settings import DeviceConfig

log = logging.getLogger(__name__)

EXIT_OK, EXIT_FAILURE, EXIT_CONFIG = 0, 1, 78
CREDENTIAL_NAME = "server.key_secret"     # LoadCredential= name of the device's CURVE secret key
STATUS_FORMAT_VERSION = 1
TICK_S = 0.05                             # supervisor period


# ---------------------------------------------------------------------------------------- options


@dataclass(frozen=True)
class RunOptions:
    """Command-line overrides of ``stereopath device run`` (``None`` = keep the file's value)."""

    source: str | None = None        # sim | replay:SPEC | picamera2 | depthai
    imu: str | None = None           # mpu6050 | emulated | source | none
    out: str | None = None           # the session folder itself (default recorder.dir/<session id>)
    duration_s: float | None = None  # stop after this long (s)
    frames: int | None = None        # stop after this many stereo pairs
    stream: bool | None = None       # False = --no-stream
    insecure: bool | None = None     # True = --insecure (loopback only)
    status_file: str | None = None
    drain_s: float | None = None
    wait_for_host_s: float = 0.0     # before capturing, wait up to this long for a host to connect (demo)

    def __post_init__(self) -> None:
        if self.duration_s is not None and not self.duration_s > 0:
            raise ConfigError(f"--duration = {self.duration_s} must be > 0")
        if self.frames is not None and self.frames < 1:
            raise ConfigError(f"--frames = {self.frames} must be >= 1")
        if self.drain_s is not None and self.drain_s < 0:
            raise ConfigError(f"--drain = {self.drain_s} must be >= 0")
        if self.wait_for_host_s < 0:
            raise ConfigError(f"--wait-for-host = {self.wait_for_host_s} must be >= 0")


def _with(obj: Any, **changes: Any) -> Any:
    return replace(obj, **changes) if changes else obj


def apply_options(cfg: DeviceConfig, opts: RunOptions) -> DeviceConfig:
    """The configuration with the command-line overrides applied (validated like the file)."""
    src, imu = cfg.source, cfg.imu
    if opts.source is not None:
        spec = opts.source
        if spec.startswith("replay:"):
            path = spec[len("replay:"):]
            if not path:
                raise ConfigError("--source replay:SPEC needs a recording, e.g. replay:session:/path/to/session")
            src = _with(src, backend="replay", replay=_with(src.replay, path=path))
        elif spec in ("sim", "picamera2", "depthai", "replay"):
            src = _with(src, backend=spec)
        else:
            raise ConfigError(f"--source {spec!r} is not one of sim, replay:SPEC, picamera2, depthai")
        if opts.imu is None and src.backend in ("sim", "replay"):
            imu = _with(imu, backend="source")  # the recording's / simulator's own IMU, on the frames' clock
    if opts.imu is not None:
        imu = _with(imu, backend=opts.imu)
    stream_changes: dict[str, Any] = {}
    if opts.stream is not None:
        stream_changes["enabled"] = opts.stream
    if opts.insecure:
        stream_changes["insecure"] = True
    if opts.drain_s is not None:
        stream_changes["drain_s"] = opts.drain_s
    service = cfg.service if opts.status_file is None else _with(cfg.service, status_file=opts.status_file)
    return dataclasses.replace(cfg, source=src, imu=imu, stream=_with(cfg.stream, **stream_changes), service=service)


def load_config(path: str | Path | None, opts: RunOptions) -> DeviceConfig:
    """Defaults < file < command line."""
    cfg = DeviceConfig() if path is None else from_mapping(DeviceConfig, load_toml(path))
    return apply_options(cfg, opts)


def secret_key_path(cfg: DeviceConfig, environ: Mapping[str, str] | None = None) -> Path:
    """The device's CURVE secret key: the systemd credential when present, else ``keys.server_secret``."""
    env = os.environ if environ is None else environ
    cred_dir = env.get("CREDENTIALS_DIRECTORY")
    if cred_dir and (Path(cred_dir) / CREDENTIAL_NAME).is_file():
        return Path(cred_dir) / CREDENTIAL_NAME
    return Path(cfg.keys.server_secret)


def check_config(cfg: DeviceConfig, environ: Mapping[str, str] | None = None) -> None:
    """Checks that need the file system (key files, calibration, recording); ConfigError names the key."""
    if cfg.stream.enabled and not cfg.stream.insecure:
        secret = secret_key_path(cfg, environ)
        if not secret.is_file():
            raise ConfigError(f"keys.server_secret = {str(secret)!r}: file not found "
                              f"(create it with `stereopath device install` or `stereopath keys generate`)")
        clients = Path(cfg.keys.clients_dir)
        if not clients.is_dir():
            raise ConfigError(f"keys.clients_dir = {str(clients)!r}: directory not found")
        if not any(clients.glob("*.key")):
            raise ConfigError(f"keys.clients_dir = {str(clients)!r} holds no host public key (*.key): "
                              "no host could connect")
    if cfg.stream.enabled and cfg.stream.insecure:
        from stereopath.device.wire.security import check_loopback_endpoint

        for key in ("pose_endpoint", "keyframe_endpoint"):
            try:
                check_loopback_endpoint(getattr(cfg.stream, key))
            except ConfigError as exc:
                raise ConfigError(f"stream.{key}: {exc}") from None
    if cfg.source.rig_file and not Path(cfg.source.rig_file).is_file():
        raise ConfigError(f"source.rig_file = {cfg.source.rig_file!r}: file not found")
    if cfg.source.backend == "replay" and not cfg.source.replay.path:
        raise ConfigError("source.replay.path is empty: name the recording (session:DIR, euroc:DIR or kitti:DIR)")
    if cfg.imu.backend == "source" and cfg.source.backend == "picamera2":
        raise ConfigError("imu.backend = 'source' but the picamera2 cameras have no IMU of their own")


def flat(mapping: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}``."""
    out: dict[str, Any] = {}
    for k, v in mapping.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flat(v, key + "."))
        else:
            out[key] = v
    return out


LIVE_KEYS = ("timealign.", "recorder.reserve_mb", "service.status_interval_s", "service.max_data_age_s",
             "service.stop_timeout_s", "service.ready_timeout_s", "stream.drain_s", "selftest.")


def split_changes(old: DeviceConfig, new: DeviceConfig) -> tuple[list[str], list[str]]:
    """Changed keys that can be applied live, and those that need a restart."""
    a, b = flat(as_dict(old)), flat(as_dict(new))
    changed = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    live = [k for k in changed if k.startswith(LIVE_KEYS)]
    return live, [k for k in changed if k not in live]


# ---------------------------------------------------------------------------------------- health


class _Window:
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


class _CpuMeter:
    """This process's CPU use (all threads) in % of one core since the previous call."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        t = os.times()
        self._last = self._start = (clock(), t.user + t.system)

    def restart(self) -> None:
        t = os.times()
        self._last = self._start = (self._clock(), t.user + t.system)

    def average_pct(self) -> float:
        """Since :meth:`restart` (or construction)."""
        t = os.times()
        now, cpu = self._clock(), t.user + t.system
        return 100.0 * (cpu - self._start[1]) / (now - self._start[0]) if now > self._start[0] else 0.0

    def pct(self) -> float:
        t = os.times()
        now, cpu = self._clock(), t.user + t.system
        wall0, cpu0 = self._last
        self._last = (now, cpu)
        return 100.0 * (cpu - cpu0) / (now - wall0) if now > wall0 else 0.0


class _LastProblem(logging.Handler):
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
        f"{s.get('hosts', 0)} host(s)",
    ]
    head = f"{s.get('state', '?')} {s.get('session_id', '')}".strip()
    return f"{head}: " + ", ".join(parts)


def write_status_file(path: Path, data: Mapping[str, Any]) -> None:
    """Replace ``path`` atomically with ``data`` as JSON, readable by every user (0644)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        os.fchmod(fd, 0o644)  # the unit's UMask would make it 0640
        os.write(fd, (json.dumps(data, indent=1, default=str) + "\n").encode())
    finally:
        os.close(fd)
    os.replace(tmp, path)


# ---------------------------------------------------------------------------------------- the service


class CaptureService:
    """One capture run (see the module doc).  ``run()`` returns the process exit status."""

    def __init__(self, cfg: DeviceConfig, options: RunOptions | None = None, config_path: str | Path | None = None,
                 *, notifier: Notifier | None = None, environ: Mapping[str, str] | None = None,
                 source: Any = None, source_inject: Mapping[str, Any] | None = None,
                 imu_inject: Mapping[str, Any] | None = None, estimator: Any = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self.options = options or RunOptions()
        self.config_path = None if config_path is None else Path(config_path)
        self.environ = os.environ if environ is None else environ
        self.notifier = notifier if notifier is not None else Notifier.from_env(self.environ)
        self._source_arg = source
        self._source_inject = dict(source_inject or {})
        self._imu_inject = dict(imu_inject or {})
        self._estimator_arg = estimator
        self._clock = clock
        self.watchdog_s = watchdog_interval_s(self.environ)
        # components (opened in _setup)
        self.source: Any = None
        self.imu: Any = None
        self.recorder: Any = None
        self.streamer: Any = None
        self.estimator: Any = None
        self.aligner: Any = None
        self.monitor: Any = None
        self.session_id = ""
        self.session_dir: Path | None = None
        # state shared with the pipeline thread (plain attributes: single writer each)
        self.state = "starting"
        self.exit_code = EXIT_OK
        self.stop_reason = ""
        self.frames_in = 0
        self.frames_done = 0
        self.imu_samples_in = 0
        self.keyframes = 0
        self.estimation_errors = 0
        self.last_frame_at: float | None = None
        self.last_imu_at: float | None = None
        self.last_estimate: Any = None
        self.ready_at: float | None = None
        self.watchdog_pings = 0
        self.stage_ms: dict[str, float] = {}   # average time per frame of record / estimate / stream (ms)
        # the estimator's own time per frame (ms), kept for the session's estimator.json
        self.estimate_ms: collections.deque[float] = collections.deque(maxlen=200_000)
        self.tracked_frames = 0
        self._failure: BaseException | None = None
        self._pipeline_done = threading.Event()
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._wake = threading.Event()
        self._pending_timealign: Any = None
        self._thread: threading.Thread | None = None
        self._problem = _LastProblem()
        self._cpu = _CpuMeter(clock)
        self._fps_window, self._imu_window = _Window(), _Window()
        self._last_status: dict[str, Any] = {}
        self._status_path: Path | None = None
        self._status_warned = False
        self._client_keys_at_start: dict[str, bytes] = {}

    # ------------------------------------------------------------------ control (any thread, signal handlers)

    def request_stop(self, reason: str = "stop requested") -> None:
        if not self._stop.is_set():
            self.stop_reason = self.stop_reason or reason
            self._stop.set()
        self._wake.set()

    def request_reload(self) -> None:
        self._reload.set()
        self._wake.set()

    @property
    def ready(self) -> bool:
        return self.ready_at is not None

    # ------------------------------------------------------------------ run

    def run(self) -> int:
        logging.getLogger().addHandler(self._problem)
        try:
            return self._run()
        finally:
            logging.getLogger().removeHandler(self._problem)
            self.notifier.close()

    def _run(self) -> int:
        self._set_status_path(self.cfg.service.status_file)
        self.notifier.notify(STATUS="starting: opening the cameras, the IMU and the recorder")
        try:
            self._setup()
        except ConfigError as exc:
            log.error("configuration error: %s", exc)
            self._fail_start("configuration error", exc, EXIT_CONFIG)
            return self.exit_code
        except StereopathError as exc:
            log.error("cannot start: %s", exc)
            self._fail_start("failed to start", exc, EXIT_FAILURE)
            return self.exit_code
        except BaseException:
            self._teardown()
            raise
        self._wait_for_host()
        self._thread = threading.Thread(target=self._pipeline, name="stereopath-pipeline", daemon=True)
        started = self._clock()
        self._thread.start()
        self._supervise(started)
        self._shutdown()
        return self.exit_code

    def _fail_start(self, what: str, exc: BaseException, code: int) -> None:
        self.exit_code = code
        self.state = "failed"
        self.notifier.notify(STATUS=f"{what}: {exc}")
        self._teardown()
        self._write_status(final=True)

    # ------------------------------------------------------------------ set-up

    def _setup(self) -> None:
        from stereopath.device.estimation.registry import make_estimator
        from stereopath.device.capture.imu import PollingImuReader, create_imu
        from stereopath.device.formats.recorder import SessionRecorder, new_session_id
        from stereopath.device.capture.sources import create_source
        from stereopath.device.capture.timealign import RateMonitor, TimeAligner

        cfg = self.cfg
        check_config(cfg, self.environ)
        log.info("configuration%s: %s", f" from {self.config_path}" if self.config_path else " (built-in defaults)",
                 json.dumps(as_dict(cfg), separators=(",", ":"), default=str))
        self.session_id = new_session_id()
        self.session_dir = Path(self.options.out) if self.options.out else Path(cfg.recorder.dir) / self.session_id
        if self.session_dir.exists() and (not self.session_dir.is_dir() or any(self.session_dir.iterdir())):
            raise ConfigError(f"--out {self.session_dir}: exists and is not empty (a session is never overwritten)")
        # source
        self.source = self._source_arg
        if self.source is None:
            self.source = create_source(cfg.source, **self._source_inject)
        self.source.open()
        rig = self.source.rig
        if rig is None:
            raise ConfigError(f"source.rig_file: the {cfg.source.backend} source has no calibration of its own; "
                              "name a rig YAML")
        # IMU (the source's own is read directly; a chip is polled on its own thread)
        imu = create_imu(cfg.imu, stereo_source=self.source, **self._imu_inject_for(cfg))
        if imu is not None and cfg.imu.backend in ("mpu6050", "emulated"):
            imu = PollingImuReader(imu, cfg.imu.read_period_ms / 1000.0)
        if imu is not None:
            imu.open()
        self.imu = imu
        if cfg.source.backend in ("sim", "replay") and cfg.imu.backend in ("mpu6050", "emulated"):
            log.warning("%s frames keep their recorded clock but the %s IMU runs on this machine's clock: "
                        "IMU blocks will not match the frames (imu.backend = 'source' uses the %s's own IMU)",
                        cfg.source.backend, cfg.imu.backend, cfg.source.backend)
        cam_hz, imu_hz = self._nominal_rates()
        # estimator
        if self._estimator_arg is not None:
            self.estimator = self._estimator_arg
        else:
            gt = getattr(getattr(self.source, "session", None), "groundtruth", None)
            self.estimator = make_estimator(cfg.estimator.preset, rig, groundtruth=gt)
        self.monitor = RateMonitor(cam_hz if cfg.source.backend in ("picamera2", "depthai") else None,
                                   imu_hz if cfg.imu.backend in ("mpu6050", "emulated") else None,
                                   cfg.timealign.gap_factor)
        self.aligner = TimeAligner.from_settings(cfg.timealign, imu_hz if imu is not None else None, self.monitor)
        # recorder
        if cfg.recorder.enabled:
            self.recorder = SessionRecorder(self.session_dir, rig, as_dict(cfg), session_id=self.session_id,
                                            reserve_bytes=int(cfg.recorder.reserve_mb * 1e6),
                                            cam_rate_hz=cam_hz, imu_rate_hz=imu_hz or 200.0)
        else:
            log.warning("recorder.enabled = false: this session is not recorded")
        # streamer
        if cfg.stream.enabled:
            from stereopath.device.streaming import DeviceStreamer, KeyframeSpool, StreamConfig

            spool = KeyframeSpool(self.session_dir / "keyframes")
            scfg = StreamConfig(pose_endpoint=cfg.stream.pose_endpoint, keyframe_endpoint=cfg.stream.keyframe_endpoint,
                                insecure=cfg.stream.insecure, server_secret=str(secret_key_path(cfg, self.environ)),
                                clients_dir=cfg.keys.clients_dir, image_encoding=cfg.stream.image_encoding,
                                jpeg_quality=cfg.stream.jpeg_quality,
                                status_interval_s=cfg.service.status_interval_s)
            self.streamer = DeviceStreamer(scfg, spool, self.session_id, rig=rig)
        else:
            log.info("streaming disabled")
        self._client_keys_at_start = self._client_keys()
        self.state = "waiting"
        self._write_status()

    def _client_keys(self) -> dict[str, bytes]:
        """The authorised host keys (read at start by the streamer's authenticator)."""
        d = Path(self.cfg.keys.clients_dir)
        try:
            return {p.name: p.read_bytes() for p in sorted(d.glob("*.key"))}
        except OSError:
            return {}

    def _wait_for_host(self) -> None:
        """``--wait-for-host``: hold capture until a host has said hello, so it sees every pose."""
        st, limit = self.streamer, self.options.wait_for_host_s
        if st is None or limit <= 0:
            return
        self.notifier.notify(STATUS="waiting for a host to connect")
        deadline = self._clock() + limit
        while not self._stop.is_set() and self._clock() < deadline:
            if any(p.get("connected") for p in st.stats().get("peers", [])):
                log.info("a host is connected; starting capture")
                self._stop.wait(0.3)  # let its pose subscription reach the publisher
                return
            self._stop.wait(0.05)
        if not self._stop.is_set():
            log.warning("no host connected within %g s; capturing anyway", limit)

    def _imu_inject_for(self, cfg: DeviceConfig) -> dict[str, Any]:
        inject = dict(self._imu_inject)
        if cfg.imu.backend == "emulated" and "clock" not in inject:
            from stereopath.device.capture.imu.emulator import RealClock

            inject["clock"] = RealClock()  # the emulator on the wall clock, like the chip
        return inject

    def _nominal_rates(self) -> tuple[float, float | None]:
        """(camera Hz, IMU Hz) for the session's sensor files and the rate monitor."""
        import numpy as np

        cfg = self.cfg
        cam_hz, imu_hz = float(cfg.source.fps), None
        seq = getattr(self.source, "session", None) or getattr(self.source, "sequence", None)
        t = getattr(seq, "t_ns", None)
        if cfg.source.backend in ("sim", "replay") and t is not None and len(t) > 2:
            d = np.diff(np.asarray(t, dtype=np.int64))
            d = d[d > 0]
            if d.size:
                cam_hz = round(1e9 / float(np.median(d)), 3)
        if cfg.imu.backend in ("mpu6050", "emulated"):
            imu_hz = float(cfg.imu.rate_hz)
        elif cfg.imu.backend == "source":
            samples = getattr(getattr(self.source, "imu", None), "samples", None)
            if samples is not None and len(samples) > 2:
                d = np.diff(samples.t_ns)
                d = d[d > 0]
                imu_hz = round(1e9 / float(np.median(d)), 3) if d.size else None
            elif cfg.source.backend == "depthai":
                imu_hz = float(cfg.source.depthai.imu_rate_hz)
        return cam_hz, imu_hz

    # ------------------------------------------------------------------ pipeline thread

    def _pipeline(self) -> None:
        imu = self.imu
        try:
            frames = iter(self.source)
            while not self._stop.is_set():
                frame = next(frames, None)
                if frame is None:
                    self.request_stop("the source has no more frames")
                    break
                now = self._clock()
                self.last_frame_at = now
                self.frames_in += 1
                if imu is not None:
                    self._take_imu(now)
                if self._pending_timealign is not None:
                    self._apply_timealign()
                for done in self.aligner.add_frame(frame):
                    self._handle(done)
                limit = self.options.frames
                if limit is not None and self.frames_in >= limit:
                    self.request_stop(f"{limit} frames captured")
                    break
            if imu is not None and self._failure is None:
                self._take_imu(self._clock())
            for done in self.aligner.flush():
                self._handle(done)
        except StereopathError as exc:
            if self._stop.is_set() and self.frames_in:
                log.info("pipeline ended while stopping: %s", exc)
            else:
                self._failure = exc
        except Exception as exc:  # a bug: keep the traceback
            log.exception("pipeline thread failed")
            self._failure = exc
        finally:
            self._pipeline_done.set()
            self._wake.set()

    def _take_imu(self, now: float) -> None:
        block = self.imu.read()
        if len(block):
            self.last_imu_at = now
            self.imu_samples_in += len(block)
            if self.recorder is not None:
                self.recorder.add_imu(block)
            self.aligner.add_imu(block)

    def _time(self, stage: str, t0: float) -> float:
        """Exponential average of a stage's time per frame (ms); returns now."""
        t1 = time.perf_counter()
        ms = (t1 - t0) * 1e3
        old = self.stage_ms.get(stage)
        self.stage_ms[stage] = ms if old is None else 0.9 * old + 0.1 * ms
        return t1

    def _handle(self, frame: Any) -> None:
        rec = self.recorder
        t0 = time.perf_counter()
        if rec is not None:
            rec.add_frame(frame)
            t0 = self._time("record", t0)
        try:
            est = self.estimator.process(frame, frame.meta.get("imu"))
            t_est = t0
            t0 = self._time("estimate", t0)
            self.estimate_ms.append((t0 - t_est) * 1e3)
        except EstimationError as exc:
            self.estimation_errors += 1
            log.log(logging.WARNING if self.estimation_errors == 1 else logging.DEBUG,
                    "frame %d not estimated: %s%s", frame.seq, exc,
                    " (further failures are counted in the status)" if self.estimation_errors == 1 else "")
            return
        self.last_estimate = est
        self.frames_done += 1
        self.tracked_frames += est.status == "ok"
        if rec is not None:
            rec.add_pose(est.t_ns, est.T_world_cam)
        st = self.streamer
        if st is not None:
            st.publish_pose(est.seq, est.t_ns, est.T_world_cam, tracking=est.status, inliers=int(est.inliers),
                            keyframe=bool(est.keyframe))
        if est.keyframe:
            self.keyframes += 1
            if st is not None:
                st.offer_keyframe(frame.seq, frame.t_ns, est.T_world_cam, frame.left, frame.right)
        if st is not None:
            self._time("stream", t0)

    def _apply_timealign(self) -> None:
        s, self._pending_timealign = self._pending_timealign, None
        a = self.aligner
        a.time_offset_ns = int(round(s.time_offset_us * 1000))
        a.max_wait_ns = int(round(s.max_wait_ms * 1e6))
        a.gap_factor = float(s.gap_factor)

    # ------------------------------------------------------------------ supervisor (main thread)

    def _ping_interval(self) -> float | None:
        return None if self.watchdog_s is None else self.watchdog_s / 2.0

    def max_data_age_s(self) -> float:
        age = self.cfg.service.max_data_age_s
        return age if self.watchdog_s is None else min(age, self.watchdog_s / 2.0)

    def data_fresh(self, now: float) -> bool:
        """A frame and (when an IMU is configured) an IMU sample arrived within the allowed age."""
        age = self.max_data_age_s()
        if self.last_frame_at is None or now - self.last_frame_at > age:
            return False
        if self.imu is not None and (self.last_imu_at is None or now - self.last_imu_at > age):
            return False
        return True

    def _supervise(self, started: float) -> None:
        next_status = started
        last_ping = None
        while True:
            self._wake.wait(TICK_S)
            self._wake.clear()
            now = self._clock()
            if self._reload.is_set():
                self._reload.clear()
                self._do_reload()
            if not self.ready and self._failure is None and self.last_frame_at is not None \
                    and (self.imu is None or self.last_imu_at is not None):
                self._become_ready(now)
                next_status = now
            if self._pipeline_done.is_set():
                if self._failure is not None:
                    self._fail(self._failure)
                elif not self._stop.is_set():
                    self.request_stop("the pipeline ended")
            if self._stop.is_set():
                return
            if not self.ready:
                if now - started > self.cfg.service.ready_timeout_s:
                    missing = (f"no stereo pair from the {self.cfg.source.backend} source"
                               if self.last_frame_at is None else f"no samples from the {self.cfg.imu.backend} IMU")
                    self._fail(StereopathError(f"not ready after {self.cfg.service.ready_timeout_s:g} s: {missing}"))
                    return
            else:
                interval = self._ping_interval()
                if interval is not None and self.data_fresh(now) and (last_ping is None or now - last_ping >= interval):
                    if self.notifier.notify("WATCHDOG=1"):
                        self.watchdog_pings += 1
                    last_ping = now
                if self.options.duration_s is not None and now - self.ready_at >= self.options.duration_s:
                    self.request_stop(f"{self.options.duration_s:g} s elapsed")
                    return
            if now >= next_status:
                status = self._write_status()
                if self.ready:
                    self.notifier.notify(STATUS=status_line(status))
                next_status = now + self.cfg.service.status_interval_s

    def _become_ready(self, now: float) -> None:
        self.ready_at = now
        self._cpu.restart()
        self.state = "running"
        status = self._write_status()
        self.notifier.notify(READY=1, STATUS=status_line(status))
        endpoints = ""
        if self.streamer is not None:
            endpoints = f"; streaming on {self.streamer.pose_endpoint} and {self.streamer.keyframe_endpoint}"
        log.info("ready: session %s in %s%s", self.session_id, self.session_dir, endpoints)

    def _fail(self, exc: BaseException) -> None:
        if isinstance(exc, StereopathError):
            log.error("stopping: %s", exc)
        self.exit_code = EXIT_FAILURE
        self.state = "failed"
        self.request_stop(f"failure: {exc}")

    def _do_reload(self) -> None:
        if self.config_path is None:
            log.warning("SIGHUP: no configuration file to reload (started with built-in defaults)")
            return
        self.notifier.notify(RELOADING=1, MONOTONIC_USEC=time.monotonic_ns() // 1000)
        try:
            new = load_config(self.config_path, self.options)
            check_config(new, self.environ)
        except ConfigError as exc:
            log.error("reload of %s failed, keeping the running configuration: %s", self.config_path, exc)
            self.notifier.notify(READY=1)
            return
        live, restart = split_changes(self.cfg, new)
        if self.streamer is not None and not self.cfg.stream.insecure \
                and self._client_keys() != self._client_keys_at_start:
            restart.append(f"host keys in {new.keys.clients_dir}")
        if live:
            if any(k.startswith("timealign.") for k in live):
                self._pending_timealign = new.timealign
            if self.recorder is not None and "recorder.reserve_mb" in live:
                self.recorder.reserve_bytes = int(new.recorder.reserve_mb * 1e6)
            old = self.cfg
            self.cfg = dataclasses.replace(
                old, timealign=new.timealign, selftest=new.selftest,
                service=dataclasses.replace(new.service, status_file=old.service.status_file),
                recorder=dataclasses.replace(old.recorder, reserve_mb=new.recorder.reserve_mb),
                stream=dataclasses.replace(old.stream, drain_s=new.stream.drain_s))
        log.info("configuration reloaded from %s: applied %s%s", self.config_path,
                 ", ".join(live) or "nothing",
                 f"; needs a restart: {', '.join(restart)}" if restart else "")
        self.notifier.notify(READY=1)

    # ------------------------------------------------------------------ stop

    def _shutdown(self) -> None:
        self.notifier.notify(STOPPING=1, STATUS=f"stopping: {self.stop_reason}")
        log.info("stopping: %s", self.stop_reason)
        now = self._clock()
        if self.ready and not self.data_fresh(now):  # e.g. the watchdog's SIGTERM: say which sensor went quiet
            ages = {"frame": self.last_frame_at, "IMU sample": self.last_imu_at if self.imu is not None else now}
            quiet = [f"no {k} for {now - t:.1f} s" for k, t in ages.items() if t is not None and
                     now - t > self.max_data_age_s()]
            if quiet:
                log.warning("sensor data stopped before the stop request: %s", ", ".join(quiet))
        if self.state != "failed":
            self.state = "stopping"
        self._write_status()
        thread = self._thread
        stop_timeout = self.cfg.service.stop_timeout_s
        if thread is not None:
            thread.join(min(2.0, stop_timeout))
            if thread.is_alive():  # blocked in the source: closing it unblocks the iterator
                self._close_source()
                thread.join(stop_timeout)
            if thread.is_alive():
                log.error("the pipeline did not stop within %.0f s (camera or IMU hung); closing the session anyway",
                          stop_timeout)
        if self._failure is not None and self.exit_code == EXIT_OK:
            self._fail(self._failure)
        self._drain()
        self._teardown()
        if self.state != "failed":
            self.state = "stopped"
        self._write_status(final=True)
        rec = self.recorder
        log.info("session %s ended (%s): %d frames in, %d estimated, %d keyframes, recorder %s", self.session_id,
                 self.stop_reason, self.frames_in, self.frames_done, self.keyframes,
                 rec.state if rec is not None else "off")

    def _drain(self) -> None:
        st = self.streamer
        drain_s = self.cfg.stream.drain_s
        if st is None or drain_s <= 0:
            return
        deadline = self._clock() + drain_s
        while self._clock() < deadline:
            s = st.stats()
            accepted = s["keyframes_offered"] - s["keyframes_refused"]
            spooled_all = s["keyframes_spooled"] + s["keyframes_failed"] >= accepted
            peers = s.get("peers", [])
            if not peers:
                return  # no host has said hello: nobody to wait for
            if spooled_all and any(p["acked"] >= st.spool.last_seq for p in peers):
                log.info("every keyframe (%d) acknowledged by a host", st.spool.count)
                return
            time.sleep(0.05)
        log.warning("stopping with keyframes not yet acknowledged by any host (they stay in %s)", st.spool.dir)

    def _close_source(self) -> None:
        src = self.source
        if src is None:
            return
        try:
            src.close()
        except StereopathError as exc:
            log.warning("closing the source: %s", exc)

    def _teardown(self) -> None:
        """Close everything that was opened, in reverse order; each step is independent."""
        if self.streamer is not None:
            self.streamer.close()
        self._write_groundtruth()
        self._write_estimator_summary()
        if self.recorder is not None:
            try:
                self.recorder.close()
            except StereopathError as exc:
                log.error("closing the recording: %s", exc)
                self.exit_code = self.exit_code or EXIT_FAILURE
        close = getattr(self.estimator, "close", None)
        if close is not None:
            close()
        if self.imu is not None:
            try:
                self.imu.close()
            except StereopathError as exc:
                log.warning("closing the IMU: %s", exc)
        self._close_source()

    def _write_estimator_summary(self) -> None:
        """``estimator.json`` in the session: the estimator's time per frame and tracking counts."""
        rec = self.recorder
        if rec is None or not self.estimate_ms:
            return
        import json

        import numpy as np

        ms = np.array(self.estimate_ms)
        stats = getattr(self.estimator, "stats", lambda: {})()
        summary = {
            "estimator": getattr(self.estimator, "name", "?"),
            "world_frame": getattr(self.estimator, "world_frame", "first_camera"),
            "frames": int(self.frames_done), "frames_tracked": int(self.tracked_frames),
            "median_frame_ms": float(np.median(ms)), "p95_frame_ms": float(np.percentile(ms, 95)),
            "stats": {k: v for k, v in stats.items() if isinstance(v, (int, float, bool, str))},
            "frame_ms": [round(float(v), 3) for v in ms],
        }
        try:
            path = Path(rec.dir) / "estimator.json"
            tmp = path.with_suffix(".json.tmp")
            tmp.write_text(json.dumps(summary, indent=2))
            os.replace(tmp, path)
        except OSError as exc:
            log.warning("could not write estimator.json: %s", exc)

    def _write_groundtruth(self) -> None:
        """Simulated runs: ground truth over the frames recorded (for evaluating the session)."""
        rec = self.recorder
        gt = getattr(getattr(self.source, "session", None), "groundtruth", None)
        if rec is None or gt is None or rec.state not in ("recording", "stopped_low_disk") or not rec.counts["frames"]:
            return
        from stereopath.device.formats.tum import Trajectory

        last = rec.manifest().get("last_frame_t_ns")
        keep = gt.t_ns <= last
        if keep.any():
            rec.write_groundtruth(Trajectory(gt.t_ns[keep], gt.T_world_cam[keep]))

    # ------------------------------------------------------------------ status

    def _set_status_path(self, path: str) -> None:
        self._status_path = Path(path) if path else None

    def status(self) -> dict[str, Any]:
        """The health report (written to the status file each period)."""
        from stereopath.device.streaming import health

        now = self._clock()
        mon = self.monitor.report() if self.monitor is not None else None
        est = self.last_estimate
        st = self.streamer
        sstats: dict[str, Any] = {}
        if st is not None:
            try:
                sstats = st.stats()
            except RuntimeError:  # peers changed while copied; next period
                sstats = {}
        rec = self.recorder
        src_stats = self.source.stats.as_dict() if self.source is not None and hasattr(self.source, "stats") else {}
        imu_gaps = (mon.imu_gaps if mon else 0) + len(getattr(self.imu, "gaps", []) or [])
        disk_path = self.session_dir if self.session_dir is not None and self.session_dir.exists() else \
            Path(self.cfg.recorder.dir)
        while not disk_path.exists() and disk_path != disk_path.parent:
            disk_path = disk_path.parent
        data: dict[str, Any] = {
            "v": STATUS_FORMAT_VERSION,
            "state": self.state,
            "pid": os.getpid(),
            "updated_unix": time.time(),
            "status_interval_s": self.cfg.service.status_interval_s,
            "session_id": self.session_id,
            "session_dir": str(self.session_dir) if self.session_dir else None,
            "source": self.cfg.source.backend,
            "imu": self.cfg.imu.backend,
            "uptime_s": round(now - self.ready_at, 3) if self.ready_at is not None else 0.0,
            "frames": self.frames_in,
            "frames_estimated": self.frames_done,
            "imu_samples": self.imu_samples_in,
            "frame_rate_hz": round(self._fps_window.rate(now, self.frames_in), 3),
            "imu_rate_hz": round(self._imu_window.rate(now, self.imu_samples_in), 3),
            "camera_fps_timestamps": round(mon.camera_fps, 3) if mon else 0.0,
            "dropped_frames": mon.dropped_frames if mon else 0,
            "source_drops": {k: v for k, v in src_stats.items() if k.startswith("dropped")},
            "imu_gaps": imu_gaps,
            "tracking": est.status if est is not None else None,
            "inliers": int(est.inliers) if est is not None else 0,
            "keyframes": self.keyframes,
            "estimation_errors": self.estimation_errors,
            "stage_ms": {k: round(v, 2) for k, v in self.stage_ms.items()},
            "cpu_process_pct": round(self._cpu.pct(), 1),
            "cpu_process_avg_pct": round(self._cpu.average_pct(), 1),
            "cpu_load_pct": health.cpu_load_pct(),
            "temperature_c": health.cpu_temperature_c(),
            "disk_free_bytes": health.disk_free_bytes(disk_path),
            "recorder_state": rec.state if rec is not None else "off",
            "recorder_counts": dict(rec.counts) if rec is not None else {},
            "streaming": st is not None,
            "pose_endpoint": st.pose_endpoint if st is not None else None,
            "keyframe_endpoint": st.keyframe_endpoint if st is not None else None,
            "hosts": sum(1 for p in sstats.get("peers", []) if p.get("connected")),
            "poses_sent": sstats.get("poses_sent", 0),
            "keyframes_spooled": sstats.get("spool_count", 0),
            "keyframes_refused": sstats.get("keyframes_refused", 0),
            "watchdog_s": self.watchdog_s,
            "watchdog_pings": self.watchdog_pings,
            "data_fresh": self.data_fresh(now) if self.ready else False,
            "stop_reason": self.stop_reason or None,
            "last_error": self._problem.text,
            "last_error_unix": self._problem.t_unix,
        }
        data["summary"] = status_line(data)
        return data

    def _write_status(self, final: bool = False) -> dict[str, Any]:
        data = self.status()
        self._last_status = data
        st = self.streamer
        if st is not None and not final:
            st.publish_status(frame_rate_hz=data["frame_rate_hz"], imu_rate_hz=data["imu_rate_hz"],
                              dropped_frames=data["dropped_frames"], imu_gaps=data["imu_gaps"],
                              cpu_load_pct=data["cpu_load_pct"], temperature_c=data["temperature_c"],
                              disk_free_bytes=data["disk_free_bytes"], recorder_state=data["recorder_state"])
        path = self._status_path
        if path is not None:
            try:
                write_status_file(path, data)
            except OSError as exc:
                if not self._status_warned:
                    log.warning("cannot write the status file %s (%s); `device status` will not see this run",
                                path, exc)
                    self._status_warned = True
        return data


# ---------------------------------------------------------------------------------------- entry point


class _JournalFormatter(logging.Formatter):
    """Prefix each line with its syslog priority (``<3>``) so journald files it at the right level."""

    PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3, logging.CRITICAL: 2}

    def format(self, record: logging.LogRecord) -> str:
        prio = self.PRIORITY.get(record.levelno, 6)
        return f"<{prio}>" + super().format(record).replace("\n", " | ")


def use_journal_format(environ: Mapping[str, str] | None = None) -> bool:
    """When stderr is connected to the journal (``$JOURNAL_STREAM``), tag log lines with priorities."""
    import sys

    env = os.environ if environ is None else environ
    stream = env.get("JOURNAL_STREAM", "")
    try:
        st = os.fstat(sys.stderr.fileno())
    except (OSError, ValueError, AttributeError):
        return False
    if stream != f"{st.st_dev}:{st.st_ino}":
        return False
    for handler in logging.getLogger().handlers:
        handler.setFormatter(_JournalFormatter("%(levelname)s %(name)s: %(message)s"))
    return True


def run_service(config_path: str | Path | None, options: RunOptions | None = None, **inject: Any) -> int:
    """Load the configuration, handle signals (in the main thread) and run one capture session.

    Returns the exit status (0, 1, or 78 for a bad configuration, reported on one log line).
    """
    options = options or RunOptions()
    try:
        cfg = load_config(config_path, options)
    except ConfigError as exc:
        log.error("configuration error: %s", exc)
        Notifier.from_env(inject.get("environ")).notify(STATUS=f"configuration error: {exc}")
        return EXIT_CONFIG
    service = CaptureService(cfg, options, config_path, **inject)
    in_main = threading.current_thread() is threading.main_thread()
    previous: dict[int, Any] = {}
    if in_main:
        def on_stop(signum: int, _frame: Any) -> None:
            service.request_stop(f"signal {signal.Signals(signum).name}")

        def on_hup(_signum: int, _frame: Any) -> None:
            service.request_reload()

        for sig, handler in ((signal.SIGTERM, on_stop), (signal.SIGINT, on_stop), (signal.SIGHUP, on_hup)):
            previous[sig] = signal.signal(sig, handler)
    try:
        return service.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
