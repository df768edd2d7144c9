"""What every recorded sequence offers, whatever its on-disk format.

A sequence (:class:`SequenceBase` subclasses, or anything with the same attributes) has

* ``rig``: the calibrated :class:`stereopath.device.core.rig.Rig`;
* ``t_ns``: (N,) int64 mid-exposure times of the stereo pairs, increasing;
* ``len(seq)`` and ``seq.frame(i) -> StereoFrame`` (decoded on demand, 8-bit grey);
* ``seq.frames(start=0, stop=None, step=1)``: an iterator of frames;
* ``imu``: :class:`stereopath.device.core.frames.ImuSamples` or ``None`` when the sequence has no IMU;
* ``groundtruth``: :class:`stereopath.device.formats.tum.Trajectory` of ``T_world_cam0`` or ``None``;
* ``name`` (short, for logs) and ``spec`` (the ``open_source`` string that reopens it).

An unreadable frame (a corrupt or truncated image file) is skipped by ``frames()`` with a warning
and its index recorded in ``skipped_frames`` (reports count them); set ``strict = True`` to stop
at the first one with its :class:`stereopath.device.errors.DatasetError` instead.  ``frame(i)``
always raises.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Protocol

import numpy as np

from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.core.rig import Rig
from stereopath.device.errors import DatasetError
from stereopath.device.formats.tum import Trajectory

log = logging.getLogger(__name__)


class StereoSequence(Protocol):
    """The sequence interface of the module doc (what :func:`~stereopath.device.formats.source.open_source`
    returns: :class:`SequenceBase` subclasses, the simulator's session).  Recorded sequences also have
    ``strict`` and ``skipped_frames`` (:class:`SequenceBase`); a rendered one never skips a frame."""

    name: str
    spec: str
    rig: Rig
    t_ns: np.ndarray

    def __len__(self) -> int: ...

    def frame(self, i: int) -> StereoFrame: ...

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[StereoFrame]: ...

    @property
    def imu(self) -> ImuSamples | None: ...

    @property
    def groundtruth(self) -> Trajectory | None: ...


class SequenceBase:
    """Shared behaviour: length, bounds checks, iteration; subclasses implement ``_load``."""

    name: str = "sequence"
    spec: str = ""
    strict: bool = False  # True: an unreadable frame stops frames() instead of being skipped

    def __init__(self, rig: Rig, t_ns: np.ndarray) -> None:
        self.rig = rig
        self.t_ns = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        self.skipped_frames: list[int] = []

    def __len__(self) -> int:
        return len(self.t_ns)

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}: {len(self)} stereo frames>"

    def frame(self, i: int) -> StereoFrame:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"{self.name}: frame {i} out of range (0..{n - 1})")
        return self._load(i % n)

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[StereoFrame]:
        for i in range(*slice(start, stop, step).indices(len(self))):
            try:
                frame = self._load(i)
            except DatasetError as exc:
                if self.strict:
                    raise DatasetError(f"{exc} (frame {i}; drop --strict to skip unreadable frames)") from None
                if i not in self.skipped_frames:
                    self.skipped_frames.append(i)
                log.warning("%s: skipping unreadable frame %d: %s", self.name, i, exc)
                continue
            yield frame

    def __iter__(self) -> Iterator[StereoFrame]:
        return self.frames()

    def _load(self, i: int) -> StereoFrame:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def imu(self) -> ImuSamples | None:
        return None

    @property
    def groundtruth(self) -> Trajectory | None:
        return None
