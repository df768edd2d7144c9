"""The ``estimate`` stage's stored progress: the estimator and its results every so many frames.

An interrupted stage continues from the last stored chunk instead of the first frame.  The estimator's
state (its map, keyframe library, IMU and offset filters, the work it had in flight, settled) is a
pickle: it is read back only from the stage folder this program wrote, under the key of the same
inputs and settings, and only by the same Python and the same on-board code (a hash of its sources);
anything else (a file cut short, another version) is logged and the stage starts from the first frame.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import pickle
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stereopath.device.estimation.base import EstimateProgress
from stereopath.device.formats.fileio import replacing

log = logging.getLogger(__name__)

FILE = "progress.pkl"
FORMAT = 1


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


@dataclass
class EstimateCheckpoint:
    """``parts/progress.pkl``: written by :meth:`save` (atomically), read by :meth:`load`."""

    parts: Path

    @property
    def path(self) -> Path:
        return Path(self.parts) / FILE

    def save(self, estimator: Any, progress: EstimateProgress) -> None:
        """Store ``estimator`` (settled first: its work in flight finished) and ``progress``."""
        settle = getattr(estimator, "settle", None)
        if settle is not None:
            settle()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with replacing(self.path) as tmp, open(tmp, "wb") as f:
            pickle.dump({"identity": _identity(), "estimator": estimator, "progress": progress}, f,
                        protocol=pickle.HIGHEST_PROTOCOL)
        log.debug("estimate: progress stored at frame %d", progress.next_seq)

    def load(self) -> tuple[Any, EstimateProgress] | None:
        """The stored estimator and progress, or None (nothing stored, or unusable: logged)."""
        if not self.path.is_file():
            return None
        try:
            with open(self.path, "rb") as f:
                data = pickle.load(f)
            if not isinstance(data, dict) or data.get("identity") != _identity():
                raise ValueError(f"written by another version ({data.get('identity') if isinstance(data, dict) else '?'})")
            est, progress = data["estimator"], data["progress"]
            if not isinstance(progress, EstimateProgress):
                raise ValueError("no progress record")
        except Exception as exc:  # noqa: BLE001 - any unreadable file means: start again from the first frame
            log.warning("%s not usable (%s): the estimate starts from the first frame", self.path, exc)
            return None
        log.info("estimate: resuming at frame %d from the stored progress", progress.next_seq)
        return est, progress
