"""The systemd watchdog: ping only while both sensors deliver, so a hung camera or IMU restarts the unit."""

from __future__ import annotations

from typing import Mapping

from stereopath.device.service.sdnotify import Notifier, watchdog_interval_s


class Watchdog:
    """``WATCHDOG=1`` every half watchdog period while data is fresh (no pings without ``$WATCHDOG_USEC``)."""

    def __init__(self, notifier: Notifier, environ: Mapping[str, str]) -> None:
        self.notifier = notifier
        self.interval_s = watchdog_interval_s(environ)
        self.pings = 0
        self._last_ping: float | None = None

    def max_data_age_s(self, configured_s: float) -> float:
        """The configured ``service.max_data_age_s``, capped at half the watchdog period."""
        return configured_s if self.interval_s is None else min(configured_s, self.interval_s / 2.0)

    def data_fresh(self, now: float, max_age_s: float, last_frame_at: float | None, last_imu_at: float | None,
                   has_imu: bool) -> bool:
        """A frame and (when an IMU is configured) an IMU sample arrived within ``max_age_s``."""
        if last_frame_at is None or now - last_frame_at > max_age_s:
            return False
        if has_imu and (last_imu_at is None or now - last_imu_at > max_age_s):
            return False
        return True

    def tick(self, now: float, fresh: bool) -> None:
        """Ping when due and the data is fresh."""
        if self.interval_s is None or not fresh:
            return
        if self._last_ping is None or now - self._last_ping >= self.interval_s / 2.0:
            if self.notifier.notify("WATCHDOG=1"):
                self.pings += 1
            self._last_ping = now
