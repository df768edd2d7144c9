"""Crash-safe file writes shared by the recorder and the host's keyframe store."""

from __future__ import annotations

import os
from pathlib import Path


def fsync_dir(path: str | Path) -> None:
    """Make a rename or a new file in ``path`` durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: str | Path, data: bytes, fsync: bool = True, tmp_name: str | None = None) -> None:
    """Write ``data`` through a temporary file in the same folder and a rename.

    A crash leaves either the old file or the new one, never half of one.  ``tmp_name``
    names the temporary file (default: ``.NAME.tmp``, hidden from image and CSV globs).
    """
    p = Path(path)
    tmp = p.with_name(tmp_name or f".{p.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        if fsync:
            os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, p)
    if fsync:
        fsync_dir(p.parent)


def check_out_folder(path: str | Path, option: str = "--out") -> None:
    """Refuse an output folder path that names an existing file (before anything is computed)."""
    from stereopath.device.errors import ConfigError

    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{option} {p}: exists and is not a folder")


def process_umask() -> int:
    """The process umask, read without changing it where the system allows (Linux /proc)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)  # no /proc: set and restore (not thread-safe, so only as a fallback)
    os.umask(mask)
    return mask
