"""What a reprocessing stage holds in memory: the process's resident set and the size of named structures.

:class:`MemoryLedger` is handed to every stage (``StageInputs.memory``); a stage notes the bytes of the
structures it holds (``note("keypoints_descriptors", nbytes)``, the largest value kept), and the
runner records them with the stage's peak resident set in ``OUT/stages/manifest.json``
(``benchmarks/bench_scale.py`` prints them).  The peak is the kernel's high-water mark of the
process (``VmHWM``), reset at each stage start where Linux allows it (``/proc/self/clear_refs``), so
each stage's figure is its own; elsewhere it is the process's peak so far.  The ledger also sums the
CPU time of a stage's named steps (``with ledger.timed("loops"): ...``), recorded beside the stage's
total (``cpu_steps``), so the part of a stage that grows with the session's length can be seen.
"""

from __future__ import annotations

import contextlib
import dataclasses
import resource
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

_STATUS = Path("/proc/self/status")
_CLEAR_REFS = Path("/proc/self/clear_refs")
MB = 1024.0 * 1024.0


def _status_kb(key: str) -> float | None:
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith(key + ":"):
                return float(line.split()[1])
    except OSError:
        return None
    return None


def rss_mb() -> float:
    """The resident set now (MB); the peak so far where /proc is missing."""
    kb = _status_kb("VmRSS")
    return kb / 1024.0 if kb is not None else peak_rss_mb()


def peak_rss_mb() -> float:
    """The resident set's high-water mark (MB) since the last :func:`reset_peak` (or the process start)."""
    kb = _status_kb("VmHWM")
    if kb is None:
        kb = float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
        if sys.platform == "darwin":  # bytes there
            kb /= 1024.0
    return kb / 1024.0


def process_cpu_s() -> float:
    """CPU seconds of this process so far: user + system, every thread."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def reset_peak() -> bool:
    """Start a new high-water mark at the current resident set (Linux); False where not possible."""
    try:
        _CLEAR_REFS.write_text("5")
        return True
    except OSError:
        return False


def release_freed() -> None:
    """Hand the memory freed by the last stage back to the system (glibc keeps freed heap pages for
    reuse, so the next stage would otherwise start from the last one's peak); nothing elsewhere."""
    import ctypes
    import gc

    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


# glibc's mallopt parameters
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
HEAP_ARRAYS_MB = 32  # arrays up to this size come from the heap (glibc's largest allowed threshold) ...
HEAP_KEEP_MB = 256  # ... and up to this much freed memory at its top is kept for the next ones


def reuse_freed_heap() -> bool:
    """Serve the stages' many large temporary arrays from the heap and keep what they free for the next
    ones (glibc ``mallopt``); False where not possible.

    By default glibc maps each array above 128 kB on its own and unmaps it when freed, and trims the
    heap's top as soon as it is freed, so every new temporary faults its pages in again: the kernel
    zeroes them (system time; figures in CHANGELOG).  The memory a stage
    freed is still handed back between stages and bundle-adjustment windows (:func:`release_freed`)."""
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, HEAP_ARRAYS_MB << 20)) and bool(
            libc.mallopt(_M_TRIM_THRESHOLD, HEAP_KEEP_MB << 20))
    except (OSError, AttributeError):
        return False


def nbytes(obj: object, _depth: int = 0) -> int:
    """Bytes held by ``obj``: NumPy arrays' buffers plus the containers (dicts, lists, tuples, sets and
    dataclasses) around them, followed a few levels deep."""
    if isinstance(obj, np.ndarray):
        return int(obj.nbytes)
    if _depth > 4:
        return sys.getsizeof(obj)
    if isinstance(obj, dict):
        return sys.getsizeof(obj) + sum(nbytes(k, _depth + 1) + nbytes(v, _depth + 1) for k, v in obj.items())
    if isinstance(obj, (list, tuple, set, frozenset)):
        return sys.getsizeof(obj) + sum(nbytes(v, _depth + 1) for v in obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return sys.getsizeof(obj) + sum(nbytes(getattr(obj, f.name), _depth + 1) for f in dataclasses.fields(obj))
    return sys.getsizeof(obj)


@dataclass
class MemoryLedger:
    """The sizes (bytes) of the structures one stage holds, the largest seen of each, and the CPU time
    of its named steps."""

    held: dict[str, int] = field(default_factory=dict)
    start_mb: float | None = None  # the resident set the stage started from (after the last one's was freed)
    cpu_steps: dict[str, float] = field(default_factory=dict)  # CPU seconds of the stage's named steps

    @contextlib.contextmanager
    def timed(self, step: str):
        """Add the process's CPU time (every thread) over the ``with`` block to step ``step`` (work a
        spreader hands to other processes, a fleet's Ray tasks, is not in it)."""
        c0 = process_cpu_s()
        try:
            yield
        finally:
            self.cpu_steps[step] = self.cpu_steps.get(step, 0.0) + process_cpu_s() - c0

    def note(self, name: str, size_bytes: int) -> None:
        self.held[name] = max(int(size_bytes), self.held.get(name, 0))

    def start(self) -> None:
        """A new stage: forget the structures of the last one, return what it freed, restart the peak."""
        self.held.clear()
        self.cpu_steps.clear()
        release_freed()
        reset_peak()
        self.start_mb = rss_mb()

    def summary(self) -> dict[str, float]:
        """``start_rss_mb`` (when started), ``peak_rss_mb``, ``rss_mb`` and each structure's MB (for the stage
        manifest)."""
        out = {"peak_rss_mb": round(peak_rss_mb(), 1), "rss_mb": round(rss_mb(), 1)}
        if self.start_mb is not None:
            out["start_rss_mb"] = round(self.start_mb, 1)
        out.update({f"{k}_mb": round(v / MB, 1) for k, v in sorted(self.held.items())})
        return out
