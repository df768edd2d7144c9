"""Cheap device health probes for the status message (each returns ``None`` when unavailable)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

THERMAL_ZONE = Path("/sys/class/thermal/thermal_zone0/temp")


def cpu_load_pct() -> float | None:
    """One-minute load average as a percentage of all cores (100 = every core busy)."""
    try:
        return 100.0 * os.getloadavg()[0] / max(os.cpu_count() or 1, 1)
    except OSError:
        return None


def cpu_temperature_c(zone: Path = THERMAL_ZONE) -> float | None:
    """SoC temperature from the kernel thermal zone (millidegrees Celsius)."""
    try:
        return int(zone.read_text().strip()) / 1000.0
    except (OSError, ValueError):
        return None


def disk_free_bytes(path: str | Path) -> int | None:
    """Free bytes on the file system holding ``path``."""
    try:
        return int(shutil.disk_usage(path).free)
    except OSError:
        return None
