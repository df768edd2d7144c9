"""One BLAS thread while the on-board estimator works: its matrices are small, and BLAS threads only spin.

NumPy's BLAS (OpenBLAS in the wheels) starts a thread per core for a product that is large enough
and keeps those threads spinning after it.  The estimator's products are a few thousand rows by 6
to 31 columns, where the threads cost CPU and save no time: measured on this project's 2-core
machine, the simulated scan's estimator took 24.5 ms of CPU per frame with BLAS's own threads and
18.0 ms with one (KITTI 06 0-50: 38.1 and 35.5 ms), at the same wall time.

:func:`one_blas_thread` is a context manager that holds BLAS at one thread while any thread of
the process is inside it (a count: the frame loop and the keyframe worker may overlap) and puts
the previous setting back when the last one leaves.  Without ``threadpoolctl`` it does nothing.
"""

from __future__ import annotations

import logging
import threading
from contextlib import contextmanager
from typing import Any, Iterator

log = logging.getLogger(__name__)

_lock = threading.Lock()
_depth = 0
_limiter: Any = None
_controller: Any = None
_unavailable = False


def _get_controller() -> Any:
    global _controller, _unavailable
    if _controller is None and not _unavailable:
        try:
            from threadpoolctl import ThreadpoolController
        except ImportError:
            _unavailable = True
            log.debug("threadpoolctl is not installed: BLAS keeps its own thread count")
            return None
        _controller = ThreadpoolController()
    return _controller


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS at one thread inside the block (and while any other thread is inside one)."""
    global _depth, _limiter
    with _lock:
        if _depth == 0:
            controller = _get_controller()
            _limiter = None if controller is None else controller.limit(limits=1, user_api="blas")
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0 and _limiter is not None:
                _limiter.restore_original_limits()
                _limiter = None
