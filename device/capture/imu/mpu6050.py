"""InvenSense MPU-6050 over I2C (smbus2): FIFO burst reads, overflow recovery, fitted timestamps.

Initialisation (:meth:`Mpu6050.open`): probe ``WHO_AM_I`` (0x68; the MPU-6500 and
MPU-9250's 0x70 / 0x71 are handled as those chips, see :data:`CHIPS`; anything else is a
:class:`CaptureError` naming the value read), device reset, wake with the X-gyro PLL as
clock, DLPF (on the MPU-6500/9250 also the accelerometer's own ``ACCEL_CONFIG2``),
sample-rate divider, gyro/accel full-scale ranges (all from
:class:`~stereopath.device.settings.ImuSettings`), FIFO overflow interrupt, FIFO reset and enable
with accel + gyro (12-byte packets; 14 with temperature).  The written configuration is
read back and compared.

Each :meth:`Mpu6050.read` is one poll:

1. ``FIFO_COUNT`` is read as one 2-byte burst starting at the high byte (reading
   FIFO_COUNT_H latches both bytes); the host time right after it is the observation
   for the timestamp fit;
2. a count of the FIFO's size (1024 bytes; 512 on the MPU-6500/9250) or more means it
   overflowed: its oldest bytes are gone and, the size not being a multiple of 12, so is
   the packet framing.  The FIFO is reset and a
   gap recorded;
3. otherwise the whole packets present are read with ``i2c_rdwr`` (write register
   0x74, repeated start, read) in chunks of at most 8192 bytes (the Linux i2c-dev limit
   per message), each chunk a whole number of packets;
4. ``INT_STATUS`` is read last (which clears it): a FIFO_OFLOW flag means the FIFO
   overflowed while we were reading, so the batch is discarded, the FIFO reset and a gap
   recorded.  An overflow after this read shows up in the next poll.

Timestamps come from :class:`~stereopath.device.capture.imu.period_fit.PeriodFit`, a running lower-envelope
fit of host time against the cumulative sample index, not from the nominal rate (the
MPU clock is off by up to about 1 %).

I2C errors (``OSError``) are retried ``imu.i2c.retries`` times with exponential backoff; a FIFO
data transfer is never retried (bytes may already have left the FIFO): the FIFO is reset
instead.  If a register transfer still fails, the chip is re-initialised (up to
``imu.i2c.reinit_attempts`` times, each recorded as a gap) and after that a
:class:`CaptureError` names the bus, address, operation and last error.

The bus (anything with ``read_byte_data``, ``write_byte_data`` and ``i2c_rdwr``, i.e.
``smbus2.SMBus`` or the emulator), the clock and the sleep function are injectable.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Protocol, TypeVar

import numpy as np

from stereopath.device.errors import CaptureError, ConfigError
from stereopath.device.core.frames import ImuSamples
from stereopath.device.capture.imu.period_fit import PeriodFit
from stereopath.device.settings import ImuSettings

if TYPE_CHECKING:
    from smbus2 import i2c_msg

log = logging.getLogger(__name__)

# registers (RM-MPU-6000A-00 r4.2)
SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
ACCEL_CONFIG2 = 0x1D     # MPU-6500/9250 only: A_DLPF_CFG (bits 2:0), ACCEL_FCHOICE_B (bit 3)
FIFO_EN = 0x23
INT_PIN_CFG = 0x37
INT_ENABLE = 0x38
INT_STATUS = 0x3A
ACCEL_XOUT_H = 0x3B
TEMP_OUT_H = 0x41
GYRO_XOUT_H = 0x43
USER_CTRL = 0x6A
PWR_MGMT_1 = 0x6B
FIFO_COUNT_H = 0x72
FIFO_R_W = 0x74
WHO_AM_I = 0x75

# bits
PWR_RESET = 0x80
PWR_SLEEP = 0x40
CLKSEL_PLL_XGYRO = 0x01
USER_FIFO_EN = 0x40
USER_FIFO_RESET = 0x04
INT_FIFO_OFLOW = 0x10
INT_DATA_RDY = 0x01
FIFO_EN_TEMP = 0x80
FIFO_EN_GYRO = 0x70      # XG | YG | ZG
FIFO_EN_ACCEL = 0x08

FIFO_SIZE = 1024
I2C_MSG_MAX = 8192       # Linux i2c-dev limit per message
WHO_AM_I_MPU6050 = 0x68
WHO_AM_I_CLONES = {0x70: "MPU-6500", 0x71: "MPU-9250"}

GYRO_LSB_PER_DPS = {250: 131.0, 500: 65.5, 1000: 32.8, 2000: 16.4}
ACCEL_LSB_PER_G = {2: 16384.0, 4: 8192.0, 8: 4096.0, 16: 2048.0}
FS_SEL = {250: 0, 500: 1, 1000: 2, 2000: 3}
AFS_SEL = {2: 0, 4: 1, 8: 2, 16: 3}
STANDARD_GRAVITY = 9.80665
TEMP_SCALE = 340.0
TEMP_OFFSET_C = 36.53


_R = TypeVar("_R")


class I2cBus(Protocol):
    """What the driver uses of ``smbus2.SMBus`` (the emulator offers the same)."""

    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int: ...

    def write_byte_data(self, i2c_addr: int, register: int, value: int, force: bool | None = None) -> None: ...

    def i2c_rdwr(self, *msgs: i2c_msg) -> None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class ChipModel:
    """What differs between the parts that answer WHO_AM_I (the driver's registers are common).

    From the Linux driver ``drivers/iio/imu/inv_mpu6050``: ``hw_info[].fifo_size`` (1024 /
    512 bytes), ``.temp`` (MPU-6050 offset 12420 and scale 2941176 nano-degC, i.e.
    raw / 340 + 36.53; MPU-6500 7011 and 2995178, i.e. raw / 333.87 + 21), and
    ``inv_mpu6050_set_lpf_regs`` (MPU-6500 and later also write the DLPF value to
    ``ACCEL_CONFIG_2`` = 0x1D).  The MPU-6500/9250 register map: ``SMPLRT_DIV`` is only
    effective with the DLPF on (0 < DLPF_CFG < 7).
    """

    name: str
    fifo_bytes: int
    temp_lsb_per_c: float
    temp_offset_c: float
    accel_config2: bool       # the accelerometer low-pass filter has its own register
    divider_needs_dlpf: bool  # SMPLRT_DIV ignored with DLPF_CFG 0 (8 kHz FIFO)

    def temp_c(self, raw: np.ndarray) -> np.ndarray:
        return np.asarray(raw, float) / self.temp_lsb_per_c + self.temp_offset_c

    def temp_raw(self, temp_c: np.ndarray) -> np.ndarray:
        return (np.asarray(temp_c, float) - self.temp_offset_c) * self.temp_lsb_per_c


MPU6050_CHIP = ChipModel("MPU-6050", FIFO_SIZE, TEMP_SCALE, TEMP_OFFSET_C, False, False)
CHIPS = {
    WHO_AM_I_MPU6050: MPU6050_CHIP,
    0x70: ChipModel("MPU-6500", 512, 333.87, 21.0, True, True),
    0x71: ChipModel("MPU-9250", 512, 333.87, 21.0, True, True),
}


def fifo_fill_ms(fifo_bytes: int, packet_bytes: int, rate_hz: float) -> float:
    """How long the FIFO takes to fill with whole packets at ``rate_hz``."""
    return fifo_bytes // packet_bytes / rate_hz * 1000.0


def temp_raw_to_c(raw: np.ndarray) -> np.ndarray:
    return MPU6050_CHIP.temp_c(raw)


@dataclass
class Mpu6050Stats:
    who_am_i: int | None = None
    polls: int = 0
    samples: int = 0
    overflows: int = 0           # FIFO overflows (count >= 1024 or INT_STATUS flag)
    fifo_resets: int = 0
    discarded_samples: int = 0   # read but dropped because an overflow hit during the read
    retries: int = 0             # I2C transfers retried
    reinits: int = 0             # re-initialisations after persistent bus errors
    max_fifo_bytes: int = 0


class _BusFailure(Exception):
    def __init__(self, what: str, exc: OSError) -> None:
        super().__init__(f"{what}: {exc}")
        self.what = what
        self.exc = exc


class Mpu6050:
    """The driver (see module doc).  ``read()`` returns new samples as :class:`ImuSamples`."""

    name = "mpu6050"

    def __init__(self, settings: ImuSettings, bus: I2cBus | None = None, clock_ns: Callable[[], int] = time.monotonic_ns,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.settings = settings
        self._bus = bus
        self._own_bus = bus is None
        self._clock_ns = clock_ns
        self._sleep = sleep
        self.sleep = sleep  # the injected sleep, for callers pacing their polls on the same clock
        self.addr = int(settings.address)
        self.packet_bytes = 14 if settings.temperature else 12
        self.nominal_period_ns = 1e9 / settings.rate_hz
        self.gyro_scale = np.deg2rad(1.0 / GYRO_LSB_PER_DPS[settings.gyro_range_dps])
        self.accel_scale = STANDARD_GRAVITY / ACCEL_LSB_PER_G[settings.accel_range_g]
        self.stats = Mpu6050Stats()
        self.gaps: list[tuple[int, int]] = []
        self.who_am_i: int | None = None
        self.chip = MPU6050_CHIP
        self._fit = PeriodFit(self.nominal_period_ns, window_ns=int(settings.timestamps.fit_window_s * 1e9),
                              min_span=max(20, int(settings.rate_hz * 0.5)))
        self._seg_count = 0
        self._last_t: int | None = None
        self._gap_open: int | None = None
        self._i2c_msg: type[i2c_msg] | None = None
        self._opened = False

    # ---------------------------------------------------------------------------------
    @property
    def where(self) -> str:
        return f"MPU-6050 at i2c-{self.settings.bus} address {self.addr:#04x}"

    def open(self) -> None:
        if self._opened:
            return
        from smbus2 import i2c_msg

        self._i2c_msg = i2c_msg
        if self._bus is None:
            from smbus2 import SMBus

            try:
                self._bus = SMBus(self.settings.bus)
            except (FileNotFoundError, PermissionError, OSError) as exc:
                raise CaptureError(f"cannot open /dev/i2c-{self.settings.bus}: {exc} "
                                   "(dtparam=i2c_arm=on in config.txt? user in group i2c?)") from None
        try:
            self._init_device()
        except _BusFailure as exc:
            self._close_bus()
            raise CaptureError(f"{self.where}: {exc.what} failed after {self.settings.i2c.retries} retries: "
                               f"{exc.exc} (wiring, address, pull-ups?)") from None
        except (CaptureError, ConfigError):
            self._close_bus()
            raise
        self._opened = True

    def close(self) -> None:
        if not self._opened:
            return
        self._opened = False
        try:
            self._bus.write_byte_data(self.addr, USER_CTRL, 0x00)
            self._bus.write_byte_data(self.addr, PWR_MGMT_1, PWR_SLEEP)
        except OSError as exc:
            log.warning("%s: could not put the chip to sleep: %s", self.where, exc)
        self._close_bus()

    def _close_bus(self) -> None:
        if self._own_bus and self._bus is not None:
            try:
                self._bus.close()
            finally:
                self._bus = None

    def __enter__(self) -> "Mpu6050":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # bus primitives with retries ------------------------------------------------------
    def _retry(self, what: str, fn: Callable[..., _R], *args: int) -> _R:
        delay = self.settings.i2c.backoff_ms / 1000.0
        for attempt in range(self.settings.i2c.retries + 1):
            try:
                return fn(*args)
            except OSError as exc:
                if attempt == self.settings.i2c.retries:
                    raise _BusFailure(what, exc) from None
                self.stats.retries += 1
                log.debug("%s: %s failed (%s); retry %d in %.1f ms", self.where, what, exc, attempt + 1, delay * 1e3)
                self._sleep(delay)
                delay *= 2

    def _read_byte(self, reg: int, what: str) -> int:
        return int(self._retry(what, self._bus.read_byte_data, self.addr, reg))

    def _write_byte(self, reg: int, value: int, what: str) -> None:
        self._retry(what, self._bus.write_byte_data, self.addr, reg, value & 0xFF)

    def _rdwr(self, reg: int, n: int) -> bytes:
        """Write the register address, repeated start, read ``n`` bytes (one transfer, no retry)."""
        w = self._i2c_msg.write(self.addr, [reg])
        r = self._i2c_msg.read(self.addr, n)
        self._bus.i2c_rdwr(w, r)
        return bytes(r)

    # initialisation ---------------------------------------------------------------------
    def _init_device(self) -> None:
        s = self.settings
        who = self._read_byte(WHO_AM_I, "WHO_AM_I read")
        self.who_am_i = self.stats.who_am_i = who
        chip = CHIPS.get(who)
        if chip is None:
            raise CaptureError(f"{self.where}: WHO_AM_I = {who:#04x}, expected 0x68 (MPU-6050) "
                               "or 0x70/0x71 (MPU-6500/9250): wrong chip or address")
        self._use_chip(chip)
        self._write_byte(PWR_MGMT_1, PWR_RESET, "device reset")
        self._sleep(0.1)
        config = (
            (PWR_MGMT_1, CLKSEL_PLL_XGYRO, "wake, PLL clock"),
            (CONFIG, s.dlpf_cfg, "CONFIG (DLPF)"),
            (SMPLRT_DIV, s.smplrt_div, "SMPLRT_DIV"),
            (GYRO_CONFIG, FS_SEL[s.gyro_range_dps] << 3, "GYRO_CONFIG"),
            (ACCEL_CONFIG, AFS_SEL[s.accel_range_g] << 3, "ACCEL_CONFIG"),
            (INT_PIN_CFG, 0x00, "INT_PIN_CFG"),
            (INT_ENABLE, INT_FIFO_OFLOW, "INT_ENABLE"),
        )
        if self.chip.accel_config2:  # the same filter setting as the gyro's, as Linux's driver writes it
            config += ((ACCEL_CONFIG2, s.dlpf_cfg, "ACCEL_CONFIG2 (accelerometer DLPF)"),)
        for reg, value, what in config:
            self._write_byte(reg, value, what)
        self._sleep(0.01)
        for reg, value, what in config[1:]:
            got = self._read_byte(reg, f"{what} read-back")
            if got != value:
                raise CaptureError(f"{self.where}: {what} reads back {got:#04x} after writing {value:#04x}")
        self._start_fifo("initialisation")

    def _use_chip(self, chip: ChipModel) -> None:
        """Take the part's FIFO size, temperature formula and filter register, or refuse what it cannot do."""
        s = self.settings
        if chip is not self.chip:
            log.warning("%s: WHO_AM_I = %#04x: an %s, not an MPU-6050: %d-byte FIFO, temperature raw / %.2f + %g "
                        "degC%s", self.where, self.who_am_i, chip.name, chip.fifo_bytes, chip.temp_lsb_per_c,
                        chip.temp_offset_c, ", accelerometer low-pass in ACCEL_CONFIG2" if chip.accel_config2 else "")
        if chip.divider_needs_dlpf and s.dlpf_cfg == 0:
            raise ConfigError(f"imu.dlpf_cfg = 0 on the {chip.name} at i2c-{s.bus} address {self.addr:#04x}: its "
                              "SMPLRT_DIV only works with the low-pass filter on, so imu.rate_hz cannot be set; "
                              "use imu.dlpf_cfg 1..6")
        fill_ms = fifo_fill_ms(chip.fifo_bytes, self.packet_bytes, s.rate_hz)
        if s.read_period_ms > 0.8 * fill_ms:
            raise ConfigError(f"imu.read_period_ms = {s.read_period_ms:g} lets the {chip.name}'s {chip.fifo_bytes}-byte "
                              f"FIFO overflow: it fills in {fill_ms:.0f} ms at {s.rate_hz:g} Hz; poll at most every "
                              f"{0.8 * fill_ms:.0f} ms")
        self.chip = chip

    def _start_fifo(self, why: str) -> None:
        """Disable, reset and re-enable the FIFO; a new timing segment starts now."""
        fifo_bits = FIFO_EN_ACCEL | FIFO_EN_GYRO | (FIFO_EN_TEMP if self.settings.temperature else 0)
        self._write_byte(FIFO_EN, 0x00, "FIFO_EN off")
        self._write_byte(USER_CTRL, 0x00, "FIFO disable")
        self._write_byte(USER_CTRL, USER_FIFO_RESET, "FIFO reset")
        self._write_byte(USER_CTRL, USER_FIFO_EN, "FIFO enable")
        self._write_byte(FIFO_EN, fifo_bits, "FIFO_EN")
        self._read_byte(INT_STATUS, "INT_STATUS clear")
        self.stats.fifo_resets += 1
        self._fit.restart()
        self._seg_count = 0
        log.debug("%s: FIFO started (%s)", self.where, why)

    # polling ----------------------------------------------------------------------------
    def read(self) -> ImuSamples:
        """One poll: the samples that arrived since the previous one (maybe none)."""
        if not self._opened:
            raise CaptureError(f"{self.where}: read() before open()")
        self.stats.polls += 1
        try:
            return self._poll()
        except _BusFailure as exc:
            self._reinitialise(exc)
            return ImuSamples.empty()

    def _poll(self) -> ImuSamples:
        pkt = self.packet_bytes
        raw = self._retry("FIFO_COUNT read", self._rdwr, FIFO_COUNT_H, 2)
        t_obs = self._clock_ns()
        count = (raw[0] << 8) | raw[1]
        self.stats.max_fifo_bytes = max(self.stats.max_fifo_bytes, count)
        if count >= self.chip.fifo_bytes:
            self._recover("FIFO overflow (count %d)" % count)
            return ImuSamples.empty()
        n = count // pkt
        chunks = []
        if n:
            per_msg = (I2C_MSG_MAX // pkt) * pkt
            left = n * pkt
            while left:
                k = min(left, per_msg)
                try:
                    chunks.append(self._rdwr(FIFO_R_W, k))
                except OSError as exc:  # bytes may have left the FIFO: never retry, reset
                    self._recover(f"FIFO read failed ({exc})")
                    return ImuSamples.empty()
                left -= k
        status = self._read_byte(INT_STATUS, "INT_STATUS read")
        if status & INT_FIFO_OFLOW:
            self.stats.discarded_samples += n
            self._recover("FIFO overflow flagged during the read")
            return ImuSamples.empty()
        if not n:
            if self._seg_count:
                self._fit.add(self._seg_count - 1, t_obs)
            return ImuSamples.empty()
        self._fit.add(self._seg_count + n - 1, t_obs)
        idx = np.arange(self._seg_count, self._seg_count + n)
        t = self._fit.times_ns(idx) - int(self.settings.timestamps.latency_us * 1000)
        self._seg_count += n
        if self._last_t is not None and t[0] <= self._last_t:
            t = np.maximum(t, self._last_t + 1 + np.arange(n))
        if self._gap_open is not None:
            self.gaps.append((self._gap_open, int(t[0])))
            self._gap_open = None
        self._last_t = int(t[-1])
        self.stats.samples += n
        return self._decode(b"".join(chunks), t)

    def _decode(self, data: bytes, t: np.ndarray) -> ImuSamples:
        words = np.frombuffer(data, dtype=">i2").reshape(len(t), self.packet_bytes // 2).astype(np.int32)
        accel = words[:, 0:3] * self.accel_scale
        if self.settings.temperature:
            temp = self.chip.temp_c(words[:, 3])
            gyro = words[:, 4:7] * self.gyro_scale
        else:
            temp = None
            gyro = words[:, 3:6] * self.gyro_scale
        return ImuSamples(t, gyro, accel, temp)

    def _mark_gap(self) -> None:
        if self._gap_open is None:
            self._gap_open = self._last_t if self._last_t is not None else int(self._clock_ns())

    def _recover(self, why: str) -> None:
        """FIFO contents unusable: reset it and record a gap."""
        if "overflow" in why:
            self.stats.overflows += 1
        log.warning("%s: %s; FIFO reset, samples lost", self.where, why)
        self._mark_gap()
        self._start_fifo(why)

    def _reinitialise(self, failure: _BusFailure) -> None:
        self._mark_gap()
        last = failure
        for attempt in range(self.settings.i2c.reinit_attempts):
            log.warning("%s: %s; re-initialising (%d/%d)", self.where, last, attempt + 1,
                        self.settings.i2c.reinit_attempts)
            self._sleep(self.settings.i2c.backoff_ms / 1000.0 * 2 ** (self.settings.i2c.retries + attempt))
            try:
                self._init_device()
            except _BusFailure as exc:
                last = exc
                continue
            self.stats.reinits += 1
            return
        raise CaptureError(
            f"{self.where}: {last.what} failed after {self.settings.i2c.retries} retries and "
            f"{self.settings.i2c.reinit_attempts} re-initialisations: {last.exc}")


def open_mpu6050(settings: ImuSettings, **inject: object) -> Mpu6050:
    """An opened driver (``bus=``, ``clock_ns=``, ``sleep=`` may be injected)."""
    dev = Mpu6050(settings, **inject)
    dev.open()
    return dev
