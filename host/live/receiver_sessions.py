"""What the host knows of each device session: its rig (stored as ``rig.yaml``) and whether it is complete.

The device sends a ``session`` message once per session on each connection, before that
session's keyframes: the rig calibration and how many keyframes it holds of the session (the
live one, or an earlier one whose keyframes no host acknowledged, e.g. after the device was
killed).  The host keeps, per session folder ``OUT/<session>/``:

* ``rig.yaml``      the device's rig, written once (atomically) through
  :func:`stereopath.device.formats.rig_files.save_rig_yaml`; ``host map OUT/<session>`` and
  ``host live --map`` map with it;
* ``session.json``  the rig reference and the number of keyframes the device reported (from the
  session message and, for the live session, its status), updated as they grow.

A session is *incomplete* while the host holds fewer keyframes than the device reported, or has
gaps; :func:`session_states` lists every session with its state (``stereopath host sessions OUT``,
and ``host live`` at start and at the end).
"""

from __future__ import annotations

import json
import logging
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stereopath.device.core.rig import Rig
from stereopath.device.errors import CalibrationError, DatasetError, ProtocolError
from stereopath.device.formats.fileio import write_json_atomic
from stereopath.device.wire.protocol import SESSION_ID_RE, SessionInfo, rig_of

log = logging.getLogger(__name__)

RIG_FILE = "rig.yaml"
SESSION_JSON = "session.json"
_KF_RE = re.compile(r"^kf_(\d{8,10})\.msgpack$")


@dataclass(frozen=True)
class SessionState:
    """One stored session as ``host sessions`` lists it."""

    session_id: str
    stored: int                      # keyframe files on this host
    on_device: int | None            # keyframes the device reported (None: never told)
    missing: int                     # seqs below the device's count (or below the highest stored) not here
    rig: str                         # "rig.yaml", or why there is none
    state: str                       # "complete", "incomplete" or "unknown"

    def line(self) -> str:
        dev = "?" if self.on_device is None else str(self.on_device)
        return f"{self.session_id}: {self.state}, {self.stored} of {dev} keyframes stored" + \
            (f" ({self.missing} missing)" if self.missing else "") + f", rig: {self.rig}"


def _stored_seqs(session_dir: Path) -> list[int]:
    d = session_dir / "keyframes"
    if not d.is_dir():
        return []
    return sorted(int(m.group(1)) for p in d.iterdir() if (m := _KF_RE.match(p.name)))


def read_session_json(session_dir: Path) -> dict[str, Any]:
    try:
        data = json.loads((session_dir / SESSION_JSON).read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def session_state(session_dir: Path) -> SessionState:
    seqs = _stored_seqs(session_dir)
    info = read_session_json(session_dir)
    dev = info.get("keyframes_on_device")
    on_device = dev if isinstance(dev, int) and not isinstance(dev, bool) and dev >= 0 else None
    upto = max(on_device or 0, seqs[-1] + 1 if seqs else 0)
    missing = upto - sum(1 for s in seqs if s < upto)
    rig = RIG_FILE if (session_dir / RIG_FILE).is_file() else "none from the device (map with --rig)"
    if on_device is None:
        state = "incomplete" if missing else "unknown"
    else:
        state = "incomplete" if missing else "complete"
    return SessionState(session_dir.name, len(seqs), on_device, missing, rig, state)


def session_states(out_dir: str | Path) -> list[SessionState]:
    """Every session folder under ``out_dir`` with its state (sorted by session id)."""
    d = Path(out_dir)
    if not d.is_dir():
        raise DatasetError(f"{d}: no such folder (expected the OUT folder of `host live`)")
    return [session_state(p) for p in sorted(d.iterdir()) if p.is_dir() and SESSION_ID_RE.match(p.name)]


class SessionCatalog:
    """The receiver's view of device sessions (rigs, device counts), written into the store."""

    def __init__(self, out_dir: Path, fsync: bool = True) -> None:
        self.out = out_dir
        self.fsync = fsync
        self._rigs: dict[str, Rig] = {}
        self._counts: dict[str, int] = {}
        self._refs: dict[str, dict[str, str]] = {}
        self._dirty: set[str] = set()
        self._lock = threading.Lock()  # rig() is called from the live mapper's thread

    def on_session(self, info: SessionInfo) -> None:
        """Store the session's rig (once) and the device's keyframe count.  OSError: not stored."""
        d = self.out / info.session_id
        rig = rig_of(info)  # validated when decoded
        with self._lock:
            if self._refs.get(info.session_id) != {"name": info.rig_name, "hash": info.rig_hash}:
                self._refs[info.session_id] = {"name": info.rig_name, "hash": info.rig_hash}
                self._dirty.add(info.session_id)
        if rig is not None:
            self._store_rig(d, info, rig)
        self.on_count(info.session_id, info.keyframes)
        if not info.live:
            log.warning("the device holds %d keyframe(s) of earlier session %s that no host acknowledged: "
                        "receiving them into %s", info.keyframes, info.session_id, d)
        self.save()

    def _store_rig(self, d: Path, info: SessionInfo, rig: Rig) -> None:
        from stereopath.device.formats.rig_files import save_rig_yaml

        path = d / RIG_FILE
        have = self.rig(info.session_id)
        if have is not None:
            from stereopath.device.wire.protocol import rig_reference

            if rig_reference(have)[1] != info.rig_hash:
                log.error("session %s: the device now names rig %s (%s) but %s holds another; keeping %s",
                          info.session_id, info.rig_name, info.rig_hash, path, path)
            return
        d.mkdir(parents=True, exist_ok=True)
        save_rig_yaml(rig, path, comment=f"rig of device session {info.session_id} ({info.rig_name}, hash "
                                         f"{info.rig_hash}), as the device sent it")
        with self._lock:
            self._rigs[info.session_id] = rig
        log.info("session %s: device rig %s stored in %s", info.session_id, info.rig_name, path)

    def on_count(self, session_id: str, keyframes: int) -> None:
        with self._lock:
            if keyframes > self._counts.get(session_id, -1):
                self._counts[session_id] = keyframes
                self._dirty.add(session_id)

    def rig(self, session_id: str) -> Rig | None:
        """The device's rig of ``session_id`` (from memory or ``OUT/<session>/rig.yaml``), or None."""
        with self._lock:
            rig = self._rigs.get(session_id)
        if rig is not None or not SESSION_ID_RE.match(session_id):
            return rig
        path = self.out / session_id / RIG_FILE
        if not path.is_file():
            return None
        from stereopath.device.formats.rig_files import load_rig_yaml

        try:
            rig = load_rig_yaml(path)
        except CalibrationError as exc:
            log.error("session %s: %s", session_id, exc)
            return None
        with self._lock:
            self._rigs[session_id] = rig
        return rig

    def save(self) -> None:
        """Write ``session.json`` of every session whose device count changed.  OSError: retried later."""
        with self._lock:
            dirty = sorted(self._dirty)
        for sid in dirty:
            d = self.out / sid
            data = read_session_json(d)
            with self._lock:
                data.update({"session_id": sid, "updated_unix": time.time()})
                if sid in self._counts:
                    data["keyframes_on_device"] = self._counts[sid]
                if sid in self._refs:
                    data["rig"] = self._refs[sid]
            d.mkdir(parents=True, exist_ok=True)
            write_json_atomic(d / SESSION_JSON, data, indent=1, fsync=self.fsync)
            with self._lock:
                self._dirty.discard(sid)


def describe_incomplete(out_dir: Path) -> list[str]:
    """One line per incomplete session under ``out_dir`` (for the log)."""
    try:
        return [s.line() for s in session_states(out_dir) if s.state == "incomplete"]
    except (OSError, DatasetError, ProtocolError) as exc:
        log.debug("cannot list sessions of %s: %s", out_dir, exc)
        return []
