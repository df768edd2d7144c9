"""Data passed between stages: stereo frames and IMU sample blocks.

``t_ns`` is always integer nanoseconds on one monotonic clock per session,
at mid-exposure for images.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import numpy as np


@dataclass
class StereoFrame:
    """One synchronised left/right pair (8-bit grey, or BGR when ``meta['color']``), and the IMU samples
    since the previous frame once time alignment has attached them (``imu``)."""

    seq: int
    t_ns: int
    left: np.ndarray
    right: np.ndarray
    meta: dict[str, object] = field(default_factory=dict)
    imu: ImuSamples | None = None


@dataclass
class ImuSamples:
    """A block of IMU samples in SI units, body (IMU) frame.

    ``t_ns`` (N,) int64, ``gyro_rad_s`` (N, 3), ``accel_m_s2`` (N, 3) specific force
    (gravity included, +9.81 up when at rest), ``temp_c`` (N,) or None.
    """

    t_ns: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray
    temp_c: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64).reshape(-1)
        self.gyro_rad_s = np.asarray(self.gyro_rad_s, dtype=float).reshape(-1, 3)
        self.accel_m_s2 = np.asarray(self.accel_m_s2, dtype=float).reshape(-1, 3)
        n = len(self.t_ns)
        if len(self.gyro_rad_s) != n or len(self.accel_m_s2) != n:
            raise ValueError("ImuSamples: t_ns, gyro and accel lengths differ")
        if self.temp_c is not None:
            self.temp_c = np.asarray(self.temp_c, dtype=float).reshape(-1)

    def __len__(self) -> int:
        return len(self.t_ns)

    def between(self, t0_ns: int, t1_ns: int) -> "ImuSamples":
        """Samples with ``t0_ns < t <= t1_ns``."""
        i0 = int(np.searchsorted(self.t_ns, t0_ns, side="right"))
        i1 = int(np.searchsorted(self.t_ns, t1_ns, side="right"))
        return self.slice(i0, i1)

    def slice(self, i0: int, i1: int) -> "ImuSamples":
        return ImuSamples(
            self.t_ns[i0:i1], self.gyro_rad_s[i0:i1], self.accel_m_s2[i0:i1],
            None if self.temp_c is None else self.temp_c[i0:i1],
        )

    @staticmethod
    def empty() -> "ImuSamples":
        return ImuSamples(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))

    @staticmethod
    def concat(blocks: list["ImuSamples"]) -> "ImuSamples":
        blocks = [b for b in blocks if len(b)]
        if not blocks:
            return ImuSamples.empty()
        temps = None if any(b.temp_c is None for b in blocks) else np.concatenate([b.temp_c for b in blocks])
        return ImuSamples(
            np.concatenate([b.t_ns for b in blocks]),
            np.concatenate([b.gyro_rad_s for b in blocks]),
            np.concatenate([b.accel_m_s2 for b in blocks]),
            temps,
        )


def median_rate_hz(t_ns: np.ndarray | list[int] | None) -> float | None:
    """Samples per second from the median step of increasing timestamps (ns); None with too few."""
    if t_ns is None or len(t_ns) < 2:
        return None
    d = np.diff(np.asarray(t_ns, dtype=np.int64))
    d = d[d > 0]
    return float(round(1e9 / float(np.median(d)), 3)) if d.size else None
