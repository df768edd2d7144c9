"""Crash-safe file writes: the one temporary-file-and-rename helper of the tree.

Every file that must never be seen half written (manifests, status files, spooled keyframes,
stored keyframes, models, reports, key files) goes through :func:`write_atomic` or one of its
text/JSON forms, so there is one temporary-name pattern (``.NAME.PID.tmp`` in the same folder,
hidden from image and CSV globs) and one durability rule.
"""

from __future__ import annotations

import json
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Iterator


def fsync_dir(path: str | Path) -> None:
    """Make a rename or a new file in ``path`` durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def temp_path(path: str | Path, keep_suffix: bool = False) -> Path:
    """The temporary name a write of ``path`` goes through (same folder, hidden, per process).

    ``keep_suffix`` repeats the file's suffix at the end, for writers that pick the format from it.
    """
    p = Path(path)
    return p.with_name(f".{p.name}.{os.getpid()}.tmp" + (p.suffix if keep_suffix else ""))


def is_temp(path: str | Path) -> bool:
    """A left-over temporary file of an interrupted write (to sweep when a folder is reopened)."""
    name = Path(path).name
    return name.endswith(".tmp") or ".tmp." in name


def write_atomic(path: str | Path, data: bytes, fsync: bool = True, mode: int | None = None) -> None:
    """Write ``data`` through a temporary file in the same folder and a rename.

    A crash leaves either the old file or the new one, never half of one.  ``mode`` sets the
    permissions exactly (whatever the process umask), e.g. ``0o644`` for a file other users
    read, ``0o600`` for a secret; by default the umask applies to ``0o644``.
    """
    p = Path(path)
    tmp = temp_path(p)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644 if mode is None else mode)
    try:
        if mode is not None:
            os.fchmod(fd, mode)
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        if fsync:
            os.fsync(fd)
    except BaseException:
        os.close(fd)
        tmp.unlink(missing_ok=True)
        raise
    os.close(fd)
    try:
        os.replace(tmp, p)
    except BaseException:  # e.g. ``path`` is a directory: leave no temporary file behind
        tmp.unlink(missing_ok=True)
        raise
    if fsync:
        fsync_dir(p.parent)


def check_out_folder(path: str | Path, option: str = "--out", inputs: Iterable[str | Path] = (),
                     not_a_session: bool = True, instead: str | Path | None = None) -> None:
    """Refuse, before anything is computed, an output folder path that names an existing file, that
    is one of the ``inputs`` folders, the file system root, a recorded session (``mav0/``) or a folder
    inside one (:func:`check_out_location`): run outputs would replace recorded files, e.g. a session's
    on-board ``trajectory.tum``; or that cannot be written: the folder itself when it exists, else the
    nearest folder above it that does (where it would be made) - read-only file system or no permission.
    ``instead``: the folder a refusal suggests (default: ``<path>-out`` beside it).  ``not_a_session``
    is kept for callers; every output folder is held to the session rule."""
    from stereopath.device.errors import ConfigError

    try:
        _check_out_folder(Path(path), option, inputs, not_a_session, instead)
    except OSError as exc:  # a name too long, a loop of links...: the path itself is unusable
        raise ConfigError(f"{option} {path}: {exc.strerror or exc}") from None


def recorded_session_around(path: str | Path) -> Path | None:
    """The recorded session (a folder holding ``mav0/``: ours, EuRoC's, TUM VI's) that ``path`` is or lies
    in, symbolic links resolved; None when there is none."""
    here = Path(path).resolve()
    for folder in (here, *here.parents):
        if (folder / "mav0").is_dir():
            return folder
    return None


def check_out_location(path: str | Path, option: str = "--out", instead: str | Path | None = None) -> None:
    """The rules every command that writes applies to where it writes, before anything is computed: never the
    file system root, never a recorded session (a folder holding ``mav0/``) nor a folder inside one (a
    run's files would mix with, or replace, what was recorded).  ``instead``: the folder a refusal suggests.
    OSError (a name too long...) is the caller's: :func:`check_out_folder` turns it into a ConfigError."""
    from stereopath.device.errors import ConfigError

    p = Path(path)
    here = p.resolve()
    if here == Path(here.anchor):
        raise ConfigError(f"{option} {p}: is the file system root; the rule: outputs go into a folder of their own "
                          f"(give one, e.g. /tmp/stereopath-out)")
    session = recorded_session_around(here)
    if session is None:
        return
    other = instead if instead is not None else session.parent / (session.name + "-out")
    if session == here:
        raise ConfigError(f"{option} {p}: holds a recorded session (mav0/); the rule: outputs never go into a "
                          f"recorded session, its recorded files would be replaced (give another folder, e.g. "
                          f"{other})")
    raise ConfigError(f"{option} {p}: is inside the recorded session {session}; the rule: outputs never go into a "
                      f"recorded session or a folder of it (give a folder outside it, e.g. {other})")


def _check_out_folder(p: Path, option: str, inputs: Iterable[str | Path], not_a_session: bool,
                      instead: str | Path | None) -> None:
    from stereopath.device.errors import ConfigError

    other = instead if instead is not None else p.resolve().parent / (p.resolve().name + "-out")
    for src in inputs:
        if Path(src).is_dir() and p.resolve() == Path(src).resolve():
            raise ConfigError(f"{option} {p}: is the input folder {src}; its recorded files would be replaced "
                              f"(give another folder, e.g. {other})")
    check_out_location(p, option, instead=instead)
    where = folder_or_parent(p, f"{option} {p}")
    if not os.access(where, os.W_OK | os.X_OK):
        why = "read-only file system" if _read_only_fs(where) else "no permission"
        raise ConfigError(f"{option} {p}: cannot write in {where} ({why})")


def folder_or_parent(path: str | Path, what: str) -> Path:
    """The folder ``path`` is, or the nearest existing folder it would be made in (ConfigError, naming
    ``what``, when ``path`` or that nearest existing ancestor is not a folder)."""
    from stereopath.device.errors import ConfigError

    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{what}: exists and is not a folder")
    where = p.absolute()
    while not where.exists() and where != where.parent:
        where = where.parent
    if not where.is_dir():
        raise ConfigError(f"{what}: {where} is not a folder")
    return where


def check_out_file(path: str | Path, option: str = "--out", example: str = "out.yaml") -> Path:
    """Refuse, before anything is computed, an output file path that is a folder or another non-file,
    or whose folder is a file or cannot be written (see :func:`check_out_folder`)."""
    from stereopath.device.errors import ConfigError

    p = Path(path)
    try:
        if p.is_dir():
            raise ConfigError(f"{option} {p}: is a folder; give the file to write, e.g. {p / example}")
        if p.exists() and not p.is_file():
            raise ConfigError(f"{option} {p}: exists and is not a regular file")
    except OSError as exc:  # a name too long, a loop of links...
        raise ConfigError(f"{option} {p}: {exc.strerror or exc}") from None
    check_out_folder(p.parent, option=f"{option} {p}: the folder")
    return p


def _read_only_fs(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def cut_torn_tail(path: str | Path, window: int = 1 << 16) -> int:
    """Cut a last line that lacks its newline (a write cut short by a full disk or a power cut) off a
    text file that is appended to, so that the next line does not join it; returns the bytes cut.
    A missing or empty file is left alone; a file with no newline in its last ``window`` bytes is
    left as it is (not a file of lines)."""
    p = Path(path)
    try:
        with p.open("rb+") as fh:
            size = fh.seek(0, os.SEEK_END)
            if size == 0:
                return 0
            fh.seek(max(0, size - window))
            tail = fh.read()
            if tail.endswith(b"\n"):
                return 0
            nl = tail.rfind(b"\n")
            if nl < 0 and size > window:
                return 0
            keep = size - len(tail) + nl + 1
            fh.truncate(keep)
            return size - keep
    except FileNotFoundError:
        return 0


def write_renamed_open(path: str | Path, data: bytes) -> int:
    """Write ``data`` through the temporary name and rename it now, returning the still open descriptor.

    For writers that make many files durable in batches: the caller fsyncs (and closes) the
    descriptors and the folder later, at its own pace.
    """
    p = Path(path)
    tmp = temp_path(p)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.replace(tmp, p)
    except BaseException:
        os.close(fd)
        tmp.unlink(missing_ok=True)
        raise
    return fd


@contextmanager
def replacing(path: str | Path, fsync: bool = False, mode: int | None = None) -> Iterator[Path]:
    """For writers that need a file name (Open3D, matplotlib): ``with replacing(p) as tmp: write(tmp)``.

    The temporary path ends with ``path``'s suffix; when the block succeeds it replaces ``path``,
    when it raises the temporary file is removed and ``path`` is left as it was.
    """
    p = Path(path)
    tmp = temp_path(p, keep_suffix=True)
    try:
        yield tmp
        if mode is not None:
            os.chmod(tmp, mode)
        if fsync:
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        os.replace(tmp, p)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if fsync:
        fsync_dir(p.parent)


def load_json(path: str | Path) -> Any:
    """A JSON file's value; nesting too deep for the parser is a :class:`json.JSONDecodeError` like any
    other invalid JSON (a ValueError, as is undecodable text), so callers catch one family."""
    text = Path(path).read_text()
    try:
        return json.loads(text)
    except RecursionError:
        raise json.JSONDecodeError("nested too deeply", text[:64], 0) from None


def write_text_atomic(path: str | Path, text: str, fsync: bool = True, mode: int | None = None) -> None:
    """:func:`write_atomic` of UTF-8 text."""
    write_atomic(path, text.encode("utf-8"), fsync=fsync, mode=mode)


def write_json_atomic(path: str | Path, data: object, indent: int | None = 2, fsync: bool = True,
                      mode: int | None = None) -> None:
    """:func:`write_atomic` of ``data`` as JSON (a trailing newline; unknown types as ``str``)."""
    write_text_atomic(path, json.dumps(data, indent=indent, default=str) + "\n", fsync=fsync, mode=mode)
