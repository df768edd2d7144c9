"""Sample timestamps for a clockless FIFO: a running lower-envelope fit of host time vs sample index.

The MPU-6050 stamps nothing.  Each poll tells us that the newest sample in the FIFO,
cumulative index ``i``, was produced no later than the host time ``t`` at which the
FIFO count was read: ``t >= a + T * i`` for the true line ``a + T * i`` (start time
``a``, period ``T``).  Bus latency and the poll's phase relative to the sample clock only
ever push observations *up*, so the line is found as the **lower envelope** of the
observations: among the edges of their lower convex hull, the one spanning the mean
index (the support line that minimises the mean residual subject to staying below every
point).  Its slope is the period estimate; the nominal period is only a prior, used
until the observations span ``min_span`` samples, and a clamp (``max_rel_dev``).  The
MPU clock drifts about 1 % with temperature, so observations older than ``window_ns``
are forgotten.

After a FIFO reset (overflow, bus error) the index restarts in a new segment: the
period estimate is kept, the offset is fitted anew.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class FitState:
    period_ns: float
    offset_ns: float     # time of segment index 0
    n_obs: int
    from_hull: bool


def _cross(o: tuple[int, int], a: tuple[int, int], b: tuple[int, int]) -> int:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


class PeriodFit:
    """Running lower-envelope fit ``t(i) = offset + period * i`` (see module doc)."""

    def __init__(self, nominal_period_ns: float, window_ns: int = 20_000_000_000, min_span: int = 200,
                 max_rel_dev: float = 0.05) -> None:
        if nominal_period_ns <= 0:
            raise ValueError("nominal_period_ns must be positive")
        self.nominal_period_ns = float(nominal_period_ns)
        self.window_ns = int(window_ns)
        self.min_span = int(min_span)
        self.max_rel_dev = float(max_rel_dev)
        self.period_ns = float(nominal_period_ns)
        self._period_known = False
        self.restart()

    def restart(self) -> None:
        """Start a new segment (index 0 again); keep the period estimate."""
        self._pts: list[tuple[int, int]] = []   # (index, t_ns - t_ref), all in the window
        self._hull: list[tuple[int, int]] = []  # lower hull of _pts
        self._t_ref: int | None = None
        self._sum_x = 0
        self._offset_rel = 0.0
        self._from_hull = False

    # ------------------------------------------------------------------------------
    def add(self, index: int, t_ns: int) -> None:
        """Sample ``index`` of this segment existed at host time ``t_ns`` (an upper bound)."""
        if self._t_ref is None:
            self._t_ref = int(t_ns)
        p = (int(index), int(t_ns) - self._t_ref)
        if self._pts and p[0] <= self._pts[-1][0]:
            return  # no new sample since the last observation: a looser bound, nothing to learn
        self._pts.append(p)
        self._sum_x += p[0]
        self._push_hull(p)
        # forget old observations in chunks (amortised rebuild)
        if self._pts[-1][1] - self._pts[0][1] > 1.5 * self.window_ns:
            cut = self._pts[-1][1] - self.window_ns
            self._pts = [q for q in self._pts if q[1] >= cut]
            self._sum_x = sum(q[0] for q in self._pts)
            self._rebuild()
        self._refit()

    def _push_hull(self, p: tuple[int, int]) -> None:
        h = self._hull
        while len(h) >= 2 and _cross(h[-2], h[-1], p) <= 0:
            h.pop()
        h.append(p)

    def _rebuild(self) -> None:
        self._hull = []
        for q in self._pts:
            self._push_hull(q)

    def _refit(self) -> None:
        pts, hull = self._pts, self._hull
        span = pts[-1][0] - pts[0][0]
        slope = self.period_ns
        self._from_hull = False
        if len(hull) >= 2 and span >= self.min_span:
            xm = self._sum_x / len(pts)
            for a, b in zip(hull[:-1], hull[1:]):
                if a[0] <= xm <= b[0]:
                    slope = (b[1] - a[1]) / (b[0] - a[0])
                    break
            lo = self.nominal_period_ns * (1 - self.max_rel_dev)
            hi = self.nominal_period_ns * (1 + self.max_rel_dev)
            if lo <= slope <= hi:
                self.period_ns = slope
                self._period_known = True
                self._from_hull = True
            else:
                slope = self.period_ns
        # offset: the highest line of this slope that stays below every observation
        self._offset_rel = min(q[1] - slope * q[0] for q in hull)

    # ------------------------------------------------------------------------------
    @property
    def ready(self) -> bool:
        return self._t_ref is not None

    def times_ns(self, indices: np.ndarray) -> np.ndarray:
        """Fitted host times (int64 ns) of segment sample ``indices``."""
        if self._t_ref is None:
            raise ValueError("PeriodFit: no observation yet")
        idx = np.asarray(indices, dtype=float)
        return (self._t_ref + np.round(self._offset_rel + self.period_ns * idx)).astype(np.int64)

    def state(self) -> FitState:
        off = (self._t_ref or 0) + self._offset_rel
        return FitState(self.period_ns, off, len(self._pts), self._from_hull)
