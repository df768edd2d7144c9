"""The sessions of a fleet run: expansion of folders and globs, session ids, path mapping.

A session is a folder written by the recorder or ``stereopath sim`` (``mav0/`` inside, and a
``manifest.json`` naming its ``session_id``).  Each argument is a session folder, a folder whose
sub-folders are sessions, or a glob pattern (expanded here, so a quoted pattern works too).
"""

from __future__ import annotations

import glob
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from stereopath.device.errors import ConfigError, DatasetError
from stereopath.device.formats.fileio import load_json

_GLOB_CHARS = re.compile(r"[*?\[]")
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


@dataclass(frozen=True)
class FleetSession:
    """One session of a fleet run: its id (the name of its output folder) and its folder."""

    id: str
    path: Path  # absolute, as this machine (the driver) sees it


def looks_like_session(d: Path) -> bool:
    """A folder the recorder wrote (``mav0/`` or ``manifest.json`` inside)."""
    return d.is_dir() and ((d / "mav0").is_dir() or (d / "manifest.json").is_file())


def session_id(d: Path) -> str:
    """The recorder's ``session_id`` from ``manifest.json``, else the folder name (file-name safe)."""
    sid = None
    try:
        man = load_json(d / "manifest.json")
        if isinstance(man, dict) and isinstance(man.get("session_id"), str):
            sid = man["session_id"]
    except (OSError, ValueError):
        pass
    sid = _UNSAFE.sub("_", sid or d.name).strip("._") or "session"
    return sid


def frame_count(d: Path) -> int:
    """Images in the session's left camera folder (its size, for the submission order; 0 if none)."""
    try:
        with os.scandir(Path(d) / "mav0" / "cam0" / "data") as it:
            return sum(1 for e in it if e.is_file())
    except OSError:
        return 0


def expand_sessions(specs: Sequence[str | Path]) -> list[FleetSession]:
    """Sessions named by ``specs`` (folders, folders of sessions, glob patterns), in order.

    Raises :class:`DatasetError` for a path or pattern that matches nothing (nothing is started
    then) and :class:`ConfigError` when two different folders carry the same session id.
    """
    paths: list[Path] = []
    for spec in specs:
        s = str(spec)
        if _GLOB_CHARS.search(s):
            hits = sorted(glob.glob(s))
            if not hits:
                raise DatasetError(f"no session matches {s!r}")
            paths.extend(Path(h) for h in hits if Path(h).is_dir())
            continue
        p = Path(s)
        if not p.exists():
            raise DatasetError(f"session folder not found: {p}")
        if p.is_dir() and not looks_like_session(p):
            children = sorted(c for c in p.iterdir() if looks_like_session(c))
            if children:
                paths.extend(children)
                continue
        paths.append(p)  # a session, or something that is not one (reported as failed by its task)
    out: list[FleetSession] = []
    seen: dict[str, Path] = {}
    for p in paths:
        p = p.absolute()
        if p in seen.values():
            continue
        sid = session_id(p)
        if sid in seen:
            raise ConfigError(f"two sessions have the id {sid!r}: {seen[sid]} and {p} (rename one folder "
                              "or fix its manifest.json)")
        seen[sid] = p
        out.append(FleetSession(sid, p))
    if not out:
        raise DatasetError("no sessions given")
    return out


@dataclass(frozen=True)
class PathMap:
    """How the paths this machine sees become the paths a cluster worker sees.

    ``pairs`` are ``(driver_prefix, worker_prefix)``; the longest matching prefix wins (whole
    path components only); paths under no prefix are passed unchanged.
    """

    pairs: tuple[tuple[str, str], ...] = ()

    @classmethod
    def parse(cls, items: Sequence[str]) -> PathMap:
        """From ``DRIVER_PREFIX=WORKER_PREFIX`` strings (``--path-map``)."""
        pairs = []
        for item in items:
            left, sep, right = item.partition("=")
            if not sep or not left.strip() or not right.strip():
                raise ConfigError(f"path map {item!r} must look like DRIVER_PREFIX=WORKER_PREFIX")
            if not Path(left).is_absolute() or not right.startswith("/"):
                raise ConfigError(f"path map {item!r}: both prefixes must be absolute paths")
            pairs.append((str(Path(left)), right.rstrip("/") or "/"))
        return cls(tuple(pairs))

    def to_worker(self, path: str | Path) -> str:
        p = str(Path(path).absolute())
        best: tuple[str, str] | None = None
        for left, right in self.pairs:
            if (p == left or p.startswith(left.rstrip("/") + "/")) and (best is None or len(left) > len(best[0])):
                best = (left, right)
        if best is None:
            return p
        rest = p[len(best[0]):].lstrip("/")
        return best[1] if not rest else best[1].rstrip("/") + "/" + rest
