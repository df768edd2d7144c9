"""One BLAS thread in the processes that run the on-board path.

The on-board estimator's linear algebra works on small matrices (a few hundred rows at most):
OpenBLAS and MKL threads cost more in start-up and synchronisation than they save there, and
on a small machine they compete with the estimator's own threads (the keyframe worker, OpenCV)
for the same cores.  The device process therefore runs its BLAS at one thread.

BLAS libraries read their thread count once, when they are loaded (the first ``import numpy``),
so :func:`use_one_blas_thread` must run before anything imports numpy: the ``stereopath`` entry
point calls it for the commands of the device path (:data:`DEVICE_PATH_COMMANDS`) before it
builds its parser, and the benchmarks of the on-board path call it first thing.  The host
commands keep the library defaults (dense mapping and reprocessing limit their own stages).
When numpy is already loaded (a caller that imported it first), the limit is applied through
``threadpoolctl`` if it is installed.

Nothing here imports numpy.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Sequence

log = logging.getLogger(__name__)

# the environment variables OpenBLAS, OpenMP (and BLAS built on it) and MKL read when loaded
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")

# commands (as the words after ``stereopath``) that run the on-board path
DEVICE_PATH_COMMANDS: tuple[tuple[str, ...], ...] = (("odometry",), ("sim",), ("device", "run"))


def command_words(argv: Sequence[str]) -> tuple[str, ...]:
    """The command words of a ``stereopath`` command line: its arguments up to the first option."""
    words = []
    for arg in argv:
        if arg.startswith("-"):
            if words:
                break
            continue  # global options before the command (-v, -q)
        words.append(arg)
    return tuple(words)


def runs_device_path(argv: Sequence[str]) -> bool:
    """True when the command line ``argv`` (without the program name) names a device-path command."""
    words = command_words(argv)
    return any(words[: len(cmd)] == cmd for cmd in DEVICE_PATH_COMMANDS)


def use_one_blas_thread() -> str:
    """Run BLAS at one thread in this process; returns how: ``"environment"`` (numpy not loaded yet),
    ``"threadpoolctl"`` (numpy loaded, limited at run time) or ``"unchanged"`` (numpy loaded and
    threadpoolctl not installed: the library keeps the thread count it started with)."""
    for name in BLAS_THREAD_VARIABLES:
        os.environ[name] = "1"
    if "numpy" not in sys.modules:
        return "environment"
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        log.debug("numpy was loaded before the BLAS thread count was set and threadpoolctl is not installed")
        return "unchanged"
    threadpool_limits(limits=1, user_api="blas")
    return "threadpoolctl"
