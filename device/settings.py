"""Device configuration: one frozen dataclass per stage, loaded from TOML.

Precedence: dataclass defaults < configuration file < command line.  A
documented example with every key, its unit and its default lives in
``firmware_cfg/device.toml``; a test keeps the two in step.

Sections (TOML tables):

``[source]``      which stereo backend and the capture settings shared by all of them,
                  with one sub-table per backend (``[source.picamera2]``, ``[source.depthai]``,
                  ``[source.replay]``, ``[source.sim]``);
``[imu]``         the inertial sensor (MPU-6050 on I2C, its emulator, the source's own, or none);
``[timealign]``   camera-IMU time offset and how long a frame may wait for IMU samples;
``[estimator]``   which motion estimator runs (``name``; the old key ``preset`` is still read) and its
                  settings by stage (``[estimator.stereo.*]``);
``[stream]``      ZeroMQ endpoints, security and keyframe encoding;
``[keys]``        CURVE key locations;
``[recorder]``    session directory and free-disk reserve;
``[service]``     the capture service: status file, watchdog data age, start/stop timeouts;
``[selftest]``    pass/fail limits of ``stereopath device selftest``.

Other stages add their own section dataclass here and a field in :class:`DeviceConfig`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Mapping

from stereopath.device.core.config import check_range, from_mapping, load_toml
from stereopath.device.core.stereo_config import StereoConfig
from stereopath.device.errors import ConfigError

log = logging.getLogger(__name__)

SourceBackend = Literal["picamera2", "depthai", "replay", "sim"]
ImuBackend = Literal["mpu6050", "emulated", "source", "none"]

GYRO_RANGES_DPS = (250, 500, 1000, 2000)
ACCEL_RANGES_G = (2, 4, 8, 16)


@dataclass(frozen=True)
class Picamera2Settings:
    """Two CSI cameras through picamera2 (Raspberry Pi 5)."""

    left_id: str = ""            # libcamera camera Id of the left camera ("" = first listed)
    right_id: str = ""           # ... of the right camera ("" = second listed)
    sync: Literal["software", "off"] = "software"  # SyncMode server (left) / client (right)
    sync_frames: int = 100       # SyncFrames: the server reports SyncReady after this many frames
    sensor_mode: int = -1        # index into Picamera2.sensor_modes (-1 = let libcamera choose)
    analogue_gain: float = 2.0   # locked analogue gain (identical on both cameras)
    colour_gains: tuple[float, float] = (1.9, 1.6)  # locked red/blue gains (AWB off; ignored on mono sensors)
    buffer_count: int = 6        # request buffers per camera
    timestamp_is: Literal["readout_start", "exposure_start"] = "readout_start"
    # what SensorTimestamp marks; mid-exposure = SensorTimestamp -/+ ExposureTime/2

    def __post_init__(self) -> None:
        check_range("source.picamera2.analogue_gain", self.analogue_gain, 1.0, 64.0)
        check_range("source.picamera2.buffer_count", self.buffer_count, 2, 32)
        check_range("source.picamera2.sync_frames", self.sync_frames, 1, 100000)
        check_range("source.picamera2.sensor_mode", self.sensor_mode, -1, 64)
        for i, g in enumerate(self.colour_gains):
            check_range(f"source.picamera2.colour_gains[{i}]", g, 0.0, 32.0)


@dataclass(frozen=True)
class DepthaiSettings:
    """OAK-D mono pair (CAM_B left, CAM_C right) through depthai v3."""

    iso: int = 400               # manual sensitivity (ISO) with the fixed exposure
    sync_threshold_ms: float = 5.0  # Sync node grouping threshold
    imu: bool = True             # also stream the OAK's own IMU
    imu_rate_hz: int = 200       # BMI270 rounds down to 25/50/100/200/250 Hz
    queue_size: int = 8          # host output queue length (non-blocking; oldest dropped)

    def __post_init__(self) -> None:
        check_range("source.depthai.iso", self.iso, 100, 1600)
        check_range("source.depthai.sync_threshold_ms", self.sync_threshold_ms, 0.1, 50.0)
        check_range("source.depthai.imu_rate_hz", self.imu_rate_hz, 25, 400)
        check_range("source.depthai.queue_size", self.queue_size, 1, 64)


@dataclass(frozen=True)
class ReplaySettings:
    """A recorded sequence: ``session:DIR`` (ours), ``euroc:DIR`` or ``kitti:DIR``."""

    path: str = ""               # dataset spec understood by stereopath.device.formats.open_source
    speed: Literal["recorded", "max"] = "max"  # sleep to the recorded timestamps, or as fast as read
    start: int = 0               # first frame index
    count: int = 0               # number of frames (0 = all)

    def __post_init__(self) -> None:
        check_range("source.replay.start", self.start, 0, None)
        check_range("source.replay.count", self.count, 0, None)


@dataclass(frozen=True)
class SimSettings:
    """The built-in simulator (stereopath.device.sim)."""

    frames: int = 200            # frames in the simulated scan
    seed: int = 0                # random seed of the scene and sensor noise
    rate_hz: float = 0.0         # pace frames at this rate (0 = as fast as rendered)

    def __post_init__(self) -> None:
        check_range("source.sim.frames", self.frames, 1, 1_000_000)
        check_range("source.sim.rate_hz", self.rate_hz, 0.0, 1000.0)


@dataclass(frozen=True)
class SourceSettings:
    """Stereo capture: the backend and the settings every camera backend shares."""

    backend: SourceBackend = "picamera2"
    size: tuple[int, int] = (640, 480)   # output width, height (px)
    fps: float = 30.0                    # fixed frame rate (frames/s)
    exposure_us: int = 8000              # fixed exposure time (µs), identical on both cameras
    pair_tolerance_us: int = 1000        # max |t_left - t_right| of a pair (µs); < half a frame
    timeout_s: float = 2.0               # no pair for this long -> CaptureError
    queue_size: int = 4                  # paired frames waiting for the consumer (oldest dropped)
    rig_file: str = ""                   # rig YAML or Kalibr camchain; "" = the backend's own (factory / dataset / sim)
    picamera2: Picamera2Settings = field(default_factory=Picamera2Settings)
    depthai: DepthaiSettings = field(default_factory=DepthaiSettings)
    replay: ReplaySettings = field(default_factory=ReplaySettings)
    sim: SimSettings = field(default_factory=SimSettings)

    def __post_init__(self) -> None:
        check_range("source.size[0]", self.size[0], 16, 8192)
        check_range("source.size[1]", self.size[1], 16, 8192)
        check_range("source.fps", self.fps, 0.5, 240.0)
        frame_us = 1e6 / self.fps
        check_range("source.exposure_us", self.exposure_us, 10, int(frame_us))
        check_range("source.pair_tolerance_us", self.pair_tolerance_us, 1, int(frame_us / 2) - 1)
        check_range("source.timeout_s", self.timeout_s, 0.05, 60.0)
        check_range("source.queue_size", self.queue_size, 1, 256)

    @property
    def frame_duration_us(self) -> int:
        return int(round(1e6 / self.fps))

    @property
    def recorded(self) -> bool:
        """Frames on a recorded clock (simulator, replay) rather than live cameras."""
        return self.backend in ("sim", "replay")


@dataclass(frozen=True)
class EmulatedImuSettings:
    """The register-level MPU-6050 emulator (``imu.backend = "emulated"``)."""

    period_error_ppm: float = 8000.0   # true sample period vs nominal (the MPU clock drifts ~1 %)
    gyro_bias_dps: tuple[float, float, float] = (0.8, -0.5, 0.3)  # simulated zero-rate offset
    seed: int = 0

    def __post_init__(self) -> None:
        check_range("imu.emulated.period_error_ppm", self.period_error_ppm, -50000.0, 50000.0)


# I2C cost of reading the FIFO: 9 bits a byte (8 + ACK); per poll the FIFO_COUNT read (address
# write, register, address read, 2 bytes), the FIFO burst's own 3 address/register bytes and
# the INT_STATUS read (4 bytes); the bus is kept below this share of its time
I2C_BITS_PER_BYTE = 9
I2C_POLL_OVERHEAD_BYTES = 12
I2C_USABLE_SHARE = 0.8


def i2c_load_bits_per_s(rate_hz: float, packet_bytes: int, read_period_ms: float) -> float:
    """Bus bits per second that reading ``rate_hz`` packets, polling every ``read_period_ms``, takes."""
    return I2C_BITS_PER_BYTE * (rate_hz * packet_bytes + 1000.0 / read_period_ms * I2C_POLL_OVERHEAD_BYTES)


def max_rate_on_bus(i2c_khz: float, packet_bytes: int, read_period_ms: float) -> float:
    """The highest sample rate an ``i2c_khz`` bus carries within :data:`I2C_USABLE_SHARE`."""
    spare = I2C_USABLE_SHARE * i2c_khz * 1000.0 / I2C_BITS_PER_BYTE - 1000.0 / read_period_ms * I2C_POLL_OVERHEAD_BYTES
    return max(0.0, spare / packet_bytes)


@dataclass(frozen=True)
class ImuSettings:
    """MPU-6050 on I2C (or its emulator): ranges, filter, rate and bus recovery."""

    backend: ImuBackend = "mpu6050"
    bus: int = 1                         # /dev/i2c-N
    address: int = 0x68                  # 0x68 (AD0 low) or 0x69 (AD0 high)
    rate_hz: float = 200.0               # FIFO sample rate (Hz) = output rate / (1 + SMPLRT_DIV)
    dlpf_cfg: int = 3                    # DLPF_CFG 0..6 (0 = off: 8 kHz gyro output rate; 3 = 44 Hz)
    gyro_range_dps: int = 500            # 250, 500, 1000 or 2000 deg/s
    accel_range_g: int = 4               # 2, 4, 8 or 16 g
    temperature: bool = False            # also put TEMP in the FIFO (14-byte packets)
    read_period_ms: float = 20.0         # FIFO poll period
    retries: int = 3                     # retries of a failed I2C transfer
    backoff_ms: float = 2.0              # first retry delay (doubles each retry)
    reinit_attempts: int = 2             # re-initialisations before giving up
    latency_us: float = 0.0              # fixed read latency subtracted from fitted timestamps
    fit_window_s: float = 20.0           # span of the running sample-period fit
    i2c_khz: float = 400.0               # the bus clock (config.txt dtparam=i2c_arm_baudrate), caps rate_hz
    emulated: EmulatedImuSettings = field(default_factory=EmulatedImuSettings)

    def __post_init__(self) -> None:
        check_range("imu.bus", self.bus, 0, 255)
        if self.address not in (0x68, 0x69):
            raise ConfigError(f"imu.address = {self.address:#x} must be 0x68 or 0x69")
        check_range("imu.dlpf_cfg", self.dlpf_cfg, 0, 6)
        if self.gyro_range_dps not in GYRO_RANGES_DPS:
            raise ConfigError(f"imu.gyro_range_dps = {self.gyro_range_dps} must be one of {list(GYRO_RANGES_DPS)}")
        if self.accel_range_g not in ACCEL_RANGES_G:
            raise ConfigError(f"imu.accel_range_g = {self.accel_range_g} must be one of {list(ACCEL_RANGES_G)}")
        base = self.output_rate_hz
        check_range("imu.rate_hz", self.rate_hz, base / 256.0, base)
        div = base / self.rate_hz - 1.0
        if abs(div - round(div)) > 1e-6:
            raise ConfigError(
                f"imu.rate_hz = {self.rate_hz} is not {base:g} Hz / (1 + n) for an integer n "
                f"(DLPF_CFG {self.dlpf_cfg} gives a {base:g} Hz output rate)")
        check_range("imu.read_period_ms", self.read_period_ms, 1.0, 1000.0)
        check_range("imu.retries", self.retries, 0, 20)
        check_range("imu.backoff_ms", self.backoff_ms, 0.0, 1000.0)
        check_range("imu.reinit_attempts", self.reinit_attempts, 0, 10)
        check_range("imu.latency_us", self.latency_us, 0.0, 10000.0)
        check_range("imu.fit_window_s", self.fit_window_s, 1.0, 600.0)
        check_range("imu.i2c_khz", self.i2c_khz, 10.0, 3400.0)
        # bytes per read must fit the 1024-byte FIFO with margin
        pkt = 14 if self.temperature else 12
        load = i2c_load_bits_per_s(self.rate_hz, pkt, self.read_period_ms)
        capacity = I2C_USABLE_SHARE * self.i2c_khz * 1000.0
        if load > capacity:
            most = max_rate_on_bus(self.i2c_khz, pkt, self.read_period_ms)
            raise ConfigError(
                f"imu.rate_hz = {self.rate_hz:g} needs {load / 1000:.0f} kbit/s of the {self.i2c_khz:g} kHz I2C bus "
                f"({pkt}-byte packets); it carries about {most:.0f} Hz ({I2C_USABLE_SHARE:.0%} of its time): lower "
                "imu.rate_hz, or raise the bus clock (dtparam=i2c_arm_baudrate) and imu.i2c_khz")
        fill_ms = 1024 // pkt / self.rate_hz * 1000.0
        if self.read_period_ms > 0.8 * fill_ms:
            raise ConfigError(
                f"imu.read_period_ms = {self.read_period_ms} lets the FIFO overflow: it fills in "
                f"{fill_ms:.0f} ms at {self.rate_hz:g} Hz; poll at most every {0.8 * fill_ms:.0f} ms")

    @property
    def polled(self) -> bool:
        """A chip (or its emulator) read on its own thread on this machine's clock."""
        return self.backend in ("mpu6050", "emulated")

    @property
    def output_rate_hz(self) -> float:
        """Gyro output rate before the divider: 8 kHz with the DLPF off, 1 kHz with it on."""
        return 8000.0 if self.dlpf_cfg == 0 else 1000.0

    @property
    def smplrt_div(self) -> int:
        return int(round(self.output_rate_hz / self.rate_hz - 1.0))


@dataclass(frozen=True)
class TimeAlignSettings:
    """Attaching IMU samples to frames."""

    time_offset_us: float = 0.0   # Kalibr's timeshift_cam_imu: t_imu = t_cam + offset (µs)
    max_wait_ms: float = 100.0    # a frame waits at most this long for IMU samples past its time
    gap_factor: float = 2.5       # an IMU step longer than this many periods is a gap

    def __post_init__(self) -> None:
        check_range("timealign.time_offset_us", self.time_offset_us, -1e6, 1e6)
        check_range("timealign.max_wait_ms", self.max_wait_ms, 0.0, 10000.0)
        check_range("timealign.gap_factor", self.gap_factor, 1.2, 100.0)


@dataclass(frozen=True)
class EstimatorSettings:
    """Motion estimator: which one, and the ``stereo`` estimator's settings by stage
    (``[estimator.stereo.keyframes]``, ``.klt``, ``.asift``, ``.geometry``, ``.gyro``, ``.disparity_offset``,
    ``.exposure``: :mod:`stereopath.device.core.stereo_config`)."""

    name: str = "stereo"          # the on-board estimator (the paper and sfm baselines run on the host only)
    stereo: StereoConfig = field(default_factory=StereoConfig)

    def __post_init__(self) -> None:
        if self.name != "stereo":
            raise ConfigError(f"[estimator] name = {self.name!r}: the device runs 'stereo' (the paper and sfm "
                              "baselines are host-side: stereopath odometry --estimator)")


@dataclass(frozen=True)
class StreamSettings:
    """The ``[stream]`` section: endpoints, security and bounds of the device's streamer.

    The one type of these settings, from device.toml to
    :class:`stereopath.device.streaming.DeviceStreamer` (which takes the ``[keys]`` section beside it).
    Every in-memory queue is bounded by one of these numbers, so the device's memory does not
    depend on what the host does.  Times are milliseconds unless the name says otherwise.
    """

    pose_endpoint: str = "tcp://*:5555"       # PUB, lossy live poses (bound by the device)
    keyframe_endpoint: str = "tcp://*:5556"   # ROUTER, loss-free keyframes, status, control
    enabled: bool = True                      # stream at all (``device run --no-stream`` overrides)
    insecure: bool = False                    # plain TCP without CURVE; only loopback endpoints allowed
    image_encoding: Literal["jpg", "png", "raw"] = "jpg"  # keyframe images on the wire
    jpeg_quality: int = 90                    # 1..100 (image_encoding = "jpg")
    png_compression: int = 1                  # 0..9 (image_encoding = "png")
    drain_s: float = 3.0                      # at the end of a run, wait up to this long (s) for a
    #                                           connected host to acknowledge every keyframe
    max_credit: int = 16                # keyframes in flight per host, whatever credit it asks for
    max_peers: int = 8                  # hosts tracked at once (least recently heard is evicted)
    pose_sndhwm: int = 16               # PUB high-water mark (per subscriber, then dropped)
    pose_flush_ms: int = 500            # at the end of a run, up to this long to send the last poses queued
    keyframe_sndhwm: int = 64           # ROUTER outbound messages per host
    control_rcvhwm: int = 64            # ROUTER inbound messages per host
    max_pending_keyframes: int = 16     # keyframes waiting to be encoded and spooled
    heartbeat_ivl_ms: int = 1000        # ZMTP heartbeats (PING every ivl, drop after timeout)
    heartbeat_timeout_ms: int = 5000
    heartbeat_ttl_ms: int = 10000
    spool_fsync: bool = True            # fsync each spooled keyframe before offering it

    def __post_init__(self) -> None:
        check_range("stream.jpeg_quality", self.jpeg_quality, 1, 100)
        check_range("stream.png_compression", self.png_compression, 0, 9)
        check_range("stream.drain_s", self.drain_s, 0.0, 600.0)
        check_range("stream.max_credit", self.max_credit, 1, 1024)
        check_range("stream.max_peers", self.max_peers, 1, 256)
        check_range("stream.pose_sndhwm", self.pose_sndhwm, 1, 100000)
        check_range("stream.pose_flush_ms", self.pose_flush_ms, 0, 10000)
        check_range("stream.keyframe_sndhwm", self.keyframe_sndhwm, self.max_credit + 2, 100000)
        check_range("stream.control_rcvhwm", self.control_rcvhwm, 1, 100000)
        check_range("stream.max_pending_keyframes", self.max_pending_keyframes, 1, 1024)
        check_range("stream.heartbeat_ivl_ms", self.heartbeat_ivl_ms, 0, 3_600_000)
        check_range("stream.heartbeat_timeout_ms", self.heartbeat_timeout_ms, 0, 3_600_000)
        check_range("stream.heartbeat_ttl_ms", self.heartbeat_ttl_ms, 0, 6_553_500)


@dataclass(frozen=True)
class KeySettings:
    """CURVE keys."""

    server_secret: str = "/etc/stereopath/server.key_secret"  # device key pair (secret file)
    clients_dir: str = "/etc/stereopath/clients"               # allowed client public keys (*.key)


@dataclass(frozen=True)
class RecorderSettings:
    """Session recorder."""

    enabled: bool = True
    dir: str = "/var/lib/stereopath/sessions"   # one sub-directory per session
    reserve_mb: float = 500.0                   # refuse to start / stop below this much free disk

    def __post_init__(self) -> None:
        check_range("recorder.reserve_mb", self.reserve_mb, 0.0, 1e7)


@dataclass(frozen=True)
class ServiceSettings:
    """The capture service (``stereopath device run``): health reporting and lifecycle."""

    status_file: str = "/run/stereopath/status.json"  # health JSON rewritten each status period ("" = none)
    status_interval_s: float = 1.0    # status file, STATUS= line and status message period (s)
    max_data_age_s: float = 2.0       # WATCHDOG=1 only if a frame and an IMU sample arrived this recently (s;
    #                                   capped at half the systemd watchdog period)
    ready_timeout_s: float = 30.0     # no paired frame / IMU sample this long after start -> exit 1 (s)
    stop_timeout_s: float = 10.0      # wait this long for the pipeline to finish its frame at stop (s)

    def __post_init__(self) -> None:
        check_range("service.status_interval_s", self.status_interval_s, 0.05, 60.0)
        check_range("service.max_data_age_s", self.max_data_age_s, 0.05, 600.0)
        check_range("service.ready_timeout_s", self.ready_timeout_s, 0.5, 3600.0)
        check_range("service.stop_timeout_s", self.stop_timeout_s, 0.5, 600.0)


@dataclass(frozen=True)
class SelftestSettings:
    """Limits of ``stereopath device selftest``."""

    frames: int = 30                  # stereo pairs to capture
    max_unpaired_ratio: float = 0.05  # dropped unpaired frames / frames received
    rate_tolerance: float = 0.10      # relative camera frame-rate error allowed
    imu_rate_tolerance: float = 0.03  # relative IMU rate error allowed (the MPU clock drifts ~1 %)
    still_s: float = 2.0              # still period for the gyro bias and gravity checks
    max_gyro_bias_dps: float = 5.0    # |mean gyro| allowed while still
    max_gyro_std_dps: float = 1.0     # larger spread = the unit moved during the test
    gravity_tolerance_m_s2: float = 0.5  # | |mean accel| - 9.80665 | allowed

    def __post_init__(self) -> None:
        check_range("selftest.frames", self.frames, 2, 100000)
        check_range("selftest.max_unpaired_ratio", self.max_unpaired_ratio, 0.0, 1.0)
        check_range("selftest.rate_tolerance", self.rate_tolerance, 0.0, 1.0)
        check_range("selftest.imu_rate_tolerance", self.imu_rate_tolerance, 0.0, 1.0)
        check_range("selftest.still_s", self.still_s, 0.1, 600.0)


@dataclass(frozen=True)
class DeviceConfig:
    """The whole device configuration (``firmware_cfg/device.toml``)."""

    source: SourceSettings = field(default_factory=SourceSettings)
    imu: ImuSettings = field(default_factory=ImuSettings)
    timealign: TimeAlignSettings = field(default_factory=TimeAlignSettings)
    estimator: EstimatorSettings = field(default_factory=EstimatorSettings)
    stream: StreamSettings = field(default_factory=StreamSettings)
    keys: KeySettings = field(default_factory=KeySettings)
    recorder: RecorderSettings = field(default_factory=RecorderSettings)
    service: ServiceSettings = field(default_factory=ServiceSettings)
    selftest: SelftestSettings = field(default_factory=SelftestSettings)


def _upgrade(raw: dict[str, Any]) -> dict[str, Any]:
    """Read files written before ``[estimator] preset`` was renamed ``name`` (it names an estimator)."""
    est = raw.get("estimator")
    if isinstance(est, Mapping) and "preset" in est:
        if "name" in est:
            raise ConfigError("[estimator]: both 'name' and its old spelling 'preset' are set; keep 'name'")
        est = {("name" if k == "preset" else k): v for k, v in est.items()}
        raw = {**raw, "estimator": est}
    return raw


def device_config_from_mapping(data: Mapping[str, Any]) -> DeviceConfig:
    return from_mapping(DeviceConfig, _upgrade(dict(data)))


INSTALLED_CONFIG = "/etc/stereopath/device.toml"  # what `device install` writes and the service runs with


def config_or_installed(path: str | Path | None) -> str | Path | None:
    """``path`` when given, else the installed configuration when there is one (the commands that look at
    the box as it runs: selftest, status), else ``None`` (built-in defaults)."""
    if path is not None:
        return path
    return INSTALLED_CONFIG if Path(INSTALLED_CONFIG).is_file() else None


def load_device_config(path: str | Path | None = None) -> DeviceConfig:
    """Defaults, overridden by the TOML file at ``path`` when given."""
    if path is None:
        return DeviceConfig()
    cfg = device_config_from_mapping(load_toml(path))
    log.debug("device configuration from %s", path)
    return cfg
