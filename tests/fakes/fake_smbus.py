"""The register-level MPU-6050 emulator as a fake ``smbus2.SMBus`` for tests.

The emulator itself lives in :mod:`stereopath.device.capture.imu.emulator` because ``stereopath device
selftest --imu emulated`` uses it on machines without the chip; this module re-exports it
and adds the helpers the tests share.
"""

from __future__ import annotations

import numpy as np

from stereopath.device.capture.imu.emulator import Mpu6050Emulator, RealClock, SimClock, samples_source, still_source

__all__ = ["Mpu6050Emulator", "RealClock", "SimClock", "counting_source", "samples_source", "still_source",
           "decode_index"]

INDEX_MOD = 30000


def counting_source(gyro_lsb_per_dps: float = 65.5, accel_z_m_s2: float = 9.80665):
    """Samples whose gyro x carries the sample index (mod 30000) in LSB, so outputs can be matched
    to the emulator's truth exactly; accel is gravity on z, gyro y/z are zero."""

    def source(k: np.ndarray, t_ns: np.ndarray):
        n = len(k)
        gyro = np.zeros((n, 3))
        gyro[:, 0] = np.deg2rad((k % INDEX_MOD) / gyro_lsb_per_dps)
        accel = np.zeros((n, 3))
        accel[:, 2] = accel_z_m_s2
        return accel, gyro, None

    return source


def decode_index(gyro_rad_s: np.ndarray, gyro_lsb_per_dps: float = 65.5) -> np.ndarray:
    """Inverse of :func:`counting_source`: the sample indices (unwrapped) of driver output."""
    k = np.round(np.rad2deg(gyro_rad_s[:, 0]) * gyro_lsb_per_dps).astype(np.int64)
    return np.unwrap(k, period=INDEX_MOD).astype(np.int64)
