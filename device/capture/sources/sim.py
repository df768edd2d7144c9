"""The simulator as a stereo source.

Wraps a simulated session (``stereopath.device.sim.session.open_sim(SimConfig(frames=, seed=))``:
``rig``, ``t_ns``, ``render(i) -> StereoFrame``, ``imu``, ``imu_truth``,
``groundtruth``).  Frames are rendered on demand, in order; with ``rate_hz > 0`` they
are paced at that rate on the injected clock (otherwise as fast as rendered).  The
simulated IMU is exposed as ``source.imu`` (an :class:`~stereopath.device.capture.imu.base.OfflineImu`).
``source.session`` gives the session itself (ground truth, IMU truth).
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable, Iterator

from stereopath.device.core.frames import StereoFrame
from stereopath.device.capture.imu.base import OfflineImu
from stereopath.device.service.settings import SimSettings
from stereopath.device.capture.sources.base import SourceBase, load_rig_override

log = logging.getLogger(__name__)


def open_sim_session(settings: SimSettings) -> Any:
    """The simulated session of ``[source.sim]``, through the one source-spec opener."""
    from stereopath.device.formats.source import open_source

    return open_source("sim", frames=settings.frames, seed=settings.seed)


class SimSource(SourceBase):
    """Frames rendered by the simulator (see module doc)."""

    name = "sim"

    def __init__(self, settings: SimSettings, session: Any = None, rig_file: str = "",
                 clock_ns: Callable[[], int] = time.monotonic_ns, sleep: Callable[[float], None] = time.sleep,
                 imu_lookahead_ns: int = 100_000_000) -> None:
        super().__init__()
        self.settings = settings
        self._session_arg = session
        self._rig_file = rig_file
        self._clock_ns = clock_ns
        self._sleep = sleep
        self._lookahead = imu_lookahead_ns
        self.session: Any = None

    def _open(self) -> None:
        self.session = self._session_arg if self._session_arg is not None else open_sim_session(self.settings)
        self._rig = load_rig_override(self._rig_file) or self.session.rig
        imu = getattr(self.session, "imu", None)
        self._imu = OfflineImu(imu, self._lookahead) if imu is not None and len(imu) else None

    def _frames(self) -> Iterator[StereoFrame]:
        sess = self.session
        n = len(sess.t_ns)
        period_ns = int(1e9 / self.settings.rate_hz) if self.settings.rate_hz > 0 else 0
        start = self._clock_ns()
        for i in range(n):
            if not self._opened:
                return
            if period_ns:
                delay = (start + i * period_ns - self._clock_ns()) / 1e9
                if delay > 0:
                    self._sleep(delay)
            frame = sess.render(i)
            self._count(frames_left=1, frames_right=1, paired=1, delivered=1)
            if self._imu is not None:
                self._imu.advance(int(frame.t_ns))
            frame.meta.setdefault("source", self.name)
            yield frame
        if self._imu is not None:
            self._imu.finish()

    def _close(self) -> None:
        pass
