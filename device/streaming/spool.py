"""The device's keyframe spool: one file per keyframe, named by seq, written atomically.

The spool is the part of the session recording the keyframe server resends from: each encoded
keyframe message (exactly the bytes sent on the wire) is written to a temporary file, flushed
(``fsync`` optional), renamed to ``<seq:08d>.kf`` and only then offered to hosts.  Seqs are
contiguous from 0, so the in-memory index is just the count: memory does not grow with the
session.  The live run never deletes them (they are part of the recording); a later run deletes
those it delivers from an earlier session's backlog (:mod:`stereopath.device.streaming.backlog`).

``acked.json`` records the highest seq a host acknowledged contiguously (:meth:`mark_acked`, on
every advance, without fsync: it survives a killed process); a later run offers what lies beyond
it.

Thread model: one writer (:meth:`append`), any number of readers (:meth:`read`) of seqs below
:attr:`count`.

Full disk: the spool keeps ``reserve_bytes`` free (the recorder's reserve) and treats ``ENOSPC``
the same way.  From then on (:attr:`disk_full`) keyframes are held in memory, up to
``max_memory_bytes``, until a host acknowledges them (:meth:`release`): keyframes that reach a
host need no spool space.  Only when that memory is full too is a keyframe refused (counted by
the streamer); :attr:`memory_count` keyframes not yet acknowledged are lost if the device stops.
"""

from __future__ import annotations

import errno
import json
import logging
import re
import shutil
import threading
from collections.abc import Callable
from pathlib import Path

from stereopath.device.errors import DatasetError
from stereopath.device.formats import fileio
from stereopath.device.formats.fileio import is_temp
from stereopath.device.streaming.acks import ContiguousAcks

log = logging.getLogger(__name__)

SUFFIX = ".kf"
ACKED_NAME = "acked.json"
_NAME_RE = re.compile(r"^(\d{8,10})\.kf$")


def read_acked(directory: str | Path) -> int:
    """The highest seq of the spool ``directory`` a host acknowledged (-1: none, or no readable record)."""
    try:
        v = fileio.load_json(Path(directory) / ACKED_NAME).get("acked_seq", -1)
    except (OSError, ValueError, AttributeError):
        return -1
    return v if isinstance(v, int) and not isinstance(v, bool) and v >= -1 else -1


def save_acked(directory: str | Path, seq: int, fsync: bool = False) -> None:
    fileio.write_atomic(Path(directory) / ACKED_NAME, json.dumps({"acked_seq": int(seq)}).encode(), fsync=fsync)


class KeyframeSpool:
    """A directory of keyframe messages ``00000000.kf``, ``00000001.kf``, ...

    Opening an existing directory resumes after its last contiguous keyframe (left-over
    temporary files of an interrupted write are removed).
    """

    def __init__(self, directory: str | Path, fsync: bool = True, reserve_bytes: int = 0,
                 max_memory_bytes: int = 64 * 2**20, disk_free: Callable[[Path], int] | None = None) -> None:
        self.dir = Path(directory)
        self.fsync = fsync
        self.reserve_bytes = max(0, int(reserve_bytes))
        self.max_memory_bytes = max(0, int(max_memory_bytes))
        self._disk_free = disk_free or (lambda p: int(shutil.disk_usage(p).free))
        self.disk_full: str | None = None  # why the spool went to memory (None: writing to disk)
        self._memory: dict[int, bytes] = {}
        self._released: set[int] = set()  # delivered from memory, never on disk (bounded by what was held)
        self._mem_lock = threading.Lock()
        self.memory_bytes = 0
        self.held_in_memory = 0  # keyframes that ever went to memory
        self.dir.mkdir(parents=True, exist_ok=True)
        for tmp in self.dir.iterdir():
            if is_temp(tmp):
                tmp.unlink(missing_ok=True)
        seqs = sorted(int(m.group(1)) for p in self.dir.iterdir() if (m := _NAME_RE.match(p.name)))
        if seqs and seqs != list(range(len(seqs))):
            raise DatasetError(f"keyframe spool {self.dir} is not contiguous from 0 "
                               f"({len(seqs)} files, last seq {seqs[-1]})")
        self._count = len(seqs)
        self.bytes_written = 0
        self._acks = ContiguousAcks(read_acked(self.dir))  # what hosts acknowledged, over the whole recording

    @property
    def count(self) -> int:
        """Number of keyframes spooled (the next seq)."""
        return self._count

    @property
    def last_seq(self) -> int:
        """Seq of the newest keyframe, -1 when empty."""
        return self._count - 1

    def path(self, seq: int) -> Path:
        return self.dir / f"{int(seq):08d}{SUFFIX}"

    def append(self, seq: int, data: bytes) -> None:
        """Store keyframe ``seq`` (must be :attr:`count`); it is readable when this returns.

        On disk (atomically) while the disk has room above the reserve, else in memory (see the
        module doc); raises :class:`DatasetError` when neither can take it.
        """
        if seq != self._count:
            raise DatasetError(f"keyframe spool {self.dir}: expected seq {self._count}, got {seq}")
        if self.disk_full is None:
            try:
                free = self._disk_free(self.dir)
            except OSError:
                free = None
            if free is not None and free - len(data) < self.reserve_bytes:
                self._go_to_memory(f"{free / 2**20:.0f} MiB free, the reserve is {self.reserve_bytes / 2**20:.0f} MiB")
            else:
                try:
                    fileio.write_atomic(self.path(seq), data, fsync=self.fsync)
                except OSError as exc:
                    if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                        raise
                    self._go_to_memory(exc.strerror or str(exc))
                else:
                    self.bytes_written += len(data)
                    self._count = seq + 1
                    return
        with self._mem_lock:
            if self.memory_bytes + len(data) > self.max_memory_bytes:
                raise DatasetError(f"keyframe spool {self.dir}: disk full ({self.disk_full}) and "
                                   f"{len(self._memory)} keyframes ({self.memory_bytes / 2**20:.1f} MiB) already wait "
                                   f"in memory for a host; keyframe {seq} dropped")
            self._memory[seq] = data
            self.memory_bytes += len(data)
            self.held_in_memory += 1
        self._count = seq + 1

    def _go_to_memory(self, why: str) -> None:
        self.disk_full = why
        log.error("keyframe spool %s: disk full (%s): keyframes are held in memory until a host acknowledges "
                  "them (up to %.0f MiB), the reserve is kept", self.dir, why, self.max_memory_bytes / 2**20)

    def release(self, acked_seq: int) -> None:
        """A host holds every keyframe up to ``acked_seq`` (its contiguous acknowledgement): free the ones
        held in memory.  A keyframe acknowledged past a gap stays until the gap is filled: the host's
        next hello has everything from the gap resent, which must still be readable."""
        if not self._memory:
            return
        with self._mem_lock:
            for s in [s for s in self._memory if s <= acked_seq]:
                self.memory_bytes -= len(self._memory.pop(s))
                self._released.add(s)

    def delivered_from_memory(self, seq: int) -> bool:
        """True for a keyframe a host acknowledged while it was held in memory (a full disk): it is on that
        host and nowhere on the device, so there is nothing to resend."""
        return seq in self._released

    def mark_acked(self, seq: int, upto: bool = False) -> None:
        """A host stored keyframe ``seq`` (``upto``: every keyframe up to ``seq``); when that advances the
        contiguous acknowledged seq, record it (a later run offers only what follows)."""
        if seq <= self.acked_seq:
            return
        if upto:
            self._acks.reset(seq)
        elif not self._acks.add(seq):
            return
        try:
            save_acked(self.dir, self.acked_seq)
        except OSError as exc:  # disk full: the next advance tries again; at worst a later run resends a few
            log.debug("keyframe spool %s: cannot record acked seq %d: %s", self.dir, self.acked_seq, exc)

    @property
    def acked_seq(self) -> int:
        """The highest seq a host acknowledged with every seq before it (-1: none)."""
        return self._acks.acked

    @property
    def memory_count(self) -> int:
        """Keyframes held only in memory (not yet freed: see :meth:`release`)."""
        return len(self._memory)

    @property
    def memory_unacked_count(self) -> int:
        """Keyframes held only in memory that no host acknowledged (lost if the device stops now); those a
        host acknowledged past a gap are held for a resend but are on that host."""
        with self._mem_lock:
            return sum(1 for s in self._memory if not self._acks.holds(s))

    def read(self, seq: int) -> bytes:
        """The bytes of keyframe ``seq`` (raises :class:`DatasetError` if it is not spooled)."""
        if not 0 <= seq < self._count:
            raise DatasetError(f"keyframe {seq} is not in spool {self.dir} (0..{self._count - 1})")
        data = self._memory.get(seq)
        if data is not None:
            return data
        if seq in self._released:
            raise DatasetError(f"keyframe spool {self.dir}: seq {seq} was delivered from memory (disk full) and "
                               f"is not on disk")
        try:
            return self.path(seq).read_bytes()
        except OSError as exc:
            raise DatasetError(f"keyframe spool {self.dir}: cannot read seq {seq}: {exc}") from None

    def seqs(self) -> list[int]:
        """Seqs present on disk (a directory scan)."""
        return sorted(int(m.group(1)) for p in self.dir.iterdir() if (m := _NAME_RE.match(p.name)))
