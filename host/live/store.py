"""The host's keyframe store: one folder per device session, one file per keyframe plus an index.

Layout under the receiver's output directory ``OUT``::

    OUT/state.json                          last session seen (so a restarted host can say hello)
    OUT/<session>/keyframes/kf_00000012.msgpack   the keyframe message exactly as received
    OUT/<session>/keyframes/index.csv       seq, frame seq, time, pose, file, size, encoding, rig

Each keyframe file is written to a temporary name, flushed (``fsync`` by default), renamed, and
only then acknowledged to the device; a keyframe whose file exists is a duplicate.  The highest
seq held contiguously from 0 (:meth:`SessionKeyframes.acked_seq`) is derived from the files, so a
host killed at any point restarts with a correct hello.  The index is rebuilt from the files when
it does not match them (a crash between the rename and the index line).

Read keyframes back with :func:`load_keyframe` (a :class:`stereopath.device.wire.protocol.Keyframe`; images via
:func:`stereopath.device.wire.protocol.decode_image`).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import re
import time
from pathlib import Path
from typing import Any

from stereopath.device.errors import DatasetError, ProtocolError
from stereopath.device.formats.fileio import is_temp, load_json, write_atomic, write_text_atomic
from stereopath.device.wire.protocol import SESSION_ID_RE, Keyframe, decode_keyframe

log = logging.getLogger(__name__)

INDEX_NAME = "index.csv"
STATE_NAME = "state.json"
INDEX_FIELDS = ("seq", "frame_seq", "t_ns", "tx", "ty", "tz", "qx", "qy", "qz", "qw", "file", "bytes",
                "encoding", "rig_name", "rig_hash")
_KF_RE = re.compile(r"^kf_(\d{8,10})\.msgpack$")


def keyframe_name(seq: int) -> str:
    return f"kf_{int(seq):08d}.msgpack"


def _index_row(kf: Keyframe, nbytes: int) -> list[Any]:
    return [kf.seq, kf.frame_seq, kf.t_ns, *(repr(float(v)) for v in kf.position_m),
            *(repr(float(v)) for v in kf.quat_xyzw), keyframe_name(kf.seq), nbytes, kf.left.encoding,
            kf.rig_name, kf.rig_hash]


def load_keyframe(path: str | Path) -> Keyframe:
    """Decode a stored keyframe file (validated like any received message)."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise DatasetError(f"cannot read keyframe {p}: {exc}") from None
    try:
        return decode_keyframe(data)
    except ProtocolError as exc:
        raise DatasetError(f"{p}: not a valid keyframe: {exc}") from None


def _parse_index(p: Path) -> tuple[list[dict[str, Any]], int | None]:
    """Rows of the index file ``p`` up to the first malformed one, and that row's line number (None: all good).

    A power cut during an append leaves a torn last line; everything before it is still valid.
    """
    rows: list[dict[str, Any]] = []
    with p.open(newline="", errors="replace") as fh:
        text = fh.read()
    lines = text.splitlines(keepends=True)
    if not lines or lines[0].rstrip("\r\n").split(",") != list(INDEX_FIELDS):
        return rows, 1
    for lineno, line in enumerate(lines[1:], start=2):
        if not line.endswith("\n"):
            return rows, lineno  # the last append did not finish
        try:
            values = next(csv.reader([line]))
        except csv.Error:
            return rows, lineno
        if len(values) != len(INDEX_FIELDS):
            return rows, lineno
        out: dict[str, Any] = dict(zip(INDEX_FIELDS, values))
        try:
            for k in ("seq", "frame_seq", "t_ns", "bytes"):
                out[k] = int(out[k])
            for k in ("tx", "ty", "tz", "qx", "qy", "qz", "qw"):
                out[k] = float(out[k])
        except ValueError:
            return rows, lineno
        if _KF_RE.match(out["file"]) is None:
            return rows, lineno
        rows.append(out)
    return rows, None


def read_index(session_dir: str | Path) -> list[dict[str, Any]]:
    """Rows of ``<session>/keyframes/index.csv`` with numeric fields converted.

    A torn or malformed line (a power cut during an append) ends the index: the valid rows
    before it are returned and a warning names the file and line.
    """
    p = Path(session_dir) / "keyframes" / INDEX_NAME
    if not p.is_file():
        return []
    rows, bad = _parse_index(p)
    if bad is not None:
        log.warning("%s: line %d is torn or malformed; using the %d valid rows before it", p, bad, len(rows))
    return rows


def list_sessions(out_dir: str | Path) -> list[str]:
    """Session ids with a folder under ``out_dir`` (sorted)."""
    d = Path(out_dir)
    if not d.is_dir():
        return []
    return sorted(p.name for p in d.iterdir() if p.is_dir() and SESSION_ID_RE.match(p.name))


class SessionKeyframes:
    """Keyframes of one device session (``OUT/<session>/keyframes``)."""

    def __init__(self, session_dir: Path, fsync: bool = True) -> None:
        self.session_id = session_dir.name
        self.dir = session_dir / "keyframes"
        self.fsync = fsync
        self.dir.mkdir(parents=True, exist_ok=True)
        for tmp in self.dir.iterdir():
            if is_temp(tmp):
                tmp.unlink(missing_ok=True)
        self.seqs: set[int] = {int(m.group(1)) for p in self.dir.iterdir() if (m := _KF_RE.match(p.name))}
        self._acked = -1
        self._advance()
        self._reconcile_index()
        self._index_fd = os.open(self.dir / INDEX_NAME, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        self._index_ok = True  # False after a failed append: the index is rebuilt from the files on reopen

    def _advance(self) -> None:
        while self._acked + 1 in self.seqs:
            self._acked += 1

    @property
    def acked_seq(self) -> int:
        """Highest seq held contiguously from 0 (-1: none)."""
        return self._acked

    def path(self, seq: int) -> Path:
        return self.dir / keyframe_name(seq)

    def has(self, seq: int) -> bool:
        return seq in self.seqs

    def put(self, kf: Keyframe, data: bytes) -> bool:
        """Store ``kf`` (its wire bytes ``data``); False if it is already stored (a duplicate)."""
        if kf.seq in self.seqs:
            return False
        write_atomic(self.path(kf.seq), data, self.fsync)  # OSError (disk full): nothing stored, nothing changed
        self.seqs.add(kf.seq)
        self._append_index(_index_row(kf, len(data)))
        self._advance()
        return True

    def _append_index(self, row: list[Any]) -> None:
        """One index line in one ``write`` (a cut leaves a torn last line, recovered on reopen).

        The keyframe file is already stored: a failed append (disk full) is logged and the index
        is rebuilt from the files when the session is next opened.
        """
        if not self._index_ok:
            return
        buf = io.StringIO()
        csv.writer(buf).writerow(row)
        data = buf.getvalue().encode()
        try:
            n = os.write(self._index_fd, data)
            if n != len(data):
                raise OSError(f"short write ({n} of {len(data)} bytes)")
        except OSError as exc:
            self._index_ok = False
            log.error("session %s: cannot append to %s (%s); the keyframe files are stored and the index is "
                      "rebuilt from them on the next start", self.session_id, self.dir / INDEX_NAME, exc)

    def _reconcile_index(self) -> None:
        """Make ``index.csv`` list exactly the stored files, keeping the valid prefix of a torn index."""
        index = self.dir / INDEX_NAME
        if not index.is_file() and not self.seqs:
            with index.open("w", newline="") as fh:
                csv.writer(fh).writerow(INDEX_FIELDS)
            return
        listed: list[dict[str, Any]] = []
        bad: int | None = None
        if index.is_file():
            listed, bad = _parse_index(index)
            seqs = [r["seq"] for r in listed]
            if bad is None and len(seqs) == len(set(seqs)) and set(seqs) == self.seqs:
                return
        if bad is not None:
            log.warning("session %s: %s line %d is torn or malformed (a write cut short); keeping the %d valid "
                        "rows before it and re-adding the rest from the %d keyframe files", self.session_id,
                        index, bad, len(listed), len(self.seqs))
        else:
            log.warning("session %s: keyframe index out of step with %d files; rebuilding", self.session_id,
                        len(self.seqs))
        rows: list[list[Any]] = []
        kept: set[int] = set()
        for r in listed:  # the valid prefix, in its order, for rows whose file is still there
            if r["seq"] in self.seqs and r["seq"] not in kept and r["file"] == keyframe_name(r["seq"]):
                rows.append([r[k] for k in INDEX_FIELDS])
                kept.add(r["seq"])
        for seq in sorted(self.seqs - kept):
            p = self.path(seq)
            try:
                kf = load_keyframe(p)
            except DatasetError as exc:
                log.error("dropping unreadable keyframe file %s: %s", p, exc)
                p.unlink(missing_ok=True)
                continue
            rows.append(_index_row(kf, p.stat().st_size))
        self.seqs = {int(r[0]) for r in rows}
        self._acked = -1
        self._advance()
        buf = io.StringIO(newline="")
        w = csv.writer(buf)
        w.writerow(INDEX_FIELDS)
        w.writerows(rows)
        write_text_atomic(index, buf.getvalue(), fsync=self.fsync)

    def close(self) -> None:
        if self._index_fd >= 0:
            os.close(self._index_fd)
            self._index_fd = -1


class KeyframeStore:
    """All sessions under ``out_dir`` plus the persisted last session (``state.json``)."""

    def __init__(self, out_dir: str | Path, fsync: bool = True, max_open: int = 8) -> None:
        self.root = Path(out_dir)
        self.root.parent.mkdir(parents=True, exist_ok=True)
        self.root.mkdir(mode=0o700, exist_ok=True)  # private by default: the scans are the user's
        self.fsync = fsync
        self.max_open = max_open
        self._sessions: dict[str, SessionKeyframes] = {}
        self._last_session: str | None = None
        state = self.root / STATE_NAME
        if state.is_file():
            try:
                sid = load_json(state).get("last_session")
                if isinstance(sid, str) and SESSION_ID_RE.match(sid):
                    self._last_session = sid
            except (OSError, ValueError, AttributeError) as exc:
                log.warning("ignoring unreadable %s: %s", state, exc)

    def session(self, session_id: str) -> SessionKeyframes:
        if not SESSION_ID_RE.match(session_id):  # decoded messages are already checked
            raise ProtocolError(f"invalid session id {session_id!r}")
        s = self._sessions.get(session_id)
        if s is None:
            if len(self._sessions) >= self.max_open:
                oldest = next(iter(self._sessions))
                self._sessions.pop(oldest).close()
            s = SessionKeyframes(self.root / session_id, self.fsync)
            self._sessions[session_id] = s
        return s

    @property
    def last_session(self) -> str | None:
        return self._last_session

    def set_last_session(self, session_id: str) -> None:
        if session_id != self._last_session:
            self._last_session = session_id
            self.save_state()

    def save_state(self) -> None:
        sid = self._last_session
        acked = self.session(sid).acked_seq if sid else -1
        data = json.dumps({"last_session": sid, "acked_seq": acked, "updated_unix": time.time()}, indent=1)
        write_atomic(self.root / STATE_NAME, data.encode(), self.fsync)

    def put(self, kf: Keyframe, data: bytes) -> bool:
        """Store a keyframe in its session's folder; False if it was already there."""
        return self.session(kf.session_id).put(kf, data)

    def hello_state(self) -> tuple[str | None, int]:
        """``(last session, highest contiguous seq)`` for a hello."""
        sid = self._last_session
        return sid, (self.session(sid).acked_seq if sid else -1)

    def close(self) -> None:
        for s in self._sessions.values():
            s.close()
        self._sessions.clear()
