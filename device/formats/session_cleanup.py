"""Remove a session folder that a failed start left with nothing captured in it."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

log = logging.getLogger(__name__)

_DATA_GLOBS = ("mav0/cam*/data/*", "keyframes/*.kf", "keyframes/kf_*.msgpack")  # not the spool's session.msgpack


def holds_captured_data(session_dir: Path) -> bool:
    """True when the folder holds any image or spooled keyframe (never discard those)."""
    return any(next(session_dir.glob(g), None) is not None for g in _DATA_GLOBS)


def discard_unused_session(session_dir: str | Path, keep_folder: bool = False) -> bool:
    """Delete what a start that failed before capture wrote into ``session_dir``.

    Nothing is deleted when any image or keyframe is there.  ``keep_folder``: empty the folder
    but keep it (the user created it).  Returns True when something was removed.
    """
    d = Path(session_dir)
    if not d.is_dir() or holds_captured_data(d):
        return False
    if keep_folder:
        for child in d.iterdir():
            if child.is_dir() and not child.is_symlink():
                shutil.rmtree(child)
            else:
                child.unlink()
    else:
        shutil.rmtree(d)
    log.info("removed the unused session folder %s (the start failed before any capture)", d)
    return True
