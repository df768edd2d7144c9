"""The ``estimate`` stage's stored progress: the estimator and its results every so many frames.

An interrupted stage continues from the last stored chunk instead of the first frame.  The estimator's
state (its map, keyframe library, IMU and offset filters, the work it had in flight, settled) is a
pickle, ``progress.pkl``, beside ``progress.json``: the identity of what wrote it (the format, a hash of
the on-board code's sources, the Python version) and an HMAC of the pickle under a key private to the
user (``~/.cache/stereopath/progress.key``, created on first use, mode 0600).  Both are checked before
the pickle is read, so a file this user's stereopath did not write (another build, another user's, a
file cut short or altered) is never unpickled: it is logged and the stage starts from the first frame.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import json
import logging
import os
import pickle
import secrets
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stereopath.device.estimation.base import EstimateProgress
from stereopath.device.formats.fileio import replacing, write_text_atomic

log = logging.getLogger(__name__)

FILE = "progress.pkl"
SIDECAR = "progress.json"
FORMAT = 2


@functools.cache
def _code_hash() -> str:
    """A hash of the on-board package's sources (what the pickled estimator's classes are made of)."""
    import stereopath.device

    root = Path(stereopath.device.__file__).parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _identity() -> dict[str, Any]:
    return {"format": FORMAT, "code": _code_hash(), "python": list(sys.version_info[:2])}


def key_path() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "stereopath" / "progress.key"


def _user_key() -> bytes:
    """This user's key for the progress files' HMAC (created once, readable by the user only)."""
    p = key_path()
    try:
        return p.read_bytes()
    except FileNotFoundError:
        pass
    p.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:  # another process made it meanwhile
        return p.read_bytes()
    with os.fdopen(fd, "wb") as f:
        f.write(secrets.token_bytes(32))
    return p.read_bytes()


def _mac(data: bytes) -> str:
    return hmac.new(_user_key(), data, hashlib.sha256).hexdigest()


@dataclass
class EstimateCheckpoint:
    """``parts/progress.pkl`` and ``parts/progress.json``: written by :meth:`save`, read by :meth:`load`."""

    parts: Path

    @property
    def path(self) -> Path:
        return Path(self.parts) / FILE

    @property
    def sidecar(self) -> Path:
        return Path(self.parts) / SIDECAR

    def save(self, estimator: Any, progress: EstimateProgress) -> None:
        """Store ``estimator`` (settled first: its work in flight finished) and ``progress``."""
        settle = getattr(estimator, "settle", None)
        if settle is not None:
            settle()
        data = pickle.dumps((estimator, progress), protocol=pickle.HIGHEST_PROTOCOL)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.sidecar.unlink(missing_ok=True)  # never a sidecar naming another pickle than the one on disk
        with replacing(self.path) as tmp:
            tmp.write_bytes(data)
        write_text_atomic(self.sidecar, json.dumps({**_identity(), "hmac": _mac(data), "next_seq": progress.next_seq}))
        log.debug("estimate: progress stored at frame %d", progress.next_seq)

    def load(self) -> tuple[Any, EstimateProgress] | None:
        """The stored estimator and progress, or None (nothing stored, or unusable: logged)."""
        if not self.sidecar.is_file() and not self.path.is_file():
            return None
        try:
            side = json.loads(self.sidecar.read_text())
            if not isinstance(side, dict) or {k: side.get(k) for k in _identity()} != _identity():
                raise ValueError("written by another version")
            data = self.path.read_bytes()
            if not hmac.compare_digest(str(side.get("hmac")), _mac(data)):
                raise ValueError("not written by this user's stereopath, or altered")
            est, progress = pickle.loads(data)
            if not isinstance(progress, EstimateProgress):
                raise ValueError("no progress record")
        except Exception as exc:  # noqa: BLE001 - any unusable file means: start again from the first frame
            log.warning("%s not usable (%s): the estimate starts from the first frame", self.path, exc)
            return None
        log.info("estimate: resuming at frame %d from the stored progress", progress.next_seq)
        return est, progress
