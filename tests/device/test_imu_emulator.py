"""The register-level MPU-6050 emulator behaves like the part on the bus (as the driver relies on)."""

from __future__ import annotations

import errno

import numpy as np
import pytest
from smbus2 import i2c_msg

from stereopath.device.capture.imu import mpu6050 as R
from tests.fakes.fake_smbus import Mpu6050Emulator, SimClock, counting_source

A = 0x68


def running(rate_div=0, fifo_bits=0x78, int_enable=R.INT_FIFO_OFLOW, ppm=0.0):
    clk = SimClock()
    em = Mpu6050Emulator(clk, counting_source(), period_error_ppm=ppm)
    for reg, v in ((R.PWR_MGMT_1, 0x01), (R.CONFIG, 1), (R.SMPLRT_DIV, rate_div), (R.GYRO_CONFIG, 1 << 3),
                   (R.INT_ENABLE, int_enable), (R.USER_CTRL, R.USER_FIFO_EN), (R.FIFO_EN, fifo_bits)):
        em.write_byte_data(A, reg, v)
    return em, clk


def rdwr(em, reg, n):
    w, r = i2c_msg.write(A, [reg]), i2c_msg.read(A, n)
    em.i2c_rdwr(w, r)
    return bytes(r)


def test_reset_values_and_who_am_i():
    em = Mpu6050Emulator(SimClock(), who_am_i=0x71)
    assert em.read_byte_data(A, R.PWR_MGMT_1) == 0x40 and em.read_byte_data(A, R.WHO_AM_I) == 0x71
    assert em.read_byte_data(A, R.USER_CTRL) == 0 and em.read_byte_data(A, R.FIFO_EN) == 0


def test_asleep_nothing_is_sampled():
    clk = SimClock()
    em = Mpu6050Emulator(clk)
    em.write_byte_data(A, R.USER_CTRL, R.USER_FIFO_EN)
    em.write_byte_data(A, R.FIFO_EN, 0x78)
    clk.sleep(0.05)
    assert rdwr(em, R.FIFO_COUNT_H, 2) == b"\x00\x00"


def test_fifo_fills_in_register_order_with_count_big_endian():
    em, clk = running()
    rdwr(em, R.FIFO_COUNT_H, 2)          # starts the sample clock
    clk.sleep(0.0105)                     # 10 samples at 1 kHz
    raw = rdwr(em, R.FIFO_COUNT_H, 2)
    count = int.from_bytes(raw, "big")
    assert count == 120
    data = np.frombuffer(rdwr(em, R.FIFO_R_W, count), ">i2").reshape(10, 6)
    assert np.all(data[:, 2] == 16384)                   # accel z = 1 g at +-2 g (AFS_SEL 0)
    assert list(np.diff(data[:, 3])) == [1] * 9          # gyro x carries the sample index: none lost


def test_temperature_packets_are_14_bytes():
    em, clk = running(fifo_bits=0xF8)
    rdwr(em, R.FIFO_COUNT_H, 2)
    clk.sleep(0.0035)
    count = int.from_bytes(rdwr(em, R.FIFO_COUNT_H, 2), "big")
    assert count == 3 * 14
    words = np.frombuffer(rdwr(em, R.FIFO_R_W, count), ">i2").reshape(3, 7)
    assert np.allclose(words[:, 3] / 340 + 36.53, 30.0, atol=0.01)


def test_overflow_loses_the_oldest_bytes_and_sets_the_flag_until_read():
    em, clk = running()
    rdwr(em, R.FIFO_COUNT_H, 2)
    clk.sleep(0.2)                                       # ~200 samples = 2400 bytes > 1024
    assert int.from_bytes(rdwr(em, R.FIFO_COUNT_H, 2), "big") == 1024
    fifo = rdwr(em, R.FIFO_R_W, 1024)
    k, _ = em.truth()
    stream = np.zeros((len(k), 6), ">i2")
    stream[:, 2] = 16384
    stream[:, 3] = k % 30000
    stream = stream.tobytes()
    assert fifo == stream[-1024:]                        # exactly the newest 1024 bytes survive
    assert (len(stream) - 1024) % 12 != 0                # so packet framing is broken
    assert em.read_byte_data(A, R.INT_STATUS) & R.INT_FIFO_OFLOW
    assert not em.read_byte_data(A, R.INT_STATUS) & R.INT_FIFO_OFLOW   # cleared by the read


def test_overflow_flag_needs_the_interrupt_enabled():
    em, clk = running(int_enable=0)
    rdwr(em, R.FIFO_COUNT_H, 2)
    clk.sleep(0.2)
    status = em.read_byte_data(A, R.INT_STATUS)
    assert em.fifo_overflows > 0 and not status & R.INT_FIFO_OFLOW


def test_fifo_reset_only_while_fifo_disabled():
    em, clk = running()
    rdwr(em, R.FIFO_COUNT_H, 2)
    clk.sleep(0.01)
    em.write_byte_data(A, R.USER_CTRL, R.USER_FIFO_EN | R.USER_FIFO_RESET)
    assert int.from_bytes(rdwr(em, R.FIFO_COUNT_H, 2), "big") > 0 and em.ignored_fifo_resets == 1
    em.write_byte_data(A, R.USER_CTRL, 0)
    em.write_byte_data(A, R.USER_CTRL, R.USER_FIFO_RESET)
    assert int.from_bytes(rdwr(em, R.FIFO_COUNT_H, 2), "big") == 0
    assert em.read_byte_data(A, R.USER_CTRL) == 0        # FIFO_RESET self-clears


def test_empty_fifo_repeats_the_last_byte():
    em, clk = running()
    rdwr(em, R.FIFO_COUNT_H, 2)
    clk.sleep(0.0015)
    data = rdwr(em, R.FIFO_R_W, 16)
    assert data[12:] == bytes([data[11]]) * 4


def test_bus_limits_and_faults():
    em, _ = running()
    with pytest.raises(ValueError, match="over 32"):
        em.read_i2c_block_data(A, R.ACCEL_XOUT_H, 33)
    assert len(em.read_i2c_block_data(A, R.ACCEL_XOUT_H, 14)) == 14
    with pytest.raises(OSError) as e:
        em.i2c_rdwr(i2c_msg.write(A, [R.FIFO_R_W]), i2c_msg.read(A, 8193))
    assert e.value.errno == errno.EINVAL
    with pytest.raises(OSError) as e:
        em.read_byte_data(0x69, R.WHO_AM_I)
    assert e.value.errno == errno.EREMOTEIO
    em.fail_next(2, op="read")
    for _ in range(2):
        with pytest.raises(OSError):
            em.read_byte_data(A, R.WHO_AM_I)
    assert em.read_byte_data(A, R.WHO_AM_I) == 0x68
    em.disconnected = True
    with pytest.raises(OSError):
        em.write_byte_data(A, R.CONFIG, 1)


def test_true_rate_follows_divider_and_clock_error():
    em, clk = running(rate_div=4, ppm=10000.0)     # 200 Hz nominal, 1 % slow
    rdwr(em, R.FIFO_COUNT_H, 2)
    for _ in range(50):
        clk.sleep(0.02)
        n = int.from_bytes(rdwr(em, R.FIFO_COUNT_H, 2), "big")
        rdwr(em, R.FIFO_R_W, n - n % 12)
    k, t = em.truth()
    assert np.allclose(np.diff(t), 5e6 * 1.01, atol=1)
