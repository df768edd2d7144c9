"""A register-level MPU-6050 behind a fake ``smbus2.SMBus``, driven by a controllable clock.

Used by the tests, the benchmarks and ``stereopath device selftest --imu emulated`` on a
machine without the chip.  It behaves like the part as the driver sees it:

* ``read_byte_data``, ``write_byte_data``, ``read_i2c_block_data`` (raises ``ValueError``
  above 32 bytes like smbus2) and ``i2c_rdwr`` filling real ``smbus2.i2c_msg`` read
  buffers (``ctypes.memmove``); a message above 8192 bytes fails with ``EINVAL`` like
  i2c-dev; another address NACKs (``OSError`` 121);
* register file with the reset values (PWR_MGMT_1 = 0x40, WHO_AM_I = 0x68 or a clone's
  value), DEVICE_RESET, SLEEP, auto-incrementing burst reads, FIFO_COUNT big-endian;
* samples are produced while awake at ``(1 + SMPLRT_DIV) / (8 kHz or 1 kHz)`` stretched by
  ``period_error_ppm`` (the real clock is up to ~1 % off), from a ``source(k, t_ns)``
  giving SI values that are converted with the configured full-scale ranges;
* an MPU-6500/9250 (``who_am_i`` 0x70/0x71) as :data:`~stereopath.device.capture.imu.mpu6050.CHIPS`
  describes it: a 512-byte FIFO, its temperature formula, ``SMPLRT_DIV`` ignored with the DLPF
  off (8 kHz); ``ACCEL_CONFIG2`` is an ordinary register;
* a 1024-byte FIFO fed in register order (accel, temp, gyro per FIFO_EN): when full the
  oldest bytes are lost (framing broken) and INT_STATUS.FIFO_OFLOW is set if enabled in
  INT_ENABLE; reading INT_STATUS clears it; FIFO_RESET is honoured only while
  USER_CTRL.FIFO_EN is (and stays) clear; reading FIFO_R_W while empty repeats the last
  byte;
* every transfer takes bus time (9 bits per byte at ``bus_hz``) on the clock when the
  clock can advance (:class:`SimClock`);
* faults: ``fail_next(n, op=...)`` makes the next ``n`` matching transfers raise
  ``OSError``; ``disconnected = True`` NACKs everything.

``truth()`` returns the index and true time of every sample produced, for benchmarks.
"""

from __future__ import annotations

import ctypes
import errno
import os
import threading
import time
from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np

from stereopath.device.core.frames import ImuSamples
from stereopath.device.capture.imu import mpu6050 as R

if TYPE_CHECKING:
    from smbus2 import i2c_msg

I2C_M_RD = 0x0001
SourceFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray | None]]


class BusClock(Protocol):
    """The emulator's time: ``now_ns()``, and ``advance_ns`` for the time a transfer takes on the bus."""

    def now_ns(self) -> int: ...

    def advance_ns(self, dt_ns: int) -> None: ...


class SimClock:
    """Simulated monotonic time: ``now_ns()`` and a ``sleep`` that advances it."""

    def __init__(self, t0_ns: int = 1_000_000_000) -> None:
        self.t_ns = int(t0_ns)
        self._lock = threading.Lock()

    def now_ns(self) -> int:
        return self.t_ns

    def advance_ns(self, dt_ns: int) -> None:
        with self._lock:
            self.t_ns += int(dt_ns)

    def sleep(self, seconds: float) -> None:
        self.advance_ns(int(round(max(0.0, seconds) * 1e9)))


class RealClock:
    """Wall monotonic time; transfers take no simulated time."""

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def advance_ns(self, dt_ns: int) -> None:
        pass

    def sleep(self, seconds: float) -> None:
        time.sleep(max(0.0, seconds))


def still_source(gyro_bias_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 gravity_dir: tuple[float, float, float] = (0.0, 0.0, 1.0),
                 gyro_noise_rad_s: float = 0.002, accel_noise_m_s2: float = 0.02,
                 temp_c: float = 30.0, seed: int = 0) -> SourceFn:
    """A unit at rest: specific force ``+g`` along ``gravity_dir``, constant gyro bias, white noise."""
    rng = np.random.default_rng(seed)
    g = np.asarray(gravity_dir, float)
    g = g / np.linalg.norm(g) * R.STANDARD_GRAVITY
    bias = np.asarray(gyro_bias_rad_s, float)

    def source(k: np.ndarray, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = len(k)
        gyro = bias + gyro_noise_rad_s * rng.standard_normal((n, 3))
        accel = g + accel_noise_m_s2 * rng.standard_normal((n, 3))
        return accel, gyro, np.full(n, temp_c)

    return source


def samples_source(imu: ImuSamples, t_start_ns: int | None = None) -> SourceFn:
    """Replay recorded/simulated samples: emulator time ``t`` maps to ``imu.t_ns[0] + (t - t_start)``.

    ``t_start_ns`` defaults to the time of the first sample requested.  Values are linearly
    interpolated; beyond the end the last sample is held.
    """
    state: dict[str, int] = {}
    if t_start_ns is not None:
        state["t0"] = int(t_start_ns)
    ts = imu.t_ns.astype(np.float64)

    def source(k: np.ndarray, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        if "t0" not in state:
            state["t0"] = int(t_ns[0])
        tq = (imu.t_ns[0] + (t_ns - state["t0"])).astype(np.float64)
        gyro = np.stack([np.interp(tq, ts, imu.gyro_rad_s[:, j]) for j in range(3)], axis=1)
        accel = np.stack([np.interp(tq, ts, imu.accel_m_s2[:, j]) for j in range(3)], axis=1)
        temp = None if imu.temp_c is None else np.interp(tq, ts, imu.temp_c)
        return accel, gyro, temp

    return source


class Mpu6050Emulator:
    """Fake ``smbus2.SMBus`` with one MPU-6050 on it (see module doc)."""

    def __init__(self, clock: BusClock | None = None, source: SourceFn | None = None, address: int = 0x68,
                 who_am_i: int = 0x68, period_error_ppm: float = 0.0, bus_hz: float = 400_000.0) -> None:
        self.clock = clock if clock is not None else RealClock()
        self.source = source if source is not None else still_source()
        self.address = int(address)
        self.who_am_i_value = int(who_am_i)
        self.chip = R.CHIPS.get(self.who_am_i_value, R.MPU6050_CHIP)
        self.period_error_ppm = float(period_error_ppm)
        self.bus_hz = float(bus_hz)
        self.disconnected = False
        self.closed = False
        self._faults: list[tuple[str, int]] = []   # (op, errno) consumed in order
        self.transfers = 0
        self.bytes_read = 0
        self.fifo_overflows = 0
        self.fifo_resets = 0
        self.resets = 0
        self.ignored_fifo_resets = 0
        self._lock = threading.RLock()
        self._truth_k: list[np.ndarray] = []
        self._truth_t: list[np.ndarray] = []
        self._k = 0  # samples produced so far (continues across device resets)
        self._power_on()

    # state --------------------------------------------------------------------------------
    def _power_on(self) -> None:
        self.regs = bytearray(128)
        self.regs[R.PWR_MGMT_1] = R.PWR_SLEEP
        self.regs[R.WHO_AM_I] = self.who_am_i_value
        self.fifo = bytearray()
        self._ptr = 0
        self._last_fifo_byte = 0
        self._next_tick: float | None = None

    @property
    def period_ns(self) -> float:
        dlpf = self.regs[R.CONFIG] & 0x07
        base = 8000.0 if dlpf in (0, 7) else 1000.0
        div = 0 if self.chip.divider_needs_dlpf and dlpf in (0, 7) else self.regs[R.SMPLRT_DIV]
        return (1 + div) / base * 1e9 * (1.0 + self.period_error_ppm * 1e-6)

    def _awake(self) -> bool:
        return not self.regs[R.PWR_MGMT_1] & R.PWR_SLEEP

    def _sync(self) -> None:
        """Produce every sample due up to the clock's current time."""
        now = self.clock.now_ns()
        if not self._awake():
            self._next_tick = None
            return
        period = self.period_ns
        if self._next_tick is None:
            self._next_tick = now + period
            return
        if now < self._next_tick:
            return
        n = int((now - self._next_tick) // period) + 1
        t = (self._next_tick + period * np.arange(n)).astype(np.int64)
        self._next_tick += n * period
        k = np.arange(self._k, self._k + n)
        self._k += n
        accel, gyro, temp = self.source(k, t)
        self._truth_k.append(k)
        self._truth_t.append(t)
        gyro_lsb = R.GYRO_LSB_PER_DPS[[250, 500, 1000, 2000][(self.regs[R.GYRO_CONFIG] >> 3) & 3]]
        accel_lsb = R.ACCEL_LSB_PER_G[[2, 4, 8, 16][(self.regs[R.ACCEL_CONFIG] >> 3) & 3]]
        a_counts = np.clip(np.round(np.asarray(accel) / R.STANDARD_GRAVITY * accel_lsb), -32768, 32767)
        g_counts = np.clip(np.round(np.rad2deg(np.asarray(gyro)) * gyro_lsb), -32768, 32767)
        t_c = np.full(n, 30.0) if temp is None else np.asarray(temp, float)
        t_counts = np.clip(np.round(self.chip.temp_raw(t_c)), -32768, 32767)
        # data registers hold the latest sample
        last = np.concatenate([a_counts[-1], t_counts[-1:], g_counts[-1]]).astype(">i2").tobytes()
        self.regs[R.ACCEL_XOUT_H:R.ACCEL_XOUT_H + 14] = last
        self.regs[R.INT_STATUS] |= R.INT_DATA_RDY
        fifo_en = self.regs[R.FIFO_EN]
        if not (self.regs[R.USER_CTRL] & R.USER_FIFO_EN) or not fifo_en:
            return
        cols = []
        if fifo_en & R.FIFO_EN_ACCEL:
            cols.append(a_counts)
        if fifo_en & R.FIFO_EN_TEMP:
            cols.append(t_counts[:, None])
        for bit, j in ((0x40, 0), (0x20, 1), (0x10, 2)):
            if fifo_en & bit:
                cols.append(g_counts[:, j:j + 1])
        packets = np.concatenate(cols, axis=1).astype(">i2").tobytes()
        self.fifo += packets
        if len(self.fifo) > self.chip.fifo_bytes:
            del self.fifo[:len(self.fifo) - self.chip.fifo_bytes]   # the oldest bytes are lost
            self.fifo_overflows += 1
            if self.regs[R.INT_ENABLE] & R.INT_FIFO_OFLOW:
                self.regs[R.INT_STATUS] |= R.INT_FIFO_OFLOW

    def truth(self) -> tuple[np.ndarray, np.ndarray]:
        """Index and true time (ns) of every sample produced since power-on."""
        if not self._truth_k:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate(self._truth_k), np.concatenate(self._truth_t)

    # faults -------------------------------------------------------------------------------
    def fail_next(self, n: int = 1, op: str = "any", err: int = errno.EREMOTEIO) -> None:
        """The next ``n`` transfers of kind ``op`` (read, write, rdwr, any) raise ``OSError(err)``."""
        self._faults.extend([(op, err)] * n)

    def _check(self, op: str, addr: int) -> None:
        if self.closed:
            raise OSError(errno.EBADF, "bus closed")
        if self.disconnected or addr != self.address:
            raise OSError(errno.EREMOTEIO, os.strerror(errno.EREMOTEIO))
        if self._faults and self._faults[0][0] in (op, "any"):
            _, e = self._faults.pop(0)
            raise OSError(e, os.strerror(e))

    def _bus_time(self, nbytes: int) -> None:
        self.clock.advance_ns(int(nbytes * 9 / self.bus_hz * 1e9))

    # register access --------------------------------------------------------------------
    def _read(self, reg: int, n: int) -> bytes:
        if reg == R.FIFO_R_W:
            k = min(n, len(self.fifo))
            out = bytes(self.fifo[:k])
            del self.fifo[:k]
            if k:
                self._last_fifo_byte = out[-1]
            out += bytes([self._last_fifo_byte]) * (n - k)
            self.bytes_read += n
            return out
        out = bytearray()
        for i in range(n):
            r = (reg + i) & 0x7F
            if r == R.FIFO_COUNT_H:
                v = (len(self.fifo) >> 8) & 0xFF
            elif r == R.FIFO_COUNT_H + 1:
                v = len(self.fifo) & 0xFF
            elif r == R.FIFO_R_W:
                v = self.fifo.pop(0) if self.fifo else self._last_fifo_byte
            else:
                v = self.regs[r]
            out.append(v)
            if r == R.INT_STATUS:
                self.regs[R.INT_STATUS] = 0  # cleared by reading
        self.bytes_read += n
        return bytes(out)

    def _write(self, reg: int, value: int) -> None:
        value &= 0xFF
        if reg == R.WHO_AM_I or reg in (R.INT_STATUS, R.FIFO_COUNT_H, R.FIFO_COUNT_H + 1):
            return  # read-only
        if reg == R.PWR_MGMT_1:
            if value & R.PWR_RESET:
                self.resets += 1
                self._power_on()
                return
            self.regs[reg] = value
            if not self._awake():
                self._next_tick = None
            return
        if reg == R.USER_CTRL:
            prev = self.regs[reg]
            if value & R.USER_FIFO_RESET:
                if (prev & R.USER_FIFO_EN) or (value & R.USER_FIFO_EN):
                    self.ignored_fifo_resets += 1   # only honoured while FIFO_EN is clear
                else:
                    self.fifo.clear()
                    self.fifo_resets += 1
            self.regs[reg] = value & ~R.USER_FIFO_RESET & 0xFF   # self-clearing
            return
        if reg == R.FIFO_R_W:
            if len(self.fifo) < self.chip.fifo_bytes:
                self.fifo.append(value)
            return
        self.regs[reg] = value

    # smbus2.SMBus interface ----------------------------------------------------------------
    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int:
        with self._lock:
            self._check("read", i2c_addr)
            self._sync()
            self.transfers += 1
            v = self._read(register, 1)[0]
            self._bus_time(3)
            return v

    def write_byte_data(self, i2c_addr: int, register: int, value: int, force: bool | None = None) -> None:
        with self._lock:
            self._check("write", i2c_addr)
            self._sync()
            self.transfers += 1
            self._write(register, value)
            self._bus_time(3)

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int, force: bool | None = None) -> list[int]:
        if length > 32:
            raise ValueError("Desired block length over 32 bytes")
        with self._lock:
            self._check("read", i2c_addr)
            self._sync()
            self.transfers += 1
            data = self._read(register, length)
            self._bus_time(2 + length)
            return list(data)

    def i2c_rdwr(self, *msgs: i2c_msg) -> None:
        with self._lock:
            for m in msgs:
                if m.len > 8192:
                    raise OSError(errno.EINVAL, os.strerror(errno.EINVAL))
            self._check("rdwr", msgs[0].addr if msgs else self.address)
            for m in msgs:
                if m.addr != self.address:
                    raise OSError(errno.EREMOTEIO, os.strerror(errno.EREMOTEIO))
            self._sync()
            self.transfers += 1
            total = 0
            for m in msgs:
                total += 1 + m.len
                if m.flags & I2C_M_RD:
                    data = self._read(self._ptr, m.len)
                    ctypes.memmove(m.buf, data, m.len)
                else:
                    payload = ctypes.string_at(m.buf, m.len)
                    if not payload:
                        continue
                    self._ptr = payload[0]
                    for i, v in enumerate(payload[1:]):
                        self._write((self._ptr + i) & 0x7F, v)
            self._bus_time(total)

    def close(self) -> None:
        self.closed = True

    def __enter__(self) -> "Mpu6050Emulator":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
