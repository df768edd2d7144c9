"""Opening one run's parts from the configuration: source, IMU, estimator, time alignment and sinks.

This is the one place that looks at which backends are configured (through
:attr:`SourceSettings.recorded` and :attr:`ImuSettings.polled`); everything downstream of it sees
a source, an IMU (or None), an estimator and two sinks.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Mapping

from stereopath.device.core.config import as_dict
from stereopath.device.core.frames import median_rate_hz
from stereopath.device.errors import CalibrationError, ConfigError
from stereopath.device.service.options import secret_key_path
from stereopath.device.settings import DeviceConfig
from stereopath.device.service.sinks import NoRecording, NoStreaming, RecordingSink, StreamingSink

if TYPE_CHECKING:
    from stereopath.device.capture.imu.base import ImuSource
    from stereopath.device.capture.sources.base import StereoSource
    from stereopath.device.capture.timealign import RateMonitor, TimeAligner
    from stereopath.device.core.rig import Rig
    from stereopath.device.estimation.base import Estimator

log = logging.getLogger(__name__)


@dataclass
class Components:
    source: StereoSource | None = None
    imu: ImuSource | None = None
    estimator: Estimator | None = None
    monitor: RateMonitor | None = None
    aligner: TimeAligner | None = None
    recording: NoRecording = NoRecording()
    streaming: NoStreaming = NoStreaming()


@dataclass(frozen=True)
class RunSeams:
    """What a run uses instead of what the configuration opens (tests, benchmarks): an unopened
    stereo source, keyword arguments for ``create_source`` / ``create_imu``, an estimator."""

    source: StereoSource | None = None
    source_inject: Mapping[str, object] = field(default_factory=dict)
    imu_inject: Mapping[str, object] = field(default_factory=dict)
    estimator: Estimator | None = None


def open_source(cfg: DeviceConfig, source: StereoSource | None, inject: Mapping[str, object]) -> StereoSource:
    """The configured (or injected, unopened) stereo source, opened; it must carry a rig."""
    from stereopath.device.capture.sources import create_source

    try:
        if source is None:
            source = create_source(cfg.source, **inject)
        source.open()
    except CalibrationError as exc:  # a bad rig is a configuration problem: 78, not a runtime failure
        where = f"source.rig_file = {cfg.source.rig_file!r}" if cfg.source.rig_file else \
            f"the {cfg.source.backend} source's own calibration"
        raise ConfigError(f"unusable rig calibration ({where}): {exc}") from None
    if source.rig is None:
        source.close()
        raise ConfigError(f"source.rig_file: the {cfg.source.backend} source has no calibration of its own; "
                          "name a rig YAML")
    return source


def open_imu(cfg: DeviceConfig, source: StereoSource, inject: Mapping[str, object]) -> ImuSource | None:
    """The IMU (the source's own is read directly; a chip is polled on its own thread), or None."""
    from stereopath.device.capture.imu import PollingImuReader, create_imu

    inject = dict(inject)
    if cfg.imu.backend == "emulated" and "clock" not in inject:
        from stereopath.device.capture.imu.emulator import RealClock

        inject["clock"] = RealClock()  # the emulator on the wall clock, like the chip
    imu = create_imu(cfg.imu, stereo_source=source, **inject)
    if imu is not None and cfg.imu.polled:
        imu = PollingImuReader(imu, cfg.imu.read_period_ms / 1000.0)
    if imu is not None:
        imu.open()
    if cfg.source.recorded and cfg.imu.polled:
        log.warning("%s frames keep their recorded clock but the %s IMU runs on this machine's clock: "
                    "IMU blocks will not match the frames (imu.backend = 'source' uses the %s's own IMU)",
                    cfg.source.backend, cfg.imu.backend, cfg.source.backend)
    return imu


def nominal_rates(cfg: DeviceConfig, source: StereoSource) -> tuple[float, float | None]:
    """(camera Hz, IMU Hz) for the session's sensor files and the rate monitor."""
    cam_hz: float = float(cfg.source.fps)
    if cfg.source.recorded:
        seq = getattr(source, "session", None) or getattr(source, "sequence", None)
        t_ns = getattr(seq, "t_ns", None)
        cam_hz = (median_rate_hz(t_ns) if t_ns is not None and len(t_ns) > 2 else None) or cam_hz
    imu_hz: float | None = None
    if cfg.imu.polled:
        imu_hz = float(cfg.imu.rate_hz)
    elif cfg.imu.backend == "source":
        samples = getattr(getattr(source, "imu", None), "samples", None)
        if samples is not None and len(samples) > 2:
            imu_hz = median_rate_hz(samples.t_ns)
        elif cfg.source.backend == "depthai":
            imu_hz = float(cfg.source.depthai.imu_rate_hz)
    return cam_hz, imu_hz


def open_recording(cfg: DeviceConfig, session_dir: Path, session_id: str, rig: Rig,
                   rates: tuple[float, float | None]) -> NoRecording:
    """The session recorder, or the do-nothing default when ``recorder.enabled = false``."""
    from stereopath.device.formats.recorder import SensorInfo, SessionRecorder

    if not cfg.recorder.enabled:
        log.warning("recorder.enabled = false: this session is not recorded")
        return NoRecording()
    cam_hz, imu_hz = rates
    return RecordingSink(SessionRecorder(session_dir, rig, as_dict(cfg), session_id=session_id,
                                         reserve_bytes=int(cfg.recorder.reserve_mb * 1e6),
                                         sensors=SensorInfo(cam_rate_hz=cam_hz, imu_rate_hz=imu_hz or 200.0)))


def open_streaming(cfg: DeviceConfig, session_dir: Path, session_id: str, rig: Rig,
                   environ: Mapping[str, str]) -> NoStreaming:
    """The streamer, or the do-nothing default when ``stream.enabled = false``."""
    if not cfg.stream.enabled:
        log.info("streaming disabled")
        return NoStreaming()
    import dataclasses

    from stereopath.device.streaming import DeviceStreamer, KeyframeSpool

    spool = KeyframeSpool(session_dir / "keyframes", fsync=cfg.stream.spool_fsync,
                          reserve_bytes=int(cfg.recorder.reserve_mb * 1e6))
    keys = dataclasses.replace(cfg.keys, server_secret=str(secret_key_path(cfg, environ)))
    # earlier sessions' spools: beside this session's folder (its --out parent) and in recorder.dir
    roots = [session_dir.parent, Path(cfg.recorder.dir)]
    return StreamingSink(DeviceStreamer(cfg.stream, spool, session_id, rig=rig, keys=keys,
                                        status_interval_s=cfg.service.status_interval_s, backlog_roots=roots))


def open_components(cfg: DeviceConfig, session_dir: Path, session_id: str, *, seams: RunSeams = RunSeams(),
                    environ: Mapping[str, str] | None = None, parts: Components | None = None) -> Components:
    """Open everything a run needs, in order; ``parts`` (filled as each opens) lets a failed start close them."""
    from stereopath.device.capture.timealign import RateMonitor, TimeAligner
    from stereopath.device.estimation.registry import make_estimator

    c = parts if parts is not None else Components()
    c.source = source = open_source(cfg, seams.source, seams.source_inject)
    c.imu = open_imu(cfg, source, seams.imu_inject)
    cam_hz, imu_hz = nominal_rates(cfg, source)
    rig = source.rig
    assert rig is not None  # open_source refuses a source without one
    c.estimator = (seams.estimator if seams.estimator is not None
                   else make_estimator(cfg.estimator.name, rig, options=cfg.estimator.stereo))
    c.monitor = RateMonitor(None if cfg.source.recorded else cam_hz, imu_hz if cfg.imu.polled else None,
                            cfg.timealign.gap_factor)
    c.aligner = TimeAligner.from_settings(cfg.timealign, imu_hz if c.imu is not None else None, c.monitor)
    c.recording = open_recording(cfg, session_dir, session_id, rig, (cam_hz, imu_hz))
    c.streaming = open_streaming(cfg, session_dir, session_id, rig, environ or {})
    return c
