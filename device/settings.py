"""Device configuration: one frozen dataclass per stage, loaded from TOML.

Precedence: dataclass defaults < configuration file < command line.  A
documented example with every key, its unit and its default lives in
``firmware_cfg/device.toml``; a test keeps the two in step.

Sections (TOML tables):

``[source]``      which stereo backend and the capture settings shared by all of them,
                  with one sub-table per backend (``[source.picamera2]``, ``[source.depthai]``,
                  ``[source.replay]``, ``[source.sim]``);
``[imu]``         the inertial sensor (MPU-6050 on I2C, its emulator, the source's own, or none), with
                  ``[imu.i2c]`` (bus clock, retries), ``[imu.timestamps]`` and ``[imu.emulated]``;
``[timealign]``   camera-IMU time offset and how long a frame may wait for IMU samples;
``[estimator]``   which motion estimator runs (``name``; the old key ``preset`` is still read) and its
                  settings by stage (``[estimator.stereo.*]``);
``[stream]``      ZeroMQ endpoints and security, with ``[stream.images]`` (keyframe encoding),
                  ``[stream.bounds]`` (queue and credit limits) and ``[stream.heartbeat]``;
``[keys]``        CURVE key locations;
``[recorder]``    session directory and free-disk reserve;
``[service]``     the capture service: status file, watchdog data age, start/stop timeouts;
``[selftest]``    pass/fail limits of ``stereopath device selftest``.

Keys that moved into a sub-table (:data:`MOVED_KEYS`) are still read at their old place, with a
logged deprecation warning.  Other stages add their own section dataclass here and a field in
:class:`DeviceConfig`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Mapping

from stereopath.device.core.config import check_range, check_ranges, from_mapping, load_toml, ranged
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
    sync_frames: int = ranged(100, 1, 100000)  # SyncFrames: the server reports SyncReady after this many frames
    sensor_mode: int = ranged(-1, -1, 64)      # index into Picamera2.sensor_modes (-1 = let libcamera choose)
    analogue_gain: float = ranged(2.0, 1.0, 64.0)  # locked analogue gain (identical on both cameras)
    colour_gains: tuple[float, float] = ranged((1.9, 1.6), 0.0, 32.0)  # locked red/blue gains (AWB off; ignored on mono sensors)
    buffer_count: int = ranged(6, 2, 32)       # request buffers per camera
    timestamp_is: Literal["readout_start", "exposure_start"] = "readout_start"
    # what SensorTimestamp marks; mid-exposure = SensorTimestamp -/+ ExposureTime/2

    def __post_init__(self) -> None:
        check_ranges(self, "source.picamera2.")


@dataclass(frozen=True)
class DepthaiSettings:
    """OAK-D mono pair (CAM_B left, CAM_C right) through depthai v3."""

    iso: int = ranged(400, 100, 1600)          # manual sensitivity (ISO) with the fixed exposure
    sync_threshold_ms: float = ranged(5.0, 0.1, 50.0)  # Sync node grouping threshold
    imu: bool = True             # also stream the OAK's own IMU
    imu_rate_hz: int = ranged(200, 25, 400)    # BMI270 rounds down to 25/50/100/200/250 Hz
    queue_size: int = ranged(8, 1, 64)         # host output queue length (non-blocking; oldest dropped)

    def __post_init__(self) -> None:
        check_ranges(self, "source.depthai.")


@dataclass(frozen=True)
class ReplaySettings:
    """A recorded sequence: ``session:DIR`` (ours), ``euroc:DIR`` or ``kitti:DIR``."""

    path: str = ""               # dataset spec understood by stereopath.device.formats.open_source
    speed: Literal["recorded", "max"] = "max"  # sleep to the recorded timestamps, or as fast as read
    start: int = ranged(0, 0)    # first frame index
    count: int = ranged(0, 0)    # number of frames (0 = all)

    def __post_init__(self) -> None:
        check_ranges(self, "source.replay.")


@dataclass(frozen=True)
class SimSettings:
    """The built-in simulator (stereopath.device.sim)."""

    frames: int = ranged(200, 1, 1_000_000)    # frames in the simulated scan
    seed: int = 0                # random seed of the scene and sensor noise
    rate_hz: float = ranged(0.0, 0.0, 1000.0)  # pace frames at this rate (0 = as fast as rendered)

    def __post_init__(self) -> None:
        check_ranges(self, "source.sim.")


@dataclass(frozen=True)
class SourceSettings:
    """Stereo capture: the backend and the settings every camera backend shares."""

    backend: SourceBackend = "picamera2"
    size: tuple[int, int] = ranged((640, 480), 16, 8192)  # output width, height (px)
    fps: float = ranged(30.0, 0.5, 240.0)  # fixed frame rate (frames/s)
    exposure_us: int = 8000              # fixed exposure time (µs), identical on both cameras
    pair_tolerance_us: int = 1000        # max |t_left - t_right| of a pair (µs); < half a frame
    timeout_s: float = ranged(2.0, 0.05, 60.0)  # no pair for this long -> CaptureError
    queue_size: int = ranged(4, 1, 256)  # paired frames waiting for the consumer (oldest dropped)
    rig_file: str = ""                   # rig YAML or Kalibr camchain; "" = the backend's own (factory / dataset / sim)
    picamera2: Picamera2Settings = field(default_factory=Picamera2Settings)
    depthai: DepthaiSettings = field(default_factory=DepthaiSettings)
    replay: ReplaySettings = field(default_factory=ReplaySettings)
    sim: SimSettings = field(default_factory=SimSettings)

    def __post_init__(self) -> None:
        check_ranges(self, "source.")
        frame_us = 1e6 / self.fps
        check_range("source.exposure_us", self.exposure_us, 10, int(frame_us))
        check_range("source.pair_tolerance_us", self.pair_tolerance_us, 1, int(frame_us / 2) - 1)

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

    period_error_ppm: float = ranged(8000.0, -50000.0, 50000.0)  # true sample period vs nominal (the MPU clock drifts ~1 %)
    gyro_bias_dps: tuple[float, float, float] = (0.8, -0.5, 0.3)  # simulated zero-rate offset
    seed: int = 0

    def __post_init__(self) -> None:
        check_ranges(self, "imu.emulated.")


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
class I2cSettings:
    """``[imu.i2c]``: the bus clock and how failed transfers are retried."""

    clock_khz: float = ranged(400.0, 10.0, 3400.0)  # the bus clock (config.txt dtparam=i2c_arm_baudrate), caps rate_hz
    retries: int = ranged(3, 0, 20)                 # retries of a failed I2C transfer
    backoff_ms: float = ranged(2.0, 0.0, 1000.0)    # first retry delay (doubles each retry)
    reinit_attempts: int = ranged(2, 0, 10)         # re-initialisations before giving up

    def __post_init__(self) -> None:
        check_ranges(self, "imu.i2c.")


@dataclass(frozen=True)
class ImuTimestampSettings:
    """``[imu.timestamps]``: how sample times are fitted to the FIFO reads."""

    latency_us: float = ranged(0.0, 0.0, 10000.0)   # fixed read latency subtracted from fitted timestamps
    fit_window_s: float = ranged(20.0, 1.0, 600.0)  # span of the running sample-period fit

    def __post_init__(self) -> None:
        check_ranges(self, "imu.timestamps.")


@dataclass(frozen=True)
class ImuSettings:
    """MPU-6050 on I2C (or its emulator): ranges, filter, rate and bus recovery."""

    backend: ImuBackend = "mpu6050"
    bus: int = ranged(1, 0, 255)         # /dev/i2c-N
    address: int = 0x68                  # 0x68 (AD0 low) or 0x69 (AD0 high)
    rate_hz: float = 200.0               # FIFO sample rate (Hz) = output rate / (1 + SMPLRT_DIV)
    dlpf_cfg: int = ranged(3, 0, 6)      # DLPF_CFG 0..6 (0 = off: 8 kHz gyro output rate; 3 = 44 Hz)
    gyro_range_dps: int = 500            # 250, 500, 1000 or 2000 deg/s
    accel_range_g: int = 4               # 2, 4, 8 or 16 g
    temperature: bool = False            # also put TEMP in the FIFO (14-byte packets)
    read_period_ms: float = ranged(20.0, 1.0, 1000.0)  # FIFO poll period
    i2c: I2cSettings = field(default_factory=I2cSettings)
    timestamps: ImuTimestampSettings = field(default_factory=ImuTimestampSettings)
    emulated: EmulatedImuSettings = field(default_factory=EmulatedImuSettings)

    def __post_init__(self) -> None:
        check_ranges(self, "imu.")
        if self.address not in (0x68, 0x69):
            raise ConfigError(f"imu.address = {self.address:#x} must be 0x68 or 0x69")
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
        # bytes per read must fit the 1024-byte FIFO with margin
        pkt = 14 if self.temperature else 12
        khz = self.i2c.clock_khz
        load = i2c_load_bits_per_s(self.rate_hz, pkt, self.read_period_ms)
        capacity = I2C_USABLE_SHARE * khz * 1000.0
        if load > capacity:
            most = max_rate_on_bus(khz, pkt, self.read_period_ms)
            raise ConfigError(
                f"imu.rate_hz = {self.rate_hz:g} needs {load / 1000:.0f} kbit/s of the {khz:g} kHz I2C bus "
                f"({pkt}-byte packets); it carries about {most:.0f} Hz ({I2C_USABLE_SHARE:.0%} of its time): lower "
                "imu.rate_hz, or raise the bus clock (dtparam=i2c_arm_baudrate) and imu.i2c.clock_khz")
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

    time_offset_us: float = ranged(0.0, -1e6, 1e6)    # Kalibr's timeshift_cam_imu: t_imu = t_cam + offset (µs)
    max_wait_ms: float = ranged(100.0, 0.0, 10000.0)  # a frame waits at most this long for IMU samples past its time
    gap_factor: float = ranged(2.5, 1.2, 100.0)       # an IMU step longer than this many periods is a gap

    def __post_init__(self) -> None:
        check_ranges(self, "timealign.")


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
class StreamImageSettings:
    """``[stream.images]``: how keyframe images are encoded on the wire."""

    encoding: Literal["jpg", "png", "raw"] = "jpg"
    jpeg_quality: int = ranged(90, 1, 100)     # 1..100 (encoding = "jpg")
    png_compression: int = ranged(1, 0, 9)     # 0..9 (encoding = "png")

    def __post_init__(self) -> None:
        check_ranges(self, "stream.images.")


@dataclass(frozen=True)
class StreamBounds:
    """``[stream.bounds]``: every in-memory queue of the streamer is bounded by one of these, so the
    device's memory does not depend on what the hosts do."""

    max_credit: int = ranged(16, 1, 1024)          # keyframes in flight per host, whatever credit it asks for
    max_peers: int = ranged(8, 1, 256)             # hosts tracked at once (least recently heard is evicted)
    pose_sndhwm: int = ranged(16, 1, 100000)       # PUB high-water mark (per subscriber, then dropped)
    pose_flush_ms: int = ranged(500, 0, 10000)     # at the end of a run, up to this long to send the last poses queued
    keyframe_sndhwm: int = 64                      # ROUTER outbound messages per host (> max_credit + 1)
    control_rcvhwm: int = ranged(64, 1, 100000)    # ROUTER inbound messages per host
    max_pending_keyframes: int = ranged(16, 1, 1024)  # keyframes waiting to be encoded and spooled

    def __post_init__(self) -> None:
        check_ranges(self, "stream.bounds.")
        check_range("stream.bounds.keyframe_sndhwm", self.keyframe_sndhwm, self.max_credit + 2, 100000)


@dataclass(frozen=True)
class HeartbeatSettings:
    """``[stream.heartbeat]``: ZMTP heartbeats (PING every ``ivl_ms``, drop the peer after ``timeout_ms``)."""

    ivl_ms: int = ranged(1000, 0, 3_600_000)
    timeout_ms: int = ranged(5000, 0, 3_600_000)
    ttl_ms: int = ranged(10000, 0, 6_553_500)

    def __post_init__(self) -> None:
        check_ranges(self, "stream.heartbeat.")


@dataclass(frozen=True)
class StreamSettings:
    """The ``[stream]`` section: endpoints, security and bounds of the device's streamer.

    The one type of these settings, from device.toml to
    :class:`stereopath.device.streaming.DeviceStreamer` (which takes the ``[keys]`` section beside it).
    Times are milliseconds unless the name says otherwise.
    """

    pose_endpoint: str = "tcp://*:5555"       # PUB, lossy live poses (bound by the device)
    keyframe_endpoint: str = "tcp://*:5556"   # ROUTER, loss-free keyframes, status, control
    enabled: bool = True                      # stream at all (``device run --no-stream`` overrides)
    insecure: bool = False                    # plain TCP without CURVE; only loopback endpoints allowed
    drain_s: float = ranged(3.0, 0.0, 600.0)  # at the end of a run, wait up to this long (s) for a
    #                                           connected host to acknowledge every keyframe
    spool_fsync: bool = True                  # fsync each spooled keyframe before offering it
    images: StreamImageSettings = field(default_factory=StreamImageSettings)
    bounds: StreamBounds = field(default_factory=StreamBounds)
    heartbeat: HeartbeatSettings = field(default_factory=HeartbeatSettings)

    def __post_init__(self) -> None:
        check_ranges(self, "stream.")


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
    reserve_mb: float = ranged(500.0, 0.0, 1e7)  # refuse to start / stop below this much free disk

    def __post_init__(self) -> None:
        check_ranges(self, "recorder.")


@dataclass(frozen=True)
class ServiceSettings:
    """The capture service (``stereopath device run``): health reporting and lifecycle."""

    status_file: str = "/run/stereopath/status.json"  # health JSON rewritten each status period ("" = none)
    status_interval_s: float = ranged(1.0, 0.05, 60.0)  # status file, STATUS= line and status message period (s)
    max_data_age_s: float = ranged(2.0, 0.05, 600.0)    # WATCHDOG=1 only if a frame and an IMU sample arrived
    #                                                     this recently (s; capped at half the systemd watchdog period)
    ready_timeout_s: float = ranged(30.0, 0.5, 3600.0)  # no paired frame / IMU sample this long after start -> exit 1 (s)
    stop_timeout_s: float = ranged(10.0, 0.5, 600.0)    # wait this long for the pipeline to finish its frame at stop (s)

    def __post_init__(self) -> None:
        check_ranges(self, "service.")


@dataclass(frozen=True)
class SelftestSettings:
    """Limits of ``stereopath device selftest``."""

    frames: int = ranged(30, 2, 100000)                # stereo pairs to capture
    max_unpaired_ratio: float = ranged(0.05, 0.0, 1.0)  # dropped unpaired frames / frames received
    rate_tolerance: float = ranged(0.10, 0.0, 1.0)      # relative camera frame-rate error allowed
    imu_rate_tolerance: float = ranged(0.03, 0.0, 1.0)  # relative IMU rate error allowed (the MPU clock drifts ~1 %)
    still_s: float = ranged(2.0, 0.1, 600.0)            # still period for the gyro bias and gravity checks
    max_gyro_bias_dps: float = 5.0    # |mean gyro| allowed while still
    max_gyro_std_dps: float = 1.0     # larger spread = the unit moved during the test
    gravity_tolerance_m_s2: float = 0.5  # | |mean accel| - 9.80665 | allowed

    def __post_init__(self) -> None:
        check_ranges(self, "selftest.")


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


def _upgrade(raw: dict[str, object]) -> dict[str, object]:
    """Read files written before ``[estimator] preset`` was renamed ``name`` (it names an estimator)."""
    est = raw.get("estimator")
    if isinstance(est, Mapping) and "preset" in est:
        if "name" in est:
            raise ConfigError("[estimator]: both 'name' and its old spelling 'preset' are set; keep 'name'")
        est = {("name" if k == "preset" else k): v for k, v in est.items()}
        raw = {**raw, "estimator": est}
    return raw


# Keys that moved from a section into one of its sub-tables: old key -> (sub-table, new key).
MOVED_KEYS: dict[str, dict[str, tuple[str, str]]] = {
    "stream": {
        "image_encoding": ("images", "encoding"),
        "jpeg_quality": ("images", "jpeg_quality"),
        "png_compression": ("images", "png_compression"),
        **{k: ("bounds", k) for k in ("max_credit", "max_peers", "pose_sndhwm", "pose_flush_ms", "keyframe_sndhwm",
                                      "control_rcvhwm", "max_pending_keyframes")},
        "heartbeat_ivl_ms": ("heartbeat", "ivl_ms"),
        "heartbeat_timeout_ms": ("heartbeat", "timeout_ms"),
        "heartbeat_ttl_ms": ("heartbeat", "ttl_ms"),
    },
    "imu": {
        "i2c_khz": ("i2c", "clock_khz"),
        "retries": ("i2c", "retries"),
        "backoff_ms": ("i2c", "backoff_ms"),
        "reinit_attempts": ("i2c", "reinit_attempts"),
        "latency_us": ("timestamps", "latency_us"),
        "fit_window_s": ("timestamps", "fit_window_s"),
    },
}


def nest_moved_keys(section: str, table: Mapping[str, object]) -> tuple[dict[str, object], list[str]]:
    """``table`` (the ``[section]`` of a file) with the keys of :data:`MOVED_KEYS` moved into their
    sub-tables, and the old spellings found (ConfigError when a key is set both ways)."""
    moved = MOVED_KEYS.get(section, {})
    out: dict[str, object] = {}
    found: list[str] = []
    for key, value in table.items():
        if key not in moved:
            out[key] = value
    for key, value in table.items():
        if key not in moved:
            continue
        sub, new = moved[key]
        current = out.get(sub, {})
        if not isinstance(current, Mapping):
            raise ConfigError(f"{section}.{sub} must be a table, got {type(current).__name__}")
        if new in current:
            raise ConfigError(f"[{section}]: both {section}.{sub}.{new} and its old spelling {section}.{key} are set; "
                              f"keep {section}.{sub}.{new}")
        out[sub] = {**current, new: value}
        found.append(f"{section}.{key} -> {section}.{sub}.{new}")
    return out, found


def _upgrade_moved_keys(raw: dict[str, object]) -> dict[str, object]:
    """Read files written before the keys of :data:`MOVED_KEYS` moved into sub-tables (with a warning)."""
    for section in MOVED_KEYS:
        table = raw.get(section)
        if isinstance(table, Mapping):
            raw[section], found = nest_moved_keys(section, table)
            if found:
                log.warning("device configuration: deprecated key(s) read at their new place: %s", ", ".join(found))
    return raw


def device_config_from_mapping(data: Mapping[str, object]) -> DeviceConfig:
    return from_mapping(DeviceConfig, _upgrade_moved_keys(_upgrade(dict(data))))


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
