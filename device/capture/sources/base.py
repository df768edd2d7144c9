"""The stereo source seam: one small protocol, shared statistics and a base class.

A :class:`StereoSource` is opened (``open()`` or ``with``), iterated for
:class:`~stereopath.device.core.frames.StereoFrame` objects and closed.  Every frame's ``t_ns`` is
the mid-exposure instant on one monotonic clock (CLOCK_MONOTONIC on the device,
the recording's clock on replay).  ``rig`` is the calibrated rig (available once
opened), ``imu`` the source's own inertial stream (an :class:`stereopath.device.capture.imu.ImuSource`)
or ``None``, and ``stats`` the counters below.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterator, Protocol, runtime_checkable

from stereopath.device.errors import CalibrationError, CaptureError
from stereopath.device.core.frames import StereoFrame
from stereopath.device.core.rig import Rig

if TYPE_CHECKING:
    from stereopath.device.capture.imu.base import ImuSource
    from stereopath.device.core.fisheye import PinholeView
    from stereopath.device.formats.rig_files import RigCalibration

log = logging.getLogger(__name__)


@dataclass
class SourceStats:
    """Counters of a stereo source (safe to read at any time; copies via :meth:`snapshot`)."""

    frames_left: int = 0        # frames received from the left camera
    frames_right: int = 0       # frames received from the right camera
    paired: int = 0             # pairs formed
    delivered: int = 0          # pairs handed to the consumer
    dropped_unpaired: int = 0   # frames whose partner never came (lost on the other camera)
    dropped_presync: int = 0    # frames before the cameras reported SyncReady
    dropped_overflow: int = 0   # frames or pairs dropped because a bounded buffer was full
    dropped_sensor: int = 0     # frames the sensor itself skipped (sequence-number gaps)
    dropped_clock: int = 0      # frames of pairs dropped because the frame clock stepped back before them
    clock_steps: int = 0        # steps of the frame clock seen against the frame period (depthai host sync)
    max_skew_ns: int = 0        # largest |t_left - t_right| among delivered pairs
    last_skew_ns: int = 0       # |t_left - t_right| of the latest pair or near-miss

    def snapshot(self) -> "SourceStats":
        return dataclasses.replace(self)

    def as_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)

    def add(self, **increments: int) -> None:
        """Add to the named counters."""
        for key, inc in increments.items():
            setattr(self, key, getattr(self, key) + inc)


@runtime_checkable
class StereoSource(Protocol):
    """What every stereo backend offers."""

    name: str

    def open(self) -> None: ...

    def close(self) -> None: ...

    def __enter__(self) -> "StereoSource": ...

    def __exit__(self, *exc: object) -> None: ...

    def __iter__(self) -> Iterator[StereoFrame]: ...

    @property
    def rig(self) -> Rig | None: ...

    @property
    def imu(self) -> ImuSource | None: ...

    @property
    def stats(self) -> SourceStats: ...


class SourceBase:
    """Common lifecycle: idempotent open/close, context manager, stats under a lock."""

    name = "source"

    def __init__(self) -> None:
        self._stats = SourceStats()
        self._stats_lock = threading.Lock()
        self._opened = False
        self._rig: Rig | None = None
        self._imu: ImuSource | None = None
        self._views: tuple[PinholeView | None, PinholeView | None] = (None, None)  # fisheye cameras: the pinhole views frames go through

    # lifecycle -------------------------------------------------------------------------
    def open(self) -> None:
        if self._opened:
            return
        self._open()
        self._opened = True
        log.info("%s source opened", self.name)

    def close(self) -> None:
        if not self._opened:
            return
        self._opened = False
        try:
            self._close()
        finally:
            log.info("%s source closed: %s", self.name, self._stats.as_dict())

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __iter__(self) -> Iterator[StereoFrame]:
        if not self._opened:
            raise CaptureError(f"{self.name} source: iterate only after open() (or use 'with')")
        if self._views[0] is None and self._views[1] is None:
            return self._frames()
        return self._through_views(self._frames())

    def _use_rig_file(self, calib: RigCalibration, size: tuple[int, int] | None = None) -> None:
        """Take a loaded rig file (:func:`load_rig_override`): its pinhole rig and its cameras' views,
        refusing (:class:`CalibrationError`) a camera calibrated for another image ``size`` than the
        source delivers (a fisheye camera's own size, or a pinhole camera's ``image_size``): its
        intrinsics would not fit the images, and a session recorded with it could not be read back."""
        cams = (calib.rig.cam0, calib.rig.cam1)
        for name, view, cam in zip(("cam0", "cam1"), calib.views, cams):
            calibrated = tuple(int(v) for v in (cam.size if view is None else view.source.size))
            if size is not None and calibrated != tuple(size):
                raise CalibrationError(f"{calib.source}: {name} is calibrated at {calibrated[0]}x{calibrated[1]} "
                                       f"but the {self.name} source delivers {size[0]}x{size[1]}")
        self._rig = calib.rig
        self._views = calib.views

    def _through_views(self, frames: Iterator[StereoFrame]) -> Iterator[StereoFrame]:
        """The frames as the rig sees them: each fisheye camera's image through its pinhole view."""
        v0, v1 = self._views  # their image size was checked against the source's at open (_use_rig_file)
        for f in frames:
            yield dataclasses.replace(f, left=f.left if v0 is None else v0.apply(f.left),
                                      right=f.right if v1 is None else v1.apply(f.right))

    # properties ------------------------------------------------------------------------
    @property
    def rig(self) -> Rig | None:
        return self._rig

    @property
    def imu(self) -> ImuSource | None:
        return self._imu

    @property
    def stats(self) -> SourceStats:
        with self._stats_lock:
            return self._stats.snapshot()

    def _count(self, **increments: int) -> None:
        with self._stats_lock:
            self._stats.add(**increments)

    # to implement ----------------------------------------------------------------------
    def _open(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError

    def _frames(self) -> Iterator[StereoFrame]:
        raise NotImplementedError


def load_rig_override(path: str) -> RigCalibration | None:
    """The configured rig file (:class:`~stereopath.device.formats.rig_files.RigCalibration`: our rig
    YAML, or a Kalibr camchain whose fisheye cameras come with their pinhole views), or None when
    ``path`` is empty."""
    if not path:
        return None
    from stereopath.device.formats.rig_files import load_rig_file

    return load_rig_file(path)
