"""The IMU seam: a source of timestamped samples in SI units, read in blocks.

An :class:`ImuSource` is opened, then :meth:`~ImuSource.read` returns the samples that
arrived since the previous call (possibly none) as :class:`~stereopath.device.core.frames.ImuSamples`;
``gaps`` lists ``(t_last_before_ns, t_first_after_ns)`` of every interruption the
source knows about (FIFO overflow, bus error, re-initialisation).

Backends: the MPU-6050 driver (:mod:`stereopath.device.capture.imu.mpu6050`), a stereo source's own IMU
(depthai), and :class:`OfflineImu` for recorded or simulated sample arrays.
:class:`PollingImuReader` runs a source's ``read`` on its own thread at a fixed period
and buffers the result for a consumer on another thread.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable, Protocol, runtime_checkable

import numpy as np

from stereopath.device.errors import CaptureError
from stereopath.device.core.frames import ImuSamples

log = logging.getLogger(__name__)


@runtime_checkable
class ImuSource(Protocol):
    name: str
    gaps: list[tuple[int, int]]

    def open(self) -> None: ...

    def close(self) -> None: ...

    def read(self) -> ImuSamples: ...


class OfflineImu:
    """Recorded/simulated samples released as playback advances.

    ``advance(t_ns)`` moves the playback time (a replay or simulated source calls it
    with each frame time); ``read`` returns the samples with ``t <= t_ns + lookahead_ns``
    not returned before.  ``finish()`` releases everything (end of the sequence).
    """

    name = "offline-imu"

    def __init__(self, samples: ImuSamples, lookahead_ns: int = 100_000_000) -> None:
        self.samples = samples
        self.lookahead_ns = int(lookahead_ns)
        self.gaps: list[tuple[int, int]] = []
        self._lock = threading.Lock()
        self._horizon: int | None = None
        self._next = 0

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def advance(self, t_ns: int) -> None:
        with self._lock:
            h = int(t_ns) + self.lookahead_ns
            self._horizon = h if self._horizon is None else max(self._horizon, h)

    def finish(self) -> None:
        with self._lock:
            self._horizon = np.iinfo(np.int64).max

    def read(self) -> ImuSamples:
        with self._lock:
            if self._horizon is None:
                return ImuSamples.empty()
            end = int(np.searchsorted(self.samples.t_ns, self._horizon, side="right"))
            i0, self._next = self._next, max(self._next, end)
        return self.samples.slice(i0, self._next)


class PollingImuReader:
    """Calls ``source.read()`` every ``period_s`` on a thread; ``read()`` drains the buffer.

    An exception in the thread (e.g. :class:`CaptureError` from the driver) stops the
    thread and is re-raised by the next :meth:`read`.  ``close`` joins the thread.
    """

    def __init__(self, source: ImuSource, period_s: float, sleep: Callable[[float], None] | None = None) -> None:
        self.source = source
        self.name = f"polling({getattr(source, 'name', 'imu')})"
        self.period_s = float(period_s)
        self._blocks: list[ImuSamples] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    @property
    def gaps(self) -> list[tuple[int, int]]:
        return list(getattr(self.source, "gaps", []))

    def open(self) -> None:
        self.source.open()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="imu-poll", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            try:
                block = self.source.read()
            except BaseException as exc:  # handed to the consumer
                self._error = exc
                return
            if len(block):
                with self._lock:
                    self._blocks.append(block)
            next_t += self.period_s
            delay = next_t - time.monotonic()
            if delay < 0:
                next_t = time.monotonic()
                delay = 0.0
            self._stop.wait(delay)

    def read(self) -> ImuSamples:
        with self._lock:
            blocks, self._blocks = self._blocks, []
        if self._error is not None and not blocks:
            err = self._error
            if isinstance(err, CaptureError):
                raise err
            raise CaptureError(f"IMU reader thread failed: {err!r}") from err
        return ImuSamples.concat(blocks)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            if self._thread.is_alive():
                log.warning("IMU reader thread did not stop within 5 s")
            self._thread = None
        self.source.close()
