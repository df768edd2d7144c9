"""Schedule sessions on Ray: start a local Ray or join a cluster, bounded in-flight tasks, faults.

Each session runs through the one-session pipeline (:func:`stereopath.host.fleet.worker.reprocess_task`)
as two Ray tasks, its stages in order: the first stops once the ``estimate`` stage is stored (and
reports the session's keyframes: what the rest will cost), the second runs the rest from the
stored estimate.  Sessions run in parallel; the costliest estimated sessions go first, so that a
long session does not run alone at the end (see :class:`_Scheduler`).  Each task declares its
resources (``task_cpus`` CPUs and ``task_memory_gb`` of memory: the dense model needs about 1 GB)
and runs that many threads inside; the driver keeps no more tasks in flight than the cluster
holds (the smaller of its CPUs and memory divided by one task's).

Faults: a session whose task raises (bad input: a :class:`StereopathError`) is reported failed
and the others go on; a task whose worker process or node dies is retried by Ray (``retries``
times) and the retry resumes from the session's stored stages; Ctrl-C cancels the running tasks,
writes the summary and re-raises :class:`KeyboardInterrupt` (a rerun resumes every session from
its stored stages; nothing finished is recomputed).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

from stereopath.device.errors import ConfigError, StereopathError
from stereopath.host.fleet.sessions import FleetSession, PathMap, frame_count
from stereopath.host.fleet.state import TASK_MEMORY_GB, FleetResult, ReprocessSettings, SessionState
from stereopath.host.fleet.worker import STAGE_ORDER

if TYPE_CHECKING:
    from ray.actor import ActorHandle

log = logging.getLogger(__name__)

GB = 1024**3


@dataclass(frozen=True)
class FleetOptions:
    """Where and how the tasks run."""

    ray: str = "auto"  # "auto": start a local Ray; otherwise the address of a running cluster
    num_cpus: int | None = None  # CPUs of the local Ray (None: the machine's); ignored with an address
    task_cpus: float = 1.0  # CPUs declared per session task
    task_memory_gb: float = TASK_MEMORY_GB  # memory declared per session task
    max_in_flight: int | None = None  # None: as many as the cluster holds
    retries: int = 3  # re-runs of a task whose worker or node died
    path_map: PathMap = field(default_factory=PathMap)
    poll_s: float = 0.5  # how often the driver looks at the progress board
    ray_logs: bool = False  # forward the workers' log output to this terminal
    spread: bool = True  # a session's independent pieces (per keyframe, per gap) as Ray tasks of their own

    def __post_init__(self) -> None:
        if not self.ray or not isinstance(self.ray, str):
            raise ConfigError("ray must be 'auto' or a cluster address such as 10.0.0.5:6379")
        if self.num_cpus is not None and self.num_cpus < 1:
            raise ConfigError(f"num_cpus must be at least 1, got {self.num_cpus}")
        if not 0 < self.task_cpus <= 1024:
            raise ConfigError(f"task_cpus must be in (0, 1024], got {self.task_cpus}")
        if not 0 <= self.task_memory_gb <= 4096:
            raise ConfigError(f"task_memory_gb must be in [0, 4096], got {self.task_memory_gb}")
        if self.max_in_flight is not None and self.max_in_flight < 1:
            raise ConfigError(f"max_in_flight must be at least 1, got {self.max_in_flight}")
        if not 0 <= self.retries <= 100:
            raise ConfigError(f"retries must be in [0, 100], got {self.retries}")
        if not 0.01 <= self.poll_s <= 60:
            raise ConfigError(f"poll_s must be in [0.01, 60], got {self.poll_s}")


def _import_ray() -> ModuleType:
    try:
        import ray
    except ImportError as exc:
        raise ConfigError("fleet reprocessing needs Ray: pip install 'stereopath[fleet]'") from exc
    return ray


def keep_workers(cpus: int) -> dict[str, int]:
    """Ray settings that keep a local Ray's idle workers: up to two per CPU plus the progress actor
    (the session tasks waiting for their pieces, and the pieces) for up to a minute, instead of one
    per CPU for a second: a new worker imports Ray, OpenCV, GTSAM and Open3D again (1-2 s of CPU),
    and a session's pieces come in bursts, stage after stage."""
    return {"num_workers_soft_limit": 2 * cpus + 2, "idle_worker_killing_time_threshold_ms": 60_000}


def connect(options: FleetOptions) -> tuple[Any, bool]:
    """Ray, started locally or joined; ``owned`` is True when this call started it (shut it down)."""
    ray = _import_ray()
    if ray.is_initialized():
        return ray, False
    kw: dict[str, Any] = {"include_dashboard": False, "log_to_driver": options.ray_logs,
                          "logging_level": logging.WARNING}
    try:
        if options.ray == "auto":
            cpus = options.num_cpus or os.cpu_count() or 1
            ray.init(address="local", num_cpus=cpus, _system_config=keep_workers(cpus), **kw)
        else:
            ray.init(address=options.ray, **kw)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        what = "start a local Ray" if options.ray == "auto" else f"join the Ray cluster at {options.ray}"
        if "InvalidAuthToken" in f"{exc} {exc.__cause__}":
            raise ConfigError(f"cannot {what}: the cluster uses token authentication and this process has no "
                              f"valid token: export RAY_AUTH_MODE=token (the cluster's token in ~/.ray/auth_token "
                              f"or RAY_AUTH_TOKEN)") from exc
        raise ConfigError(f"cannot {what}: {exc}") from exc
    return ray, True


def capacity(resources: dict[str, float], options: FleetOptions) -> int:
    """How many session tasks the cluster holds at once (CPU and memory), at least one."""
    cpus = float(resources.get("CPU", 0.0))
    mem = float(resources.get("memory", 0.0))
    n = math.floor(cpus / options.task_cpus + 1e-9)
    if options.task_memory_gb > 0:
        n = min(n, math.floor(mem / (options.task_memory_gb * GB) + 1e-9))
    if n < 1:
        raise ConfigError(f"the Ray cluster ({cpus:g} CPUs, {mem / GB:.1f} GB memory) cannot hold one task of "
                          f"{options.task_cpus:g} CPUs and {options.task_memory_gb:g} GB")
    return n if options.max_in_flight is None else min(n, options.max_in_flight)


def _error_text(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None)
    if isinstance(cause, BaseException):
        name = type(cause).__name__
        return f"{name}: {cause}" if isinstance(cause, StereopathError) else f"{name}: {cause} (a bug: see the log)"
    first = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {first[0] if first else ''}".rstrip(": ")


def cluster_info(ray: ModuleType, options: FleetOptions) -> dict[str, Any]:
    """The cluster as ``fleet.json`` records it, with ``max_in_flight`` (:func:`capacity`)."""
    res = ray.cluster_resources()
    return {"address": options.ray, "nodes": len([n for n in ray.nodes() if n.get("Alive")]),
            "cpus": res.get("CPU"), "memory_gb": round(res.get("memory", 0.0) / GB, 2),
            "task_cpus": options.task_cpus, "task_memory_gb": options.task_memory_gb,
            "max_in_flight": capacity(res, options)}


def submission_order(states: Sequence[SessionState]) -> list[SessionState]:
    """Largest sessions (most frames) first, so that a long one does not run alone at the end."""
    return sorted(states, key=lambda st: -frame_count(st.session.path))


# the lead session's stages that are mostly independent pieces (tracks: each keyframe's keypoints,
# each gap's matching), and how many CPUs such a stage keeps busy (its gaps: the track window)
WIDE_STAGES = ("tracks",)
LEAD_WIDTH = 8
# the rest of a session costs about one unit per offline keyframe (its keypoints, matching, bundle
# adjustment) and one per FRAMES_PER_KEYFRAME frames (the per-frame work of tracks, ba and map),
# fitted on the one-thread CPU of bench_fleet's sessions
FRAMES_PER_KEYFRAME = 56
# the share of a keyframe-heavy session's rest that runs on one core after its wide stage (bundle
# adjustment, fusion), and after its bundle adjustment
SERIAL_SHARE = 0.35
LEFT_AFTER = {"tracks": SERIAL_SHARE, "ba": SERIAL_SHARE / 3}


def _cost(st: SessionState) -> float:
    """What the rest of a session costs, from its first part (:func:`~stereopath.host.fleet.worker.first_part`):
    its offline keyframes as guessed (else its estimator's keyframes) and its frames."""
    f = st.first or {}
    kf = f.get("offline_keyframes")
    kf = f.get("keyframes") if kf is None else kf
    frames = f.get("frames")
    frames = frame_count(st.session.path) if frames is None else frames
    return float(kf or 0) + frames / FRAMES_PER_KEYFRAME


def _left(st: SessionState) -> float:
    """What is left of a session's rest by the stages it has stored (:func:`_cost` before its tracks)."""
    done = [LEFT_AFTER[s] for s in LEFT_AFTER if s in st.stored]
    return _cost(st) * min(done, default=1.0)


class _Scheduler:
    """Submits session tasks while the cluster has room and records how each one ends.

    A session runs as two tasks, its stages in order: "first" (the estimate, which also measures
    the session: its keyframes) and "rest" (tracks, ba, map, outputs).  A free slot takes the rest
    of the costliest estimated session once ``2 * slots`` sessions wait for theirs (or every first
    part has ended), else the next first part: the long sessions start early instead of running
    alone at the end.  A rest that is the fleet's critical path (:meth:`_leads`) is the lead: its
    pieces go first to the CPUs that other tasks free, and the other rests wait while it is in its
    wide stage as far as its serial stages leave room for them (:meth:`_startable`).  A new task starts
    only on a CPU that is idle.  With ``force`` a session is one task ("all": a split would reuse
    the later stages).
    """

    def __init__(self, ray: ModuleType, states: list[SessionState], settings: ReprocessSettings, options: FleetOptions,
                 after_stage: Callable[[str], None] | None) -> None:
        from stereopath.host.fleet.worker import IdleCpus, ProgressBoard, reprocess_task

        self.ray, self.options, self.after_stage = ray, options, after_stage
        self.kwargs = dataclasses.asdict(settings)
        self.split = not settings.force
        self.first = submission_order(states)  # sessions whose first task is still to start
        self.rest: list[SessionState] = []  # estimated sessions waiting for their second task
        self.inflight: dict[Any, tuple[SessionState, str]] = {}
        self.lead_refs: set[Any] = set()  # the running rests that lead (see :meth:`_leads`)
        self.idle_cpus = IdleCpus(max_age_s=0.0)  # asked afresh: each answer may start a task
        self.board = ray.remote(num_cpus=0)(ProgressBoard).remote()
        self.task = ray.remote(reprocess_task)
        self.task_opts: dict[str, Any] = {"num_cpus": options.task_cpus, "max_retries": options.retries,
                                          "retry_exceptions": False}
        if options.task_memory_gb > 0:
            self.task_opts["memory"] = int(options.task_memory_gb * GB)
        self.threads = max(1, math.ceil(options.task_cpus))  # threads inside a task: its CPUs

    def busy(self) -> bool:
        return bool(self.first or self.rest or self.inflight)

    def _next(self, slots: int) -> tuple[SessionState, str] | None:
        estimating = any(p == "first" for _, p in self.inflight.values())
        if self.rest and (len(self.rest) >= 2 * slots or not (self.first or estimating)):
            st = self._startable(slots)
            if st is not None:
                self.rest.remove(st)
                return st, "rest"
        if self.first:
            return self.first.pop(0), ("first" if self.split else "all")
        return None

    def _startable(self, slots: int) -> SessionState | None:
        """The waiting rest to start now, None while they wait for a lead's wide stage.

        The costliest, unless a lead is in its wide stage (:data:`WIDE_STAGES`) on a cluster no wider
        than it can use (:data:`LEAD_WIDTH`): a session started then holds a core the lead's pieces
        need for its whole run, and delays the lead by about its cost over the lead's cores.  The
        lead's serial stages leave :data:`SERIAL_SHARE` of its cost on each core it does not use:
        the rests wait as long as they fit there, and when they do not, the cheapest one whose start
        makes the others fit starts now (else the costliest): held, they would run on after the lead."""
        st = max(self.rest, key=_cost)
        wide = [o for ref, (o, p) in self.inflight.items() if ref in self.lead_refs
                and any(w not in o.stored for w in WIDE_STAGES)]
        if not wide or self._leads(st, "rest", slots) or len(self.inflight) - len(wide) < slots - LEAD_WIDTH:
            return st
        room = SERIAL_SHARE * max(_cost(o) for o in wide) * max(slots - len(wide), 1)
        excess = sum(_cost(o) for o in self.rest) - room
        if excess <= 0:
            return None
        enough = [o for o in self.rest if _cost(o) >= excess]
        return min(enough, key=_cost) if enough else st

    def _idle(self) -> bool:
        """Whether a CPU for one more session task is idle: a CPU the lead session's queued pieces
        take as soon as it is freed is not (the critical path first, see :class:`RaySpreader`)."""
        return self.idle_cpus() >= self.options.task_cpus

    def _leads(self, st: SessionState, part: str, slots: int) -> bool:
        """Whether the rest of ``st`` is the fleet's critical path when it starts: no estimated session,
        waiting for its rest or running it, costs more (:func:`_cost`; a running one: what it has
        left, :func:`_left`), and it costs more than a slot's share of all the work left (the
        sessions not yet estimated counted at the mean cost of the others).  In a batch of similar
        sessions nobody leads: whole sessions fill the cores and pieces go only to idle ones."""
        if part != "rest":
            return False
        running = [o for o, p in self.inflight.values() if p == "rest" and o is not st]
        known = [_cost(o) for o in self.rest if o is not st] + [_left(o) for o in running]
        mine = _cost(st)
        if any(c > mine for c in known):
            return False
        unknown = len(self.first) + sum(1 for _, p in self.inflight.values() if p != "rest")
        total = mine + sum(known) + unknown * (mine + sum(known)) / (1 + len(known))
        return mine * slots > total

    def submit(self, slots: int) -> None:
        from stereopath.host.fleet.worker import TaskPlan

        pm = self.options.path_map
        while len(self.inflight) < slots and (not self.inflight or self._idle()) and (nxt := self._next(slots)) is not None:
            st, part = nxt
            lead = self._leads(st, part, slots)
            ref = self.task.options(name=f"reprocess {st.session.id} ({part})", **self.task_opts).remote(
                st.session.id, pm.to_worker(st.session.path), pm.to_worker(st.out), self.kwargs, self.board,
                self.after_stage, TaskPlan(part, self.threads, self.options.spread, lead))
            self.inflight[ref] = (st, part)
            if lead:
                self.lead_refs.add(ref)
            st.status, st.stage = "running", (STAGE_ORDER[1] if part == "rest" else STAGE_ORDER[0])
            st.started = st.started or time.time()

    def collect(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a task to end; True when one did."""
        ready, _ = self.ray.wait(list(self.inflight), num_returns=1, timeout=timeout_s)
        for ref in ready:
            st, part = self.inflight.pop(ref)
            self.lead_refs.discard(ref)
            try:
                r = self.ray.get(ref)
            except self.ray.exceptions.RayError as exc:
                st.status, st.stage, st.error, st.finished = "failed", None, _error_text(exc), time.time()
                log.warning("session %s failed: %s", st.session.id, st.error)
                continue
            if r.get("status") == "estimated":  # the first part: queue the rest
                st.first, st.status, st.stage = r, "pending", None
                self.rest.append(st)
                continue
            if st.first:  # the session's figures cover both tasks
                r["wall_s"] = round(r["wall_s"] + st.first["wall_s"], 3)
                r["cpu_s"] = round(r["cpu_s"] + st.first["cpu_s"], 3)
                r["pieces"] = r.get("pieces", 0) + st.first.get("pieces", 0)
                r["stages"] = {**r["stages"], **st.first["stages"]}
            st.result, st.status, st.stage, st.finished = r, "done", None, time.time()
            st.stored = [s for s in STAGE_ORDER if r["stages"].get(s) in ("computed", "reused")]
            st.node = r.get("node")
        return bool(ready)

    def cancel(self) -> None:
        """Stop every running task (Ctrl-C, or an unexpected error in the driver)."""
        for ref, (st, _) in self.inflight.items():
            self.ray.cancel(ref, force=True)
            st.status, st.stage = "interrupted", None
        for st in self.rest:
            st.status = "interrupted"
        self.inflight.clear()
        self.lead_refs.clear()
        self.rest.clear()


def run_fleet(sessions: Sequence[FleetSession], out_dir: str | Path, settings: ReprocessSettings = ReprocessSettings(),
              options: FleetOptions = FleetOptions(), on_update: Callable[[list[SessionState]], None] | None = None,
              after_stage: Callable[[str], None] | None = None) -> FleetResult:
    """Reprocess ``sessions`` into ``out_dir/<session id>/`` on Ray and write the fleet summary.

    ``on_update(states)`` is called in this process whenever a session changes (progress display).
    ``after_stage(name)`` runs inside the task after each stored stage (tests inject faults with
    it; it must be picklable).  Uses an already initialised Ray as it is (and leaves it running).
    """
    from stereopath.host.fleet.summary import write_summary

    out = Path(out_dir).absolute()
    if out.exists() and not out.is_dir():
        raise StereopathError(f"output {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    states = [SessionState(s, out / s.id) for s in sessions]
    t0 = time.perf_counter()
    ray, owned = connect(options)
    cluster: dict[str, Any] = {}
    result = FleetResult(out, states, 0.0, cluster)
    sched: _Scheduler | None = None

    def save() -> None:
        result.wall_s = time.perf_counter() - t0
        write_summary(out, result, settings)

    try:
        cluster.update(cluster_info(ray, options))
        log.info("Ray: %s nodes, %s CPUs; %d session tasks at a time", cluster["nodes"], cluster["cpus"],
                 cluster["max_in_flight"])
        sched = _Scheduler(ray, states, settings, options, after_stage)
        save()
        last_poll = 0.0
        while sched.busy():
            sched.submit(cluster["max_in_flight"])
            changed = sched.collect(options.poll_s)
            if changed or time.perf_counter() - last_poll >= options.poll_s:
                last_poll = time.perf_counter()
                changed |= _poll(ray, sched.board, states, settings)
            if changed:
                save()
                if on_update is not None:
                    on_update(states)
    except KeyboardInterrupt:
        result.interrupted = True
        raise
    finally:
        if sched is not None:
            sched.cancel()  # nothing left running after Ctrl-C or an unexpected error here
        if cluster:
            try:
                save()
            except OSError as exc:
                log.error("cannot write the fleet summary into %s: %s", out, exc)
        if owned:
            ray.shutdown()
    result.wall_s = time.perf_counter() - t0
    return result


def _poll(ray: ModuleType, board: ActorHandle, states: list[SessionState], settings: ReprocessSettings) -> bool:
    """Copy the board's view (attempts, node, stored stages) into the running sessions' states."""
    try:
        snap = ray.get(board.snapshot.remote(), timeout=10)
    except ray.exceptions.GetTimeoutError:
        return False
    order = STAGE_ORDER if settings.do_map else STAGE_ORDER[:-1]
    changed = False
    for st in states:
        e = snap.get(st.session.id)
        if not e:
            continue
        st.pid = e.get("pid", st.pid)
        new = (e.get("attempts", 0), e.get("node"), list(e.get("stored", [])))
        if new != (st.attempts, st.node, st.stored):
            st.attempts, st.node, st.stored = new
            changed = True
        if st.status == "running":
            nxt = next((s for s in order if s not in st.stored), order[-1])
            if nxt != st.stage:
                st.stage, changed = nxt, True
    return changed
