"""MPU-6050 driver on the register-level emulator: init, SI units, bursts, overflow, bus errors, timing."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from stereopath.device.core.config import from_mapping
from stereopath.device.errors import CaptureError
from stereopath.device.core.frames import ImuSamples
from stereopath.device.capture.imu import create_imu, mpu6050 as R
from stereopath.device.capture.imu.mpu6050 import Mpu6050
from stereopath.device.settings import ImuSettings
from tests.fakes.fake_smbus import Mpu6050Emulator, SimClock, counting_source, decode_index, still_source

pytestmark = pytest.mark.timeout(60)


def make(rate=1000.0, dlpf=1, ppm=8000.0, source=None, who=0x68, **kw):
    s = from_mapping(ImuSettings, {"rate_hz": rate, "dlpf_cfg": dlpf, **kw})
    clk = SimClock()
    em = Mpu6050Emulator(clk, source or counting_source(), who_am_i=who, period_error_ppm=ppm)
    drv = Mpu6050(s, bus=em, clock_ns=clk.now_ns, sleep=clk.sleep)
    return drv, em, clk


def run_polls(drv, clk, n, period_s=0.02, jitter_s=0.0, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        clk.sleep(period_s + rng.uniform(0, jitter_s))
        out.append(drv.read())
    return ImuSamples.concat(out)


def test_initialisation_writes_the_configuration():
    drv, em, _ = make(rate=200.0, dlpf=3, gyro_range_dps=1000, accel_range_g=8, read_period_ms=20)
    drv.open()
    r = em.regs
    assert (r[R.PWR_MGMT_1], r[R.CONFIG], r[R.SMPLRT_DIV]) == (0x01, 3, 4)
    assert (r[R.GYRO_CONFIG], r[R.ACCEL_CONFIG]) == (2 << 3, 2 << 3)
    assert (r[R.INT_ENABLE], r[R.USER_CTRL], r[R.FIFO_EN]) == (0x10, 0x40, 0x78)
    assert em.resets == 1 and em.fifo_resets == 1 and drv.who_am_i == 0x68
    drv.close()
    assert em.regs[R.PWR_MGMT_1] & R.PWR_SLEEP and em.regs[R.USER_CTRL] == 0


def test_clone_who_am_i_is_accepted_with_a_warning(caplog):
    drv, _, _ = make(who=0x70)
    with caplog.at_level(logging.WARNING, logger="stereopath.device.capture.imu.mpu6050"):
        drv.open()
    assert "0x70" in caplog.text and "MPU-6500" in caplog.text


@pytest.mark.parametrize("who, name", [(0x70, "MPU-6500"), (0x71, "MPU-9250")])
def test_mpu6500_family_gets_its_filter_register_fifo_size_and_temperature(who, name):
    drv, em, clk = make(rate=1000.0, dlpf=3, who=who, source=still_source(temp_c=31.5), temperature=True,
                        read_period_ms=20)
    drv.open()
    assert drv.chip.name == name and drv.chip.fifo_bytes == 512
    assert em.regs[R.ACCEL_CONFIG2] == 3 and em.regs[R.CONFIG] == 3     # accelerometer filter as the gyro's
    got = run_polls(drv, clk, 5)
    assert len(got) > 80 and np.allclose(got.temp_c, 31.5, atol=0.01)  # raw / 333.87 + 21, not raw / 340 + 36.53
    clk.sleep(0.05)                                                     # 36 14-byte packets fill 512 bytes
    drv.read()
    assert drv.stats.overflows == 1 and em.fifo_overflows >= 1          # seen at 512 bytes, not 1024
    after = run_polls(drv, clk, 3)
    assert len(after) > 40 and np.allclose(after.temp_c, 31.5, atol=0.01)  # framing restored by the reset
    drv.close()


def test_mpu6500_refuses_what_it_cannot_do():
    from stereopath.device.errors import ConfigError

    drv, em, _ = make(rate=1000.0, dlpf=0, who=0x70)       # SMPLRT_DIV ignored without the DLPF
    with pytest.raises(ConfigError, match=r"imu\.dlpf_cfg = 0 on the MPU-6500"):
        drv.open()
    drv, em, _ = make(rate=1000.0, dlpf=1, who=0x71, read_period_ms=40)  # fine for 1024 bytes, not for 512
    with pytest.raises(ConfigError, match=r"imu\.read_period_ms = 40 .* 512-byte FIFO"):
        drv.open()
    drv, em, _ = make(rate=1000.0, dlpf=1, who=0x68, read_period_ms=40)
    drv.open()
    assert drv.chip.fifo_bytes == 1024 and em.regs[R.ACCEL_CONFIG2] == 0  # an MPU-6050 has no ACCEL_CONFIG2
    drv.close()


def test_unknown_who_am_i_names_the_value():
    drv, _, _ = make(who=0x12)
    with pytest.raises(CaptureError, match="WHO_AM_I = 0x12"):
        drv.open()


def test_si_units_and_temperature():
    bias = (0.01, -0.02, 0.03)
    src = still_source(gyro_bias_rad_s=bias, gravity_dir=(0, 1, 0), gyro_noise_rad_s=0, accel_noise_m_s2=0,
                       temp_c=31.5)
    drv, _, clk = make(rate=200.0, dlpf=3, source=src, temperature=True, read_period_ms=20)
    drv.open()
    x = run_polls(drv, clk, 20)
    assert drv.packet_bytes == 14 and len(x) > 70
    lsb_g = np.deg2rad(1 / 65.5)
    assert np.allclose(x.gyro_rad_s, bias, atol=lsb_g)
    assert np.allclose(x.accel_m_s2, [0, 9.80665, 0], atol=9.80665 / 8192)
    assert np.allclose(x.temp_c, 31.5, atol=1 / 340)


def test_no_sample_lost_at_1khz_read_every_20ms():
    drv, em, clk = make()
    drv.open()
    x = run_polls(drv, clk, 500, jitter_s=0.004)          # 10 s
    k = decode_index(x.gyro_rad_s)
    assert np.all(np.diff(k) == 1)
    produced, _ = em.truth()
    still_in_fifo = len(em.fifo) // 12
    assert k[-1] == produced[-1] - still_in_fifo
    assert drv.stats.overflows == 0 and drv.gaps == [] and np.all(np.diff(x.t_ns) > 0)
    assert np.allclose(x.accel_m_s2[:, 2], 9.80665, atol=1e-3)


def test_fitted_timestamps_track_a_clock_one_percent_off():
    drv, em, clk = make(ppm=10000.0)
    drv.open()
    x = run_polls(drv, clk, 500, jitter_s=0.004)
    k = decode_index(x.gyro_rad_s)
    tk, tt = em.truth()
    truth = tt[np.searchsorted(tk, k)]
    err = (x.t_ns - truth)[len(x) // 2:] / 1e6       # steady state (ms)
    assert np.sqrt(np.mean(err ** 2)) < 0.2
    assert drv._fit.period_ns == pytest.approx(1.01e6, rel=2e-4)   # not the nominal 1.00 ms


def test_stalled_reads_overflow_then_recover_with_a_gap():
    drv, em, clk = make()
    drv.open()
    a = run_polls(drv, clk, 50)
    clk.sleep(2.0)                                          # the host stalls for 2 s
    b = run_polls(drv, clk, 100)
    assert drv.stats.overflows >= 1 and len(drv.gaps) == 1
    g0, g1 = drv.gaps[0]
    assert g0 == a.t_ns[-1] and g1 == b.t_ns[0] and (g1 - g0) / 1e9 > 1.9
    # after recovery every sample is a whole, correct packet (framing restored)
    kb = decode_index(b.gyro_rad_s)
    assert np.all(np.diff(kb) == 1) and np.allclose(b.accel_m_s2[:, 2], 9.80665, atol=1e-3)
    tk, tt = em.truth()
    err = (b.t_ns - tt[np.searchsorted(tk, kb)])[20:] / 1e6
    assert np.max(np.abs(err)) < 1.0                        # the period survives the reset


def test_overflow_between_count_and_data_read_discards_the_batch():
    # the host is preempted for 100 ms right after reading FIFO_COUNT: the FIFO overflows before
    # the data transfer, so the packets read are misframed; INT_STATUS (read last) says so
    drv, em, clk = make()
    drv.open()
    a = run_polls(drv, clk, 10)
    real = em.i2c_rdwr

    def preempted(*msgs):
        real(*msgs)
        if bytes(msgs[0])[0] == R.FIFO_COUNT_H:
            clk.sleep(0.1)

    em.i2c_rdwr = preempted
    clk.sleep(0.02)
    x = drv.read()
    em.i2c_rdwr = real
    assert len(x) == 0 and drv.stats.discarded_samples > 0 and drv.stats.overflows == 1
    b = run_polls(drv, clk, 10)
    assert np.allclose(b.accel_m_s2[:, 2], 9.80665, atol=1e-3)   # nothing misframed got through
    assert np.all(np.diff(decode_index(b.gyro_rad_s)) == 1)
    assert drv.gaps == [(int(a.t_ns[-1]), int(b.t_ns[0]))]


def test_transient_bus_errors_are_retried_with_backoff():
    drv, em, clk = make()
    drv.open()
    run_polls(drv, clk, 5)
    em.fail_next(2, op="rdwr")                               # the FIFO_COUNT read fails twice
    t0 = clk.now_ns()
    x = drv.read()
    assert drv.stats.retries == 2 and len(x) > 0 and drv.gaps == []
    assert clk.now_ns() - t0 >= (2 + 4) * 1_000_000          # 2 ms then 4 ms backoff


def test_fifo_data_read_error_resets_the_fifo_instead_of_retrying():
    drv, em, clk = make()
    drv.open()
    a = run_polls(drv, clk, 5)
    clk.sleep(0.02)
    real = em.i2c_rdwr

    def flaky(*msgs):  # the count read succeeds, the FIFO data transfer fails
        if bytes(msgs[0])[0] == R.FIFO_R_W:
            raise OSError(121, "Remote I/O error")
        return real(*msgs)

    em.i2c_rdwr = flaky
    x = drv.read()
    em.i2c_rdwr = real
    assert len(x) == 0 and drv.stats.fifo_resets == 2 and drv.stats.retries == 0
    b = run_polls(drv, clk, 10)
    assert len(drv.gaps) == 1 and drv.gaps[0][0] == a.t_ns[-1] and drv.gaps[0][1] == b.t_ns[0]


def test_persistent_error_reinitialises_then_fails_clearly():
    drv, em, clk = make(i2c={"retries": 2, "reinit_attempts": 1})
    drv.open()
    run_polls(drv, clk, 3)
    em.fail_next(3, op="rdwr")                               # exhausts the retries once
    assert len(drv.read()) == 0
    assert drv.stats.reinits == 1 and em.resets == 2
    after = run_polls(drv, clk, 5)
    assert len(after) > 0 and len(drv.gaps) == 1
    em.disconnected = True
    with pytest.raises(CaptureError, match=r"i2c-1 address 0x68: .* after 2 retries and 1 re-initialisations"):
        drv.read()


def test_burst_reads_are_whole_packets_within_the_message_limit(monkeypatch):
    monkeypatch.setattr(R, "I2C_MSG_MAX", 100)                # force chunking (real limit 8192)
    drv, em, clk = make()
    drv.open()
    sizes = []
    real = em.i2c_rdwr

    def spy(*msgs):
        sizes.append((msgs[0].len and bytes(msgs[0])[0], msgs[-1].len))
        return real(*msgs)

    em.i2c_rdwr = spy
    x = run_polls(drv, clk, 20)
    fifo_reads = [n for reg, n in sizes if reg == R.FIFO_R_W]
    count_reads = [n for reg, n in sizes if reg == R.FIFO_COUNT_H]
    assert count_reads and set(count_reads) == {2}            # high byte first, both in one burst
    assert max(fifo_reads) == 96 and all(n % 12 == 0 for n in fifo_reads)
    assert np.all(np.diff(decode_index(x.gyro_rad_s)) == 1)


def test_create_imu_emulated_backend_runs_on_its_own_clock():
    s = from_mapping(ImuSettings, {"backend": "emulated"})
    imu = create_imu(s)
    imu.open()
    for _ in range(10):
        imu.sleep(0.02)
        imu.read()
    imu.close()
    assert imu.stats.samples > 30 and imu.who_am_i == 0x68


def test_polling_reader_thread_on_real_time_and_its_error_path():
    import time

    from stereopath.device.capture.imu import PollingImuReader
    from tests.fakes.fake_smbus import RealClock

    s = from_mapping(ImuSettings, {"rate_hz": 200.0})
    em = Mpu6050Emulator(RealClock(), still_source())
    reader = PollingImuReader(Mpu6050(s, bus=em, sleep=lambda _s: None), period_s=0.02)
    reader.open()
    try:
        time.sleep(0.3)
        x = reader.read()
        assert 30 <= len(x) <= 90 and np.all(np.diff(x.t_ns) > 0)
        em.disconnected = True
        deadline = time.monotonic() + 5
        with pytest.raises(CaptureError, match="0x68"):
            while time.monotonic() < deadline:
                reader.read()
                time.sleep(0.02)
    finally:
        reader.close()
    assert reader._thread is None
