"""Line-oriented reading of the ASL CSV files (and our appended text files).

The recorder only ever appends whole lines, so after a crash or power cut a file can end in at
most one partial line, the one being written when it stopped.  :func:`read_rows` therefore
drops a final line without a newline, with a warning; every other line must be well formed,
and a malformed one raises :class:`DatasetError` naming the file and the line number.
"""

from __future__ import annotations

import logging
from pathlib import Path

from stereopath.device.errors import DatasetError

log = logging.getLogger(__name__)


def read_lines(path: Path, torn_tail_ok: bool = True) -> list[tuple[int, str]]:
    """``(line_number, text)`` of every non-blank, non-comment line of ``path``.

    With ``torn_tail_ok`` a final line that lacks its newline is logged and ignored
    (the file was being appended to when the writer stopped).
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(f"file not found: {path}") from None
    except IsADirectoryError:
        raise DatasetError(f"{path}: is a directory, expected a file") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
    lines = text.split("\n")
    tail = lines.pop()  # text after the last newline ("" when the file ends with one)
    out: list[tuple[int, str]] = []
    for i, line in enumerate(lines, 1):
        s = line.strip()
        if s and not s.startswith("#"):
            out.append((i, s))
    s = tail.strip()
    if s and not s.startswith("#"):
        if torn_tail_ok:
            log.warning("%s:%d: ignoring the final line, which has no newline (torn write?): %r",
                        path, len(lines) + 1, s[:80])
        else:
            out.append((len(lines) + 1, s))
    return out


def read_rows(path: Path, ncols: int | tuple[int, int], torn_tail_ok: bool = True) -> list[tuple[int, list[str]]]:
    """Comma-separated rows with ``ncols`` fields (or ``(min, max)``); wrong counts raise."""
    lo, hi = (ncols, ncols) if isinstance(ncols, int) else ncols
    rows = []
    for i, s in read_lines(path, torn_tail_ok):
        fields = [f.strip() for f in s.split(",")]
        if not lo <= len(fields) <= hi:
            want = str(lo) if lo == hi else f"{lo} to {hi}"
            raise DatasetError(f"{path}:{i}: expected {want} comma-separated values, got {len(fields)}: {s[:80]!r}")
        rows.append((i, fields))
    return rows


INT64_MIN, INT64_MAX = -2**63, 2**63 - 1


def parse_int(path: Path, line: int, text: str, what: str = "timestamp") -> int:
    """``text`` as an integer that fits int64 (timestamps are stored as int64 nanoseconds)."""
    try:
        v = int(text)
    except ValueError:
        raise DatasetError(f"{path}:{line}: {what} is not an integer: {text!r}") from None
    if not INT64_MIN <= v <= INT64_MAX:
        raise DatasetError(f"{path}:{line}: {what} is out of the 64-bit integer range: {text!r}")
    return v


def parse_float(path: Path, line: int, text: str, what: str = "value") -> float:
    try:
        v = float(text)
    except ValueError:
        raise DatasetError(f"{path}:{line}: {what} is not a number: {text!r}") from None
    if v != v or v in (float("inf"), float("-inf")):
        raise DatasetError(f"{path}:{line}: {what} is not finite: {text!r}")
    return v
