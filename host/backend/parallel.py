"""How a stage runs independent pieces of its work: in order in this thread, or spread by the caller.

A stage calls :func:`parallel_map` for work whose pieces do not depend on each other (the tracks
stage: each keyframe's stereo keypoints; the matching of each keyframe gap).  By default the
pieces run one after another here, exactly as a plain loop would.  A caller that has idle
processors can install a spreader for the duration of a call with :func:`spread_with` (a fleet
task spreads the pieces as Ray tasks, so that a long session uses the cores other sessions have
left free).  The results always come back in the order of ``items`` and are joined by the stage
in that order, so the stage's output does not depend on where or in which order the pieces ran.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any

Spreader = Callable[[Callable[[Any, Any], Any], Any, Sequence[Any]], Sequence[Any]]

_SPREADER: ContextVar[Spreader | None] = ContextVar("stereopath_reprocess_spreader", default=None)


def parallel_map(fn: Callable[[Any, Any], Any], shared: Any, items: Sequence[Any]) -> list[Any]:
    """``[fn(shared, item) for item in items]``, possibly computed elsewhere (see the module doc).

    ``fn`` must be a module-level function (a spreader sends it to other processes by name) that
    depends on nothing but its arguments; ``shared`` is what every piece reads (sent once),
    ``items`` what differs between them.
    """
    spread = _SPREADER.get()
    if spread is None or len(items) < 2:
        return [fn(shared, item) for item in items]
    out = list(spread(fn, shared, items))
    if len(out) != len(items):
        raise RuntimeError(f"spreader returned {len(out)} results for {len(items)} pieces")
    return out


def spreading() -> bool:
    """Whether a spreader is installed (work guessed ahead in parallel only pays where pieces can spread)."""
    return _SPREADER.get() is not None


def spare_cores() -> bool:
    """Whether pieces handed to the installed spreader would run on idle processors now: a spreader
    with an ``idle()`` method answers for itself (a fleet task asks Ray), one without is assumed to
    have them, and without a spreader there are none.  Work that is only worth doing in parallel
    (guessing ahead) asks this before each batch, so that it is not done while every core is busy."""
    spread = _SPREADER.get()
    if spread is None:
        return False
    idle = getattr(spread, "idle", None)
    return True if idle is None else bool(idle())


@contextmanager
def spread_with(spreader: Spreader | None) -> Iterator[None]:
    """Within the block, :func:`parallel_map` hands its pieces to ``spreader(fn, shared, items)``
    (which must return the results in the order of ``items``); None runs them here."""
    token = _SPREADER.set(spreader)
    try:
        yield
    finally:
        _SPREADER.reset(token)


@contextmanager
def opencv_threads(n: int) -> Iterator[None]:
    """OpenCV's thread pool at ``n`` threads within the block, as it was after it.  The setting is the
    process's: for a block that runs OpenCV calls side by side on threads of its own."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(n)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


class ThreadSpreader:
    """A spreader for one process: the pieces of a call run on ``workers`` threads, OpenCV's own pool at
    one thread meanwhile (as it was after).  For pieces whose work is OpenCV and NumPy calls that release
    the GIL (the map stage's depth maps, the frames between keyframes, parts of a keyframe's keypoints:
    side by side they cost less CPU and time than one at a time with OpenCV splitting each).  Its
    :meth:`idle` says no: nothing is guessed ahead for it."""

    def __init__(self, workers: int) -> None:
        self.workers = max(1, int(workers))

    def idle(self) -> bool:
        return False

    def __call__(self, fn: Callable[[Any, Any], Any], shared: Any, items: Sequence[Any]) -> list[Any]:
        from concurrent.futures import ThreadPoolExecutor

        if self.workers == 1 or len(items) < 2:  # nothing side by side: OpenCV's pool left as it is
            return [fn(shared, item) for item in items]
        with opencv_threads(1), ThreadPoolExecutor(min(self.workers, len(items))) as pool:
            return list(pool.map(lambda item: fn(shared, item), items))


def local_spreader() -> ThreadSpreader | None:
    """A :class:`ThreadSpreader` over the cores OpenCV may use here; None on one core, or when a
    spreader is installed already (a fleet task's, which spreads over Ray)."""
    import cv2

    if _SPREADER.get() is not None or cv2.getNumThreads() < 2:
        return None
    return ThreadSpreader(cv2.getNumThreads())
