"""The device's keyframe spool: one file per keyframe, named by seq, written atomically.

The spool is the part of the session recording the keyframe server resends from: each encoded
keyframe message (exactly the bytes sent on the wire) is written to a temporary file, flushed
(``fsync`` optional), renamed to ``<seq:08d>.kf`` and only then offered to hosts.  Seqs are
contiguous from 0, so the in-memory index is just the count: memory does not grow with the
session.  Files are never deleted by the streamer (they are part of the recording).

Thread model: one writer (:meth:`append`), any number of readers (:meth:`read`) of seqs below
:attr:`count`.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

from stereopath.device.errors import DatasetError
from stereopath.device.formats.fileio import is_temp, write_atomic

log = logging.getLogger(__name__)

SUFFIX = ".kf"
_NAME_RE = re.compile(r"^(\d{8,10})\.kf$")


class KeyframeSpool:
    """A directory of keyframe messages ``00000000.kf``, ``00000001.kf``, ...

    Opening an existing directory resumes after its last contiguous keyframe (left-over
    temporary files of an interrupted write are removed).
    """

    def __init__(self, directory: str | Path, fsync: bool = True) -> None:
        self.dir = Path(directory)
        self.fsync = fsync
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
        """Write keyframe ``seq`` (must be :attr:`count`) atomically; it is readable when this returns."""
        if seq != self._count:
            raise DatasetError(f"keyframe spool {self.dir}: expected seq {self._count}, got {seq}")
        final = self.path(seq)
        write_atomic(final, data, fsync=self.fsync)
        self.bytes_written += len(data)
        self._count = seq + 1

    def read(self, seq: int) -> bytes:
        """The bytes of keyframe ``seq`` (raises :class:`DatasetError` if it is not spooled)."""
        if not 0 <= seq < self._count:
            raise DatasetError(f"keyframe {seq} is not in spool {self.dir} (0..{self._count - 1})")
        try:
            return self.path(seq).read_bytes()
        except OSError as exc:
            raise DatasetError(f"keyframe spool {self.dir}: cannot read seq {seq}: {exc}") from None

    def seqs(self) -> list[int]:
        """Seqs present on disk (a directory scan)."""
        return sorted(int(m.group(1)) for p in self.dir.iterdir() if (m := _NAME_RE.match(p.name)))
