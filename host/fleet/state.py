"""What the fleet driver knows of a run: the sessions' settings and states, and the run's result
(read by :mod:`stereopath.host.fleet.runner`, which updates them, and :mod:`stereopath.host.fleet.summary`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from stereopath.host.fleet.sessions import FleetSession


# memory declared per session task (GB): the peak resident set of one reprocessing, with and without the
# dense model, that benchmarks/bench_scale.py measures on the simulated scan from 200 to 4,000 frames
# (with the model, its stage is the peak; without it, one bundle-adjustment window is), rounded up to
# half a GB: docs/reprocess.md has the figures
TASK_MEMORY_GB = 2.5
TASK_MEMORY_NO_MAP_GB = 2.0


@dataclass(frozen=True)
class ReprocessSettings:
    """The one-session command's settings, the same for every session of the run."""

    preset: str = "standard"
    do_map: bool = True
    map_preset: str = "auto"
    imu_priors: bool = False
    force: bool = False  # recompute every stored stage (first attempt of each task only)
    strict: bool = False  # stop a session at its first unreadable frame (default: skip it, counted)


@dataclass
class SessionState:
    session: FleetSession
    out: Path  # DIR/<session id> as the driver sees it
    status: str = "pending"  # pending | running | done | failed | interrupted
    stage: str | None = None  # the stage running now (while running)
    stored: list[str] = field(default_factory=list)
    attempts: int = 0
    node: str | None = None
    pid: int | None = None  # worker process of the latest attempt
    error: str | None = None
    result: dict[str, Any] | None = None
    first: dict[str, Any] | None = None  # what the first of the session's two tasks reported
    started: float | None = None
    finished: float | None = None


@dataclass
class FleetResult:
    out_dir: Path
    sessions: list[SessionState]
    wall_s: float
    cluster: dict[str, Any]
    interrupted: bool = False

    def counts(self) -> dict[str, int]:
        return count_states(self.sessions)


def count_states(states: Sequence[SessionState]) -> dict[str, int]:
    out = {k: 0 for k in ("done", "running", "failed", "pending", "interrupted")}
    for s in states:
        out[s.status] = out.get(s.status, 0) + 1
    return out
