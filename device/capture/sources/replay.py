"""Replay of a recorded sequence (our ASL sessions, EuRoC, KITTI) as a stereo source.

The sequence comes from :func:`stereopath.device.formats.open_source` (``session:DIR``,
``euroc:DIR``, ``kitti:DIR``) or is passed in directly: anything with ``rig``, ``t_ns``,
``len()``, ``frame(i) -> StereoFrame`` and ``imu`` (``ImuSamples`` or ``None``).
Frames keep their recorded ``t_ns``.  At ``speed = "recorded"`` each frame is held back
until its recorded time has elapsed since the first one (on the injected clock); at
``"max"`` frames come as fast as they are decoded.  The recorded IMU is exposed as
``source.imu`` (an :class:`~stereopath.device.capture.imu.base.OfflineImu` released up to the latest frame
time plus a look-ahead, as a live IMU would have delivered it).
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Callable, Iterator, Sequence

from stereopath.device.errors import CalibrationError, CaptureError, DatasetError
from stereopath.device.core.frames import StereoFrame
from stereopath.device.capture.imu.base import OfflineImu
from stereopath.device.settings import ReplaySettings, SimSettings
from stereopath.device.capture.sources.base import SourceBase, load_rig_override

if TYPE_CHECKING:
    import numpy as np

    from stereopath.device.formats.sequence import StereoSequence

log = logging.getLogger(__name__)


def paced(times_ns: Sequence[int] | np.ndarray, clock_ns: Callable[[], int], sleep: Callable[[float], None]) -> Callable[[int], None]:
    """A function that waits until recorded time ``t`` (relative to the first call) is due."""
    state: dict[str, int] = {}

    def wait_for(t_ns: int) -> None:
        if "t0" not in state:
            state["t0"], state["h0"] = int(t_ns), clock_ns()
            return
        due = state["h0"] + (int(t_ns) - state["t0"])
        delay = (due - clock_ns()) / 1e9
        if delay > 0:
            sleep(delay)

    return wait_for


class SequenceSource(SourceBase):
    """A sequence (``rig``, ``t_ns``, ``len()``, ``frame(i)``, ``imu``) played as a stereo source.

    The one frame loop of the replay and simulator sources: subclasses say where the sequence
    comes from (:meth:`_load`), which frames to play (:meth:`_span`) and how to pace them (:meth:`_pacer`).
    """

    name = "sequence"

    def __init__(self, settings: ReplaySettings | SimSettings, sequence: StereoSequence | None = None, rig_file: str = "",
                 clock_ns: Callable[[], int] = time.monotonic_ns, sleep: Callable[[float], None] = time.sleep,
                 imu_lookahead_ns: int = 100_000_000) -> None:
        """``settings``: the subclass's section of ``[source]``; ``sequence``: an already opened one (tests)."""
        super().__init__()
        self.settings = settings
        self._seq_arg = sequence
        self._rig_file = rig_file
        self._clock_ns = clock_ns
        self._sleep = sleep
        self._lookahead = imu_lookahead_ns
        self.sequence: StereoSequence | None = None

    def _load(self) -> StereoSequence:
        raise NotImplementedError

    def _span(self) -> tuple[int, int]:
        return 0, len(self.sequence)

    def _pacer(self) -> Callable[[int, int], None] | None:
        """``wait(i, t_ns)`` before frame ``i`` is delivered, or None for as fast as read."""
        return None

    def _open(self) -> None:
        seq = self._seq_arg if self._seq_arg is not None else self._load()
        self.sequence = seq
        calib = load_rig_override(self._rig_file)
        if calib is not None:
            if calib.has_views:  # recorded images are pinhole already (a session) or read through their own lens model
                raise CalibrationError(f"{calib.source}: a fisheye calibration cannot be replayed over recorded images: "
                                       f"a session holds them as pinhole views already, and a fisheye dataset is read "
                                       f"through its own calibration (sensor.yaml or a Kalibr camchain beside mav0)")
            own = getattr(seq, "rig", None)  # the recorded images' size (the sequence's own calibration)
            self._use_rig_file(calib, None if own is None else tuple(own.cam0.size))
        else:
            self._rig = seq.rig
        imu = getattr(seq, "imu", None)
        self._imu = OfflineImu(imu, self._lookahead) if imu is not None and len(imu) else None

    def _frames(self) -> Iterator[StereoFrame]:
        seq = self.sequence
        start, stop = self._span()
        wait = self._pacer()
        for out_seq, i in enumerate(range(start, stop)):
            if not self._opened:
                return
            t = int(seq.t_ns[i])
            if wait is not None:
                wait(i, t)
            try:
                frame = seq.frame(i)
            except DatasetError as exc:
                if getattr(seq, "strict", False):
                    raise CaptureError(f"replay source: {exc}") from None
                log.warning("replay: skipping unreadable frame %d: %s", i, exc)
                self._count(dropped_sensor=1)  # a frame the recording lost, as a sensor gap would be
                continue
            self._count(frames_left=1, frames_right=1, paired=1, delivered=1)
            if self._imu is not None:
                self._imu.advance(t)
            meta = dict(frame.meta)
            meta.setdefault("source", self.name)
            meta["index"] = i
            yield StereoFrame(seq=out_seq, t_ns=t, left=frame.left, right=frame.right, meta=meta)
        if self._imu is not None and stop == len(seq):
            self._imu.finish()  # end of the recording: the IMU tail is available too

    def _close(self) -> None:
        close = getattr(self.sequence, "close", None)
        if callable(close) and self._seq_arg is None:
            close()


class ReplaySource(SequenceSource):
    """Frames of a recorded sequence (see module doc)."""

    name = "replay"
    settings: ReplaySettings

    def _load(self) -> StereoSequence:
        if not self.settings.path:
            raise CaptureError("replay source: no sequence configured (source.replay.path, e.g. 'euroc:DIR')")
        from stereopath.device.formats import open_source

        try:
            return open_source(self.settings.path)
        except DatasetError as exc:
            raise CaptureError(f"replay source: {exc}") from None

    def _open(self) -> None:
        super()._open()
        seq = self.sequence
        n = len(seq)
        if n == 0:
            raise CaptureError(f"replay source: {getattr(seq, 'name', 'sequence')} has no frames")
        if self.settings.start >= n:
            raise CaptureError(f"replay source: start frame {self.settings.start} beyond the last frame ({n - 1})")
        self.name = f"replay:{getattr(seq, 'name', 'sequence')}"

    def _span(self) -> tuple[int, int]:
        s, n = self.settings, len(self.sequence)
        return s.start, n if s.count == 0 else min(n, s.start + s.count)

    def _pacer(self) -> Callable[[int, int], None] | None:
        if self.settings.speed != "recorded":
            return None
        wait = paced([], self._clock_ns, self._sleep)
        return lambda _i, t_ns: wait(t_ns)
