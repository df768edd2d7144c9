"""The simulator as a stereo source.

Wraps a simulated session (``stereopath.device.sim.session.open_sim(SimConfig(frames=, seed=))``:
``rig``, ``t_ns``, ``frame(i) -> StereoFrame``, ``imu``, ``imu_truth``,
``groundtruth``), played by the replay source's frame loop (:class:`~stereopath.device.capture.sources.replay.SequenceSource`).
Frames are rendered on demand, in order; with ``rate_hz > 0`` they
are paced at that rate on the injected clock (otherwise as fast as rendered).  The
simulated IMU is exposed as ``source.imu`` (an :class:`~stereopath.device.capture.imu.base.OfflineImu`).
``source.session`` gives the session itself (ground truth, IMU truth).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Callable

from stereopath.device.capture.sources.replay import SequenceSource
from stereopath.device.settings import SimSettings

if TYPE_CHECKING:
    from stereopath.device.formats.sequence import StereoSequence

log = logging.getLogger(__name__)


def open_sim_session(settings: SimSettings) -> StereoSequence:
    """The simulated session of ``[source.sim]``, through the one source-spec opener."""
    from stereopath.device.formats.source import open_source

    return open_source("sim", frames=settings.frames, seed=settings.seed)


class SimSource(SequenceSource):
    """Frames rendered by the simulator (see module doc)."""

    name = "sim"
    settings: SimSettings

    @property
    def session(self) -> StereoSequence | None:
        """The simulated session itself (ground truth, IMU truth); None before :meth:`open`."""
        return self.sequence

    def _load(self) -> StereoSequence:
        return open_sim_session(self.settings)

    def _pacer(self) -> Callable[[int, int], None] | None:
        if self.settings.rate_hz <= 0:
            return None
        period_ns = int(1e9 / self.settings.rate_hz)
        start = self._clock_ns()

        def wait(i: int, _t_ns: int) -> None:
            delay = (start + i * period_ns - self._clock_ns()) / 1e9
            if delay > 0:
                self._sleep(delay)

        return wait
