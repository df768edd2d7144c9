"""Inertial sensing: the :class:`ImuSource` seam, the MPU-6050 driver and its emulator.

``create_imu(settings, stereo_source=None)`` returns an unopened source for
``settings.backend``: ``mpu6050`` (the chip on ``/dev/i2c-N``), ``emulated`` (the
register-level emulator on a simulated clock, for machines without the chip),
``source`` (the stereo source's own IMU, e.g. an OAK-D's) or ``none`` (``None``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from stereopath.device.errors import ConfigError
from stereopath.device.capture.imu.base import ImuSource, OfflineImu, PollingImuReader
from stereopath.device.settings import ImuSettings

if TYPE_CHECKING:
    from stereopath.device.capture.sources.base import StereoSource

__all__ = ["ImuSource", "OfflineImu", "PollingImuReader", "create_imu"]


def create_imu(settings: ImuSettings, stereo_source: StereoSource | None = None, **inject: object) -> ImuSource | None:
    """The configured IMU, not yet opened (``bus=``, ``clock=``, ``source_fn=`` injectable)."""
    backend = settings.backend
    if backend == "none":
        return None
    if backend == "source":
        imu = getattr(stereo_source, "imu", None)
        if imu is None:
            raise ConfigError("imu.backend = 'source' but the stereo source has no IMU of its own")
        return imu
    from stereopath.device.capture.imu.mpu6050 import Mpu6050

    if backend == "mpu6050":
        kw = {k: inject[k] for k in ("bus", "clock_ns", "sleep") if k in inject}
        return Mpu6050(settings, **kw)
    if backend == "emulated":
        import numpy as np

        from stereopath.device.capture.imu.emulator import Mpu6050Emulator, SimClock, still_source

        clock = inject.get("clock") or SimClock()
        em = settings.emulated
        source_fn = inject.get("source_fn") or still_source(
            gyro_bias_rad_s=tuple(np.deg2rad(em.gyro_bias_dps)), seed=em.seed)
        bus = Mpu6050Emulator(clock, source_fn, address=settings.address, period_error_ppm=em.period_error_ppm)
        return Mpu6050(settings, bus=bus, clock_ns=clock.now_ns, sleep=clock.sleep)
    raise ConfigError(f"imu.backend = {backend!r} is not one of mpu6050, emulated, source, none")
