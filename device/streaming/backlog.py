"""Earlier sessions' keyframes that no host acknowledged (a killed run, or no host in reach), offered again.

Every spool the streamer writes holds, beside its keyframes, ``session.msgpack`` (the session
message: its id and rig, see :func:`stereopath.device.wire.protocol.encode_session`) and
``acked.json`` (the highest seq a host acknowledged contiguously, rewritten as acknowledgements
arrive; see :class:`stereopath.device.streaming.spool.KeyframeSpool`).  When a new run starts, the
streamer scans its spool roots (the folder holding the new session folder, and ``recorder.dir``)
for spools of other sessions with keyframes after their acknowledged seq.  Those are offered to
every host after the live session's keyframes, oldest session first, each preceded by its session
message (so the host stores the rig too).  A backlog keyframe a host acknowledged is deleted from
the device: the host has it, and the device's disk is small.  Keyframes a host acknowledged while
their own run was alive stay, as part of that session's recording.

The scan is bounded (entries per root, sessions kept) and never follows what it cannot decode: a
spool whose ``session.msgpack`` is unreadable is named in a warning and left alone.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import threading
from bisect import bisect_right
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

from stereopath.device.errors import ProtocolError
from stereopath.device.streaming.spool import SUFFIX, read_acked, save_acked
from stereopath.device.wire.protocol import SessionInfo, decode_session, encode_session

log = logging.getLogger(__name__)

MARKER_NAME = "session.msgpack"
MAX_SCAN_ENTRIES = 10_000   # entries looked at per spool root
MAX_SESSIONS = 32           # earlier sessions offered in one run (the oldest first; a host admits 64 new ids a run)
_KF_RE = re.compile(r"^(\d{8,10})\.kf$")


@dataclass
class BacklogSession:
    """One earlier session's spool and the seqs in it no host acknowledged yet (ascending)."""

    dir: Path
    info: SessionInfo
    pending: list[int]
    total: int            # keyframes the session spooled (its highest seq on disk + 1)
    delivered: int = 0    # acknowledged by a host in this run (and deleted)
    message: bytes = field(default=b"", repr=False)

    @property
    def session_id(self) -> str:
        return self.info.session_id


def write_marker(spool_dir: Path, data: bytes) -> None:
    """Write the session message beside a spool's keyframes (what a later run identifies it by)."""
    from stereopath.device.formats.fileio import write_atomic

    write_atomic(Path(spool_dir) / MARKER_NAME, data, fsync=True)


def _spool_seqs(d: Path) -> list[int]:
    return sorted(int(m.group(1)) for p in d.iterdir() if (m := _KF_RE.match(p.name)))


def _load(d: Path) -> BacklogSession | None:
    """The backlog of the spool ``d`` (None: nothing unacknowledged, or not a usable spool)."""
    try:
        info = decode_session((d / MARKER_NAME).read_bytes())
        seqs = _spool_seqs(d)
    except (OSError, ProtocolError) as exc:
        log.warning("earlier keyframe spool %s left alone: %s unreadable (%s)", d, MARKER_NAME, exc)
        return None
    acked = read_acked(d)
    pending = [s for s in seqs if s > acked]
    if not pending:
        return None
    total = seqs[-1] + 1
    msg = encode_session(dataclasses.replace(info, keyframes=total, live=False))
    return BacklogSession(d, info, pending, total, message=msg)


def _candidates(root: Path) -> Iterable[Path]:
    try:
        it = root.iterdir()
    except OSError:
        return
    for n, child in enumerate(it):
        if n >= MAX_SCAN_ENTRIES:
            log.warning("spool root %s has more than %d entries: the rest is not searched for undelivered "
                        "keyframes", root, MAX_SCAN_ENTRIES)
            return
        for cand in (child / "keyframes", child):
            if (cand / MARKER_NAME).is_file():
                yield cand
                break


def find_backlog(roots: Iterable[str | Path], exclude: str | Path) -> list[BacklogSession]:
    """Earlier sessions under ``roots`` (each a folder of session folders or spools) with keyframes
    no host acknowledged, oldest first; ``exclude`` is the live session's spool."""
    skip = Path(exclude).resolve()
    seen: set[Path] = set()
    found: list[tuple[int, str, BacklogSession]] = []
    for root in roots:
        r = Path(root)
        if not r.is_dir() or r.resolve() in seen:
            continue
        seen.add(r.resolve())
        for cand in _candidates(r):
            real = cand.resolve()
            if real == skip or real in seen:
                continue
            seen.add(real)
            b = _load(cand)
            if b is not None:
                try:
                    found.append(((cand / MARKER_NAME).stat().st_mtime_ns, b.session_id, b))
                except OSError:
                    continue  # removed while scanned
    found.sort(key=lambda t: (t[0], t[1]))
    if len(found) > MAX_SESSIONS:
        log.warning("%d earlier sessions hold undelivered keyframes; offering the oldest %d in this run",
                    len(found), MAX_SESSIONS)
    return [b for _, _, b in found[:MAX_SESSIONS]]


class Backlog:
    """The earlier sessions offered in this run; driven by the keyframe server's I/O thread.

    A cursor ``(session index, last seq sent)`` walks it in order; :meth:`acknowledged` deletes a
    delivered keyframe and, once a session has none left, records it as delivered.
    """

    def __init__(self, sessions: list[BacklogSession]) -> None:
        self.sessions = sessions
        self._index = {b.session_id: i for i, b in enumerate(sessions)}
        self._lock = threading.Lock()  # stats() is read from other threads

    @property
    def pending(self) -> int:
        with self._lock:
            return sum(len(b.pending) for b in self.sessions)

    def summary(self) -> dict[str, int]:
        with self._lock:
            return {"backlog_sessions": sum(1 for b in self.sessions if b.pending),
                    "backlog_keyframes": sum(len(b.pending) for b in self.sessions),
                    "backlog_delivered": sum(b.delivered for b in self.sessions)}

    def next_after(self, cursor: tuple[int, int]) -> tuple[int, int] | None:
        """The next ``(session index, seq)`` still pending after ``cursor``, or None."""
        si, last = cursor
        with self._lock:
            while si < len(self.sessions):
                pending = self.sessions[si].pending
                j = bisect_right(pending, last)
                if j < len(pending):
                    return si, pending[j]
                si, last = si + 1, -1
        return None

    def read(self, si: int, seq: int) -> bytes | None:
        """The keyframe's bytes; None when it is gone (delivered meanwhile, or removed by hand)."""
        try:
            return (self.sessions[si].dir / f"{int(seq):08d}{SUFFIX}").read_bytes()
        except OSError:
            with self._lock:
                self._drop(self.sessions[si], seq)
            return None

    def acknowledged(self, session_id: str, seq: int) -> bool:
        """A host stored keyframe ``seq`` of an earlier session: delete it from the device."""
        si = self._index.get(session_id)
        if si is None:
            return False
        b = self.sessions[si]
        with self._lock:
            if not self._drop(b, seq):
                return False
            b.delivered += 1
            done = not b.pending
        try:
            (b.dir / f"{int(seq):08d}{SUFFIX}").unlink(missing_ok=True)
        except OSError as exc:  # e.g. a read-only or foreign spool: the host has it, a later run offers it again
            log.warning("earlier session %s: keyframe %d is on a host but cannot be deleted here: %s",
                        session_id, seq, exc)
        if done:
            try:
                save_acked(b.dir, b.total - 1)
            except OSError as exc:
                log.debug("cannot record %s as delivered: %s", b.dir, exc)
            log.info("earlier session %s: every undelivered keyframe is now on a host (%d sent in this run)",
                     session_id, b.delivered)
        return True

    @staticmethod
    def _drop(b: BacklogSession, seq: int) -> bool:
        j = bisect_right(b.pending, seq) - 1
        if j >= 0 and b.pending[j] == seq:
            del b.pending[j]
            return True
        return False
