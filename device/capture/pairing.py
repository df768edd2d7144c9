"""Thread-safe pairing of left/right frames by sensor timestamp.

Each camera delivers its frames in order on its own thread.  :meth:`FramePairer.push`
appends a frame to that camera's bounded queue and matches the two queue heads:

* heads within ``tolerance_ns`` of each other form a pair;
* otherwise the older head can never be matched any more (its partner would have to be
  older than the other camera's head, and frames arrive in order), so it is dropped
  and counted as ``dropped_unpaired``.

With a tolerance below half the frame period a frame can only ever pair with the
partner of its own exposure: pairing never crosses frames.  Pairs wait in a bounded
output queue; when the consumer is slower than the cameras the oldest pair is dropped
(``dropped_overflow``), so capture threads never block.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any, Callable

LEFT, RIGHT = 0, 1
SIDE_NAMES = ("left", "right")


class FramePairer:
    """Pairs frames from two producer threads; one consumer takes pairs with :meth:`get`."""

    def __init__(self, tolerance_ns: int, count: Callable[..., None], maxlen: int = 8,
                 out_maxlen: int = 4, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        if tolerance_ns <= 0:
            raise ValueError("tolerance_ns must be positive")
        self.tolerance_ns = int(tolerance_ns)
        self._count = count
        self._maxlen = int(maxlen)
        self._out_maxlen = int(out_maxlen)
        self._clock_ns = clock_ns
        self._cond = threading.Condition()
        self._queues: tuple[collections.deque, collections.deque] = (collections.deque(), collections.deque())
        self._out: collections.deque = collections.deque()
        self._closed = False
        self.last_arrival_ns: list[int | None] = [None, None]
        self.last_pair_ns: int | None = None
        self.last_skew_ns: int = 0

    def push(self, side: int, key_ns: int, item: object) -> None:
        """Called from a camera thread: add one frame (``key_ns`` = its sensor timestamp)."""
        with self._cond:
            if self._closed:
                return
            self.last_arrival_ns[side] = self._clock_ns()
            q = self._queues[side]
            if q and key_ns <= q[-1][0]:
                # out of order or repeated: cannot be paired safely
                self._count(dropped_unpaired=1)
                return
            if len(q) >= self._maxlen:
                q.popleft()
                self._count(dropped_overflow=1)
            q.append((int(key_ns), item))
            self._match()

    def _match(self) -> None:
        left, right = self._queues
        made = False
        while left and right:
            dt = left[0][0] - right[0][0]
            self.last_skew_ns = abs(dt)
            if abs(dt) <= self.tolerance_ns:
                l_item, r_item = left.popleft()[1], right.popleft()[1]
                if len(self._out) >= self._out_maxlen:
                    self._out.popleft()
                    self._count(dropped_overflow=2)
                self._out.append((l_item, r_item, abs(dt)))
                self.last_pair_ns = self._clock_ns()
                self._count(paired=1)
                made = True
            elif dt < 0:
                left.popleft()
                self._count(dropped_unpaired=1)
            else:
                right.popleft()
                self._count(dropped_unpaired=1)
        if made:
            self._cond.notify_all()

    def get(self, timeout_s: float) -> tuple[Any, Any, int] | None:
        """Oldest waiting pair ``(left_item, right_item, skew_ns)``, or None after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._out:
                if self._closed:
                    return None
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)
            return self._out.popleft()

    def wake(self) -> None:
        """Wake a waiting consumer (e.g. after a callback recorded an error)."""
        with self._cond:
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._queues[0].clear()
            self._queues[1].clear()
            self._out.clear()
            self._cond.notify_all()

    def pending(self) -> tuple[int, int, int]:
        """Frames waiting on the left, on the right, and pairs waiting for the consumer."""
        with self._cond:
            return len(self._queues[0]), len(self._queues[1]), len(self._out)
