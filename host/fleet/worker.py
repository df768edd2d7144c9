"""What runs inside a Ray worker: one session through the one-session pipeline.

:func:`reprocess_task` calls :func:`stereopath.host.reprocess.pipeline.reprocess_session` with the
session's folder and its output folder ``DIR/<session id>/`` (both as the worker sees them), so
the stages, their resumable store and every output are exactly those of the one-session
command.  Nothing large crosses Ray: the task reads the images from the session folder, keeps the
stage arrays in the output folder's store, and returns a small summary dict.  A retried task
(the worker died) calls the pipeline again, which reuses every stage already stored.

:class:`ProgressBoard` is the actor the tasks tell when they start (process, node, the stages
already stored) and when a stage is stored; the driver reads it for the progress display.
"""

from __future__ import annotations

import json
import logging
import math
import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:
    from ray.actor import ActorHandle

    from stereopath.host.reprocess.pipeline import ReprocessResult

log = logging.getLogger(__name__)

STAGE_ORDER = ("estimate", "tracks", "ba", "map")  # the order the pipeline runs its stages in
Shared = TypeVar("Shared")  # what every piece of a stage reads
Item = TypeVar("Item")  # one piece's input
Out = TypeVar("Out")  # one piece's result


class ProgressBoard:
    """Per session: attempts, process and node of the latest attempt, stages stored so far.

    A session may run as two tasks (``part`` "first": up to its estimate, then "rest"); each
    counts its own attempts, and the session's ``attempts`` is the largest of them.
    """

    def __init__(self) -> None:
        self.sessions: dict[str, dict[str, Any]] = {}

    def started(self, sid: str, info: dict[str, Any], part: str = "all") -> int:
        """Record an attempt of the task ``part`` of session ``sid``; returns its number (1 for the first)."""
        e = self.sessions.setdefault(sid, {"attempts": 0, "stored": [], "parts": {}})
        e["parts"][part] = e["parts"].get(part, 0) + 1
        e["attempts"] = max(e["parts"].values())
        e.update({k: info[k] for k in ("pid", "node") if k in info})
        e["stored"] = [s for s in STAGE_ORDER if s in info.get("stored", ()) or s in e["stored"]]
        e["started"] = time.time()
        return int(e["parts"][part])

    def stage_done(self, sid: str, name: str) -> None:
        e = self.sessions.setdefault(sid, {"attempts": 0, "stored": [], "parts": {}})
        if name not in e["stored"]:
            e["stored"] = [s for s in STAGE_ORDER if s in e["stored"] or s == name]

    def snapshot(self) -> dict[str, dict[str, Any]]:
        return self.sessions


def stored_stages(out_dir: str | Path) -> list[str]:
    """Stages listed in ``OUT/stages/manifest.json`` (for the display only; ``[]`` if unreadable)."""
    try:
        man = json.loads((Path(out_dir) / "stages" / "manifest.json").read_text())
        return [s for s in STAGE_ORDER if s in (man.get("stages") or {})]
    except (OSError, ValueError, AttributeError):
        return []


def _node() -> str:
    """``IP/node`` of this worker (the first 8 digits of the Ray node id: two nodes may share an IP)."""
    try:
        import ray

        return f"{ray.util.get_node_ip_address()}/{ray.get_runtime_context().get_node_id()[:8]}"
    except Exception:  # noqa: BLE001 - outside Ray (tests of the task body) the host name will do
        return socket.gethostname()


def summarise(res: ReprocessResult, wall_s: float, cpu_s: float) -> dict[str, Any]:
    """The figures of one finished session for ``fleet.json`` (from a ``ReprocessResult``)."""
    rep = res.report or {}
    extra = rep.get("extra") or {}
    mp = extra.get("map") or {}
    ba = extra.get("before_after") or {}
    mesh = Path(res.out_dir) / "mesh.ply"
    return {
        "status": "done",
        "frames": rep.get("frames"),
        "keyframes": (extra.get("estimate") or {}).get("keyframes"),
        "ate_rmse_m": rep.get("ate_rmse_m"),
        "ate_reestimated_m": (ba.get("reestimated") or {}).get("ate_rmse_m"),
        "mesh_vertices": mp.get("mesh_vertices"),
        "mesh_triangles": mp.get("mesh_triangles"),
        "mesh_bytes": mesh.stat().st_size if mesh.is_file() else None,
        "map_error": mp.get("error"),
        "stages": dict(res.stages),
        "stage_seconds": {k: round(float(v), 3) for k, v in res.seconds.items()},
        "files": list(res.files),
        "wall_s": round(wall_s, 3),
        "cpu_s": round(cpu_s, 3),
    }


class _Stop(Exception):
    """Ends the first part of a split session once its ``estimate`` stage is stored."""


_TBB_LIMITS: dict[int, Any] = {}  # oneTBB global_control objects, alive as long as the worker


def limit_tbb(n: int) -> bool:
    """Open3D's TBB pool (the map stage) at ``n`` threads; False when that is not possible.

    Open3D has no Python call for it, so this creates oneTBB's ``global_control(max_allowed_parallelism,
    n)`` through the entry points of the TBB library Open3D ships (``tbb::detail::r1``, oneTBB's stable
    binary interface; the object is three words: value, reserved, parameter 0) and checks the
    active value TBB reports back.
    """
    import ctypes
    import glob

    if n in _TBB_LIMITS:
        return True
    try:
        import open3d

        lib = ctypes.CDLL(sorted(glob.glob(os.path.join(os.path.dirname(open3d.__file__), "libtbb.so*")))[0])
        create = lib._ZN3tbb6detail2r16createERNS0_2d114global_controlE
        active = lib._ZN3tbb6detail2r127global_control_active_valueEi
    except (ImportError, IndexError, OSError, AttributeError) as exc:
        log.warning("cannot limit Open3D's TBB threads: %s", exc)
        return False
    active.restype, active.argtypes = ctypes.c_size_t, [ctypes.c_int]
    ctl = (ctypes.c_size_t * 3)(n, 0, 0)
    create(ctypes.byref(ctl))
    _TBB_LIMITS[n] = ctl
    return int(active(0)) == n


def limit_threads(n: int, tbb: bool = True) -> None:
    """Every thread pool of this worker process at ``n`` threads, the task's CPUs: OpenCV's, every
    BLAS (threadpoolctl) and Open3D's TBB, so that the tasks Ray places by their declared CPUs do not
    oversubscribe the cores.  Results do not depend on it (the stages pin BLAS to one thread; OpenCV
    and TBB split independent work: only the order of the model's elements changes, not the elements)."""
    import cv2
    import scipy.linalg  # noqa: F401 - each library brings its own BLAS, which must be loaded to be limited
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(n)
    threadpool_limits(limits=n)
    if tbb:
        limit_tbb(n)


def run_piece(fn: Callable[[Shared, Item], Out], shared: Shared, item: Item) -> tuple[Out, float]:
    """One piece of a stage's :func:`~stereopath.host.backend.parallel.parallel_map`, as a Ray task
    of one CPU: every pool of its worker at one thread (as in the stage it came from: one BLAS
    thread, so the same bits), then ``fn(shared, item)``; returns it with the CPU seconds it took."""
    limit_threads(1, tbb=False)
    c0 = time.process_time()
    out = fn(shared, item)
    return out, time.process_time() - c0


class IdleCpus:
    """The cluster's idle CPUs (Ray's available resources), asked of Ray's control store at most
    every ``max_age_s``: every task of a large cluster asks between its pieces, and a view a
    fraction of a second old is as good as Ray's own (it lags its raylets by about that much)."""

    def __init__(self, max_age_s: float = 0.25, clock: Callable[[], float] = time.monotonic) -> None:
        self.max_age_s, self.clock, self.at, self.value = max_age_s, clock, -math.inf, 0.0

    def __call__(self) -> float:
        now = self.clock()
        if now - self.at >= self.max_age_s:
            import ray

            self.value, self.at = float(ray.available_resources().get("CPU", 0.0)), now
        return self.value


class RaySpreader:
    """A spreader for :func:`~stereopath.host.backend.parallel.spread_with`: the calling task runs
    pieces itself, in order from the front, while pieces from the back go out as Ray tasks of one
    CPU (``shared`` put once into the object store, read by reference) onto the cluster's idle CPUs
    (Ray's available resources); the results come back in the order of the items.  When other
    sessions keep every core busy, every piece runs here: no task, no serialisation, no worker
    started, nothing done that a core was not free for.  At a batch's end the task waits for its
    pieces and Ray lends its CPU to them.  ``pieces`` counts the pieces sent out, ``cpu_s`` their
    CPU seconds (the ones run here are in the task's own CPU time).

    ``lead``: the session the fleet waits for (the costliest running, its critical path) also keeps
    up to ``queue_ahead`` pieces queued in Ray beyond the idle CPUs, so that a CPU another task
    frees goes to the lead's next piece first (the driver starts a new session only on a CPU that
    stays idle); the other sessions run in the cores the lead leaves idle (its serial stages).
    ``idle_cpus``: how many CPUs are idle now (default: the cluster's available CPUs, from Ray)."""

    def __init__(self, retries: int = 3, idle_cpus: Callable[[], float] | None = None, lead: bool = False,
                 queue_ahead: int = 2) -> None:
        import ray

        self.ray, self.pieces, self.cpu_s = ray, 0, 0.0
        self.ahead = queue_ahead if lead else 0
        self.task = ray.remote(num_cpus=1, max_retries=retries)(run_piece)
        self.idle_cpus = idle_cpus or IdleCpus()

    def idle(self) -> bool:
        """Whether a piece sent now would run soon (an idle CPU, or the lead's turn at the next one)."""
        return self.ahead > 0 or self.idle_cpus() >= 1.0

    def __call__(self, fn: Callable[[Shared, Item], Out], shared: Shared, items: list[Item]) -> list[Out]:
        out: list[Any] = [None] * len(items)
        pending: dict[Any, int] = {}
        ref = None
        lo, hi = 0, len(items)  # this task takes pieces from the front, other CPUs from the back
        while lo < hi or pending:
            # as many out as CPUs are idle (the lead: and queued ahead), then one piece here
            n = 0 if hi - lo < 2 else min(hi - lo - 1, max(int(self.idle_cpus()), self.ahead - len(pending)))
            for _ in range(n):
                if ref is None:
                    ref = self.ray.put(shared)
                hi -= 1
                pending[self.task.options(name=f"piece {fn.__name__}").remote(fn, ref, items[hi])] = hi
            if lo < hi:
                out[lo] = fn(shared, items[lo])
                lo += 1
                ready, _ = self.ray.wait(list(pending), num_returns=len(pending), timeout=0) if pending else ([], [])
            else:
                ready, _ = self.ray.wait(list(pending), num_returns=1)
            for r in ready:
                out[pending.pop(r)], cpu = self.ray.get(r)
                self.pieces += 1
                self.cpu_s += cpu
        return out


def guess_offline_keyframes(session: str | Path, est: dict[str, Any], preset: str) -> int | None:
    """How many offline keyframes the session's tracks stage will choose (what its rest costs), guessed
    from cheap corners (:func:`~stereopath.host.reprocess.stage_tracks.guessed_keyframe_count`); None
    when the session's frames cannot be read for it (the scheduler then goes by the estimator's keyframes)."""
    from stereopath.device.errors import StereopathError
    from stereopath.host.reprocess.config import resolve_preset
    from stereopath.host.reprocess.pipeline import open_session_checked
    from stereopath.host.reprocess.stage_tracks import guessed_keyframe_count

    try:
        seq = open_session_checked(session)
        cfg = resolve_preset(preset)[1].tracks

        def images_of(i: int) -> tuple[Any, Any]:
            fr = seq.frame(int(est["seq"][i]))
            return fr.left, fr.right

        return guessed_keyframe_count(seq.rig, est, images_of, cfg)
    except (StereopathError, KeyError) as exc:
        log.warning("%s: offline keyframes not guessed (%s); scheduled by the estimator's keyframes", session, exc)
        return None


def first_part(session: str | Path, out_dir: str | Path, preset: str, t0: float, c0: float) -> dict[str, Any]:
    """What the first part of a split session reports: its frames, its estimate's keyframes and the
    offline keyframes guessed (:func:`guess_offline_keyframes`): what the rest will cost.  ``t0``, ``c0``:
    the task's start (``perf_counter``, ``process_time``)."""
    from stereopath.host.reprocess.store import load_npz

    est = load_npz(Path(out_dir) / "stages" / "estimate.npz") or {}
    kf = est.get("keyframe")
    guess = guess_offline_keyframes(session, est, preset) if "status" in est else None
    return {"status": "estimated", "frames": len(est.get("t_ns", ())), "offline_keyframes": guess,
            "keyframes": None if kf is None else int(kf.sum()), "stages": {"estimate": "computed"},
            "wall_s": round(time.perf_counter() - t0, 3), "cpu_s": round(time.process_time() - c0, 3)}


@dataclass(frozen=True)
class TaskPlan:
    """How one session task runs.

    ``part``: "all"; or "first": stop once the ``estimate`` stage is computed and return
    :func:`first_part`'s dict (when it was already stored, the session runs to its end); or
    "rest": the session from its stored estimate (the driver runs "first" before it).
    ``threads``: the thread count of every pool in the worker (:func:`limit_threads`; None leaves them).
    ``spread``: the stages' independent pieces run as Ray tasks of their own on idle CPUs
    (:class:`RaySpreader`); ``lead``: this session is the one the fleet waits for (its spreader's ``lead``).
    """

    part: str = "all"
    threads: int | None = None
    spread: bool = False
    lead: bool = False


def reprocess_task(sid: str, session: str, out_dir: str, settings: dict[str, Any],
                   board: ActorHandle | None = None, after_stage: Callable[[str], None] | None = None,
                   plan: TaskPlan = TaskPlan()) -> dict[str, Any]:
    """Reprocess one session (paths as this worker sees them) as ``plan`` says; returns :func:`summarise`'s dict.

    ``settings``: the preset, ``strict`` and :class:`RunChoices` fields (do_map, map_preset, imu_priors,
    force; force applies to the first attempt only).  ``board``: a :class:`ProgressBoard` actor
    handle or None.
    ``after_stage(name)`` is called after each stored stage, after the board is told.
    A :class:`StereopathError` (bad input) propagates: the driver reports the session failed.
    """
    from stereopath.host.backend.parallel import spread_with
    from stereopath.host.reprocess.pipeline import RunChoices, reprocess_session
    from stereopath.host.reprocess.preset_names import DEFAULT_PRESET

    part = plan.part
    if plan.threads is not None:
        limit_threads(max(1, int(plan.threads)))
    t0, c0 = time.perf_counter(), time.process_time()
    node = _node()
    if board is not None:
        import ray

        attempt = ray.get(board.started.remote(sid, {"pid": os.getpid(), "node": node,
                                                     "stored": stored_stages(out_dir)}, part))
        if attempt > 1:  # a retry (the worker died): resume from the stored stages even with force
            settings = {**settings, "force": False}

    def hook(name: str) -> None:
        if board is not None:
            board.stage_done.remote(sid, name)
        if after_stage is not None:
            after_stage(name)
        if part == "first" and name == "estimate":
            raise _Stop

    spreader = RaySpreader(lead=plan.lead) if plan.spread else None
    try:
        with spread_with(spreader):
            choices = {k: v for k, v in settings.items() if k not in ("preset", "strict")}
            res = reprocess_session(session, out_dir, preset=settings.get("preset", DEFAULT_PRESET),
                                    run=RunChoices(progress=False, after_stage=hook, **choices),
                                    strict=bool(settings.get("strict", False)))
    except _Stop:
        out = first_part(session, out_dir, settings.get("preset", DEFAULT_PRESET), t0, c0)
    else:  # CPU: this task's and its pieces'
        cpu_s = time.process_time() - c0 + (spreader.cpu_s if spreader else 0.0)
        out = summarise(res, time.perf_counter() - t0, cpu_s)
    out.update({"node": node, "pid": os.getpid(), "pieces": spreader.pieces if spreader else 0})
    return out
