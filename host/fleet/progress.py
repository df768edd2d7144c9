"""The terminal progress display of a fleet run: counts and the stage of each running session.

On a terminal one status line is redrawn in place; elsewhere (a log file, CI) a line is printed
whenever a session changes state or stage.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any, TextIO

from stereopath.host.fleet.state import SessionState, count_states


def status_line(states: Sequence[SessionState]) -> str:
    """``2/4 done, 1 running, 0 failed | s1: ba, s3: tracks (attempt 2)``."""
    c = count_states(states)
    head = f"{c['done']}/{len(states)} done, {c['running']} running, {c['failed']} failed"
    if c["interrupted"]:
        head += f", {c['interrupted']} interrupted"
    running = [f"{s.session.id}: {s.stage}" + (f" (attempt {s.attempts})" if s.attempts > 1 else "")
               for s in states if s.status == "running"]
    return head + (" | " + ", ".join(running) if running else "")


class FleetProgress:
    """``on_update`` callback for :func:`stereopath.host.fleet.runner.run_fleet`."""

    def __init__(self, stream: TextIO | None = None, width: int = 160) -> None:
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.width = width
        self.last = ""
        self.reported: set[tuple[str, str]] = set()

    def __call__(self, states: Sequence[SessionState]) -> None:
        for s in states:  # finished sessions get a line of their own
            if s.status in ("done", "failed") and (s.session.id, s.status) not in self.reported:
                self.reported.add((s.session.id, s.status))
                detail = s.error if s.status == "failed" else _done_detail(s.result or {})
                self._line(f"{s.session.id}: {s.status}" + (f" ({detail})" if detail else ""))
        line = status_line(states)
        if line != self.last:
            self.last = line
            if self.tty:
                self.stream.write("\r\033[K" + line[: self.width])
                self.stream.flush()
            else:
                self._line(line)

    def _line(self, text: str) -> None:
        if self.tty:
            self.stream.write("\r\033[K")
        self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.tty and self.last:
            self.stream.write("\n")
            self.stream.flush()


def _done_detail(r: dict[str, Any]) -> str:
    parts = []
    if r.get("ate_rmse_m") is not None:
        parts.append(f"ATE {r['ate_rmse_m'] * 1000:.3f} mm")
    if r.get("wall_s") is not None:
        parts.append(f"{r['wall_s']:.1f} s")
    st = r.get("stages") or {}
    if st and all(v == "reused" or v == "skipped" for v in st.values()):
        parts.append("all stages reused")
    return ", ".join(parts)
