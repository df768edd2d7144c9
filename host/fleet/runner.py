"""Schedule sessions on Ray: start a local Ray or join a cluster, bounded in-flight tasks, faults.

One Ray task per session (:func:`stereopath.host.fleet.worker.reprocess_task`): the session's
stages run in order inside it, sessions run in parallel.  Each task declares its resources
(``task_cpus`` CPUs and ``task_memory_gb`` of memory: the dense model needs about 1 GB), and the
driver keeps no more tasks in flight than the cluster holds (the smaller of its CPUs and memory
divided by one task's), submitting the next session as one finishes.

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
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from stereopath.device.errors import ConfigError, StereopathError
from stereopath.host.fleet.sessions import FleetSession, PathMap
from stereopath.host.fleet.worker import STAGE_ORDER

log = logging.getLogger(__name__)

GB = 1024**3


@dataclass(frozen=True)
class FleetOptions:
    """Where and how the tasks run."""

    ray: str = "auto"  # "auto": start a local Ray; otherwise the address of a running cluster
    num_cpus: int | None = None  # CPUs of the local Ray (None: the machine's); ignored with an address
    task_cpus: float = 1.0  # CPUs declared per session task
    task_memory_gb: float = 1.0  # memory declared per session task (the dense model needs ~1 GB)
    max_in_flight: int | None = None  # None: as many as the cluster holds
    retries: int = 3  # re-runs of a task whose worker or node died
    path_map: PathMap = field(default_factory=PathMap)
    poll_s: float = 0.5  # how often the driver looks at the progress board
    ray_logs: bool = False  # forward the workers' log output to this terminal

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


@dataclass(frozen=True)
class ReprocessSettings:
    """The one-session command's settings, the same for every session of the run."""

    preset: str = "standard"
    do_map: bool = True
    map_preset: str = "object"
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


def _import_ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise ConfigError("fleet reprocessing needs Ray: pip install 'stereopath[fleet]'") from exc
    return ray


def connect(options: FleetOptions) -> tuple[Any, bool]:
    """Ray, started locally or joined; ``owned`` is True when this call started it (shut it down)."""
    ray = _import_ray()
    if ray.is_initialized():
        return ray, False
    kw: dict[str, Any] = {"include_dashboard": False, "log_to_driver": options.ray_logs,
                          "logging_level": logging.WARNING}
    try:
        if options.ray == "auto":
            ray.init(address="local", num_cpus=options.num_cpus, **kw)
        else:
            ray.init(address=options.ray, **kw)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        what = "start a local Ray" if options.ray == "auto" else f"join the Ray cluster at {options.ray}"
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


def run_fleet(sessions: Sequence[FleetSession], out_dir: str | Path, settings: ReprocessSettings = ReprocessSettings(),
              options: FleetOptions = FleetOptions(), on_update: Callable[[list[SessionState]], None] | None = None,
              after_stage: Callable[[str], None] | None = None) -> FleetResult:
    """Reprocess ``sessions`` into ``out_dir/<session id>/`` on Ray and write the fleet summary.

    ``on_update(states)`` is called in this process whenever a session changes (progress display).
    ``after_stage(name)`` runs inside the task after each stored stage (tests inject faults with
    it; it must be picklable).  Uses an already initialised Ray as it is (and leaves it running).
    """
    from stereopath.host.fleet.summary import write_summary
    from stereopath.host.fleet.worker import ProgressBoard, reprocess_task

    out = Path(out_dir).absolute()
    if out.exists() and not out.is_dir():
        raise StereopathError(f"output {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    states = [SessionState(s, out / s.id) for s in sessions]
    kwargs = {k: v for k, v in dataclasses.asdict(settings).items()}
    t0 = time.perf_counter()
    ray, owned = connect(options)
    cluster: dict[str, Any] = {}
    interrupted = False
    inflight: dict[Any, SessionState] = {}

    def save() -> None:
        write_summary(out, FleetResult(out, states, time.perf_counter() - t0, cluster, interrupted), settings)

    try:
        res = ray.cluster_resources()
        slots = capacity(res, options)
        cluster.update({"address": options.ray, "nodes": len([n for n in ray.nodes() if n.get("Alive")]),
                        "cpus": res.get("CPU"), "memory_gb": round(res.get("memory", 0.0) / GB, 2),
                        "task_cpus": options.task_cpus, "task_memory_gb": options.task_memory_gb,
                        "max_in_flight": slots})
        log.info("Ray: %s nodes, %s CPUs; %d session tasks at a time", cluster["nodes"], cluster["cpus"], slots)
        board = ray.remote(num_cpus=0)(ProgressBoard).remote()
        task = ray.remote(reprocess_task)
        task_opts: dict[str, Any] = {"num_cpus": options.task_cpus, "max_retries": options.retries,
                                     "retry_exceptions": False}
        if options.task_memory_gb > 0:
            task_opts["memory"] = int(options.task_memory_gb * GB)
        threads = max(1, math.ceil(options.task_cpus))
        queue = list(states)
        save()
        last_poll = 0.0
        while queue or inflight:
            while queue and len(inflight) < slots:
                st = queue.pop(0)
                ref = task.options(name=f"reprocess {st.session.id}", **task_opts).remote(
                    st.session.id, options.path_map.to_worker(st.session.path), options.path_map.to_worker(st.out),
                    kwargs, board, after_stage, threads)
                inflight[ref] = st
                st.status, st.stage, st.started = "running", STAGE_ORDER[0], time.time()
            changed = False
            ready, _ = ray.wait(list(inflight), num_returns=1, timeout=options.poll_s)
            for ref in ready:
                st = inflight.pop(ref)
                st.finished = time.time()
                try:
                    st.result = ray.get(ref)
                    st.status, st.stage = "done", None
                    st.stored = [s for s in STAGE_ORDER if st.result["stages"].get(s) in ("computed", "reused")]
                    st.node = st.result.get("node")
                except ray.exceptions.RayError as exc:
                    st.status, st.stage, st.error = "failed", None, _error_text(exc)
                    log.warning("session %s failed: %s", st.session.id, st.error)
                changed = True
            now = time.perf_counter()
            if now - last_poll >= options.poll_s or changed:
                last_poll = now
                changed |= _poll(ray, board, states, settings)
            if changed:
                save()
                if on_update is not None:
                    on_update(states)
    except KeyboardInterrupt:
        interrupted = True
        for ref, st in inflight.items():
            ray.cancel(ref, force=True)
            st.status, st.stage = "interrupted", None
        inflight.clear()
        raise
    finally:
        if inflight:  # an unexpected error in this loop: do not leave tasks running
            for ref, st in inflight.items():
                ray.cancel(ref, force=True)
                st.status, st.stage = "interrupted", None
        if cluster:
            try:
                save()
            except OSError as exc:
                log.error("cannot write the fleet summary into %s: %s", out, exc)
        if owned:
            ray.shutdown()
    return FleetResult(out, states, time.perf_counter() - t0, cluster, interrupted)


def _poll(ray: Any, board: Any, states: list[SessionState], settings: ReprocessSettings) -> bool:
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
