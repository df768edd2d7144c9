"""Fleet reprocessing on Ray (issue 14 targets): local Ray vs one after another, a two-node
cluster on loopback, and a worker killed with SIGKILL during a session's `ba` stage.

    .venv/bin/python benchmarks/bench_fleet.py [--frames N] [--runs R] [--preset NAME]
                                               [--skip-cluster] [--skip-fault] [--keep DIR] [--profile]

Four simulated sessions (`stereopath sim`: seeds 1-4, trajectories arc/line/orbit/arc, N frames
each; written once, not timed), then:

0. with --profile: the costliest session (orbit) alone through the one-session entry point, per
   stage: wall, CPU of the process and CPU of each thread, with the default thread pools and
   with every pool at one thread (as in a fleet task): where the time goes, how parallel a
   session is by itself, whether threads spin.
1. sequential: the four through the one-session entry point (`reprocess_session`, the code of
   `stereopath host reprocess SESSION`) one after another in this process; and fleet: the same
   four with `run_fleet` on a local Ray of 2 CPUs, Ray's start and shutdown included in its wall
   time.  R alternating repetitions, medians.  Ratio fleet / sequential (target <= 0.65).
   The machine is shared with other jobs, so each phase also reports its own CPU time (all
   threads of all our processes: this one, Ray's daemons and workers) and the CPU time the rest of
   the machine used meanwhile (/proc/stat minus ours), and a CPU-normalised ratio: each wall time
   scaled by the share of the 2 cores the other jobs left free during that phase.
   Every fleet output is checked against the sequential one (`stereopath.host.fleet.compare`).
   Each sequential run prints each session's wall and CPU, each fleet run each session's tasks
   (wall, CPU with its pieces, pieces sent out) and the CPU of every process by kind (the driver,
   Ray's daemons, the workers by the task they ran): where the fleet's extra CPU goes.
   With --bound, each run also measures each session alone in a fresh process with every thread
   pool at one thread (as in a fleet task), CPU of the pipeline call: no schedule on the 2 cores
   can end before the sum of those over the cores (a session cannot do its work in less CPU than
   single-threaded, and the fleet adds Ray's processes and the pieces' transfers to it), so
   sum / cores / sequential wall is the lowest ratio any fleet could reach in that run.
2. two-node cluster on loopback: `ray start --head` (1 CPU) and a second `ray start --address`
   (1 CPU, its own --temp-dir), the four sessions through `run_fleet(ray=ADDRESS)` with a path
   map (the workers see the sessions through another path, a symbolic link); which node ran each
   session; same results.  The Ray processes started here are stopped by their process ids.
3. fault: local Ray, the four sessions, the worker of the second session killed with SIGKILL
   once its `ba` stage has started; every session must end done, the killed one retried with
   `tracks` reused (its `estimate` came from its first task), and the same results.
Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereopath.host.fleet.compare import differences  # noqa: E402
from stereopath.host.fleet.runner import FleetOptions, ReprocessSettings, run_fleet  # noqa: E402
from stereopath.host.fleet.sessions import PathMap, expand_sessions  # noqa: E402
from stereopath.host.reprocess.pipeline import RunChoices, reprocess_session  # noqa: E402

TRAJECTORIES = ("arc", "line", "orbit", "arc")
CORES = os.cpu_count() or 2


def machine_busy_s() -> float:
    """CPU seconds the whole machine has spent busy (all cores), from /proc/stat."""
    with open("/proc/stat") as f:
        vals = [int(x) for x in f.readline().split()[1:]]
    idle = vals[3] + (vals[4] if len(vals) > 4 else 0)
    return (sum(vals[:8]) - idle) / os.sysconf("SC_CLK_TCK")


class TreeCpu:
    """CPU seconds of this process and every descendant that lived during the block, sampled every
    ``period_s`` (Ray starts and ends worker processes on its own: a worker that exits is counted
    up to its last sample, and a pid is known by its start time)."""

    def __init__(self, period_s: float = 0.2) -> None:
        import threading

        self.period_s, self.seen, self.kind = period_s, {}, {}
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def sample(self) -> None:
        import psutil

        me = psutil.Process()
        for p in [me, *me.children(recursive=True)]:
            try:
                t = p.cpu_times()
                key = (p.pid, p.create_time())
                self.seen[key] = t.user + t.system
                if key not in self.kind or self.kind[key].startswith("ray::IDLE"):
                    self.kind[key] = process_kind(p)
            except psutil.NoSuchProcess:
                pass

    def _run(self) -> None:
        while not self.stop_event.wait(self.period_s):
            self.sample()

    def __enter__(self) -> "TreeCpu":
        self.sample()
        self.start = dict(self.seen)
        self.thread.start()
        return self

    def total(self) -> float:
        """CPU used since the start (processes alive at the start count from their start value)."""
        self.sample()
        return sum(c - self.start.get(k, 0.0) for k, c in self.seen.items())

    def by_kind(self) -> dict[str, tuple[int, float]]:
        """CPU since the start per kind of process (this driver, each Ray daemon, workers by the
        task they ran): number of processes and CPU seconds."""
        out: dict[str, tuple[int, float]] = {}
        for k, c in self.seen.items():
            n, s = out.get(self.kind.get(k, "?"), (0, 0.0))
            out[self.kind.get(k, "?")] = (n + 1, s + c - self.start.get(k, 0.0))
        return out

    def __exit__(self, *exc) -> None:
        self.stop_event.set()
        self.thread.join()


def process_kind(p) -> str:
    """A process's kind: the driver, a Ray daemon's name, or a worker's title (``ray::<task>``)."""
    import psutil

    if p.pid == os.getpid():
        return "driver"
    try:
        cmd = p.cmdline()
    except psutil.Error:
        return "?"
    if cmd and cmd[0].startswith("ray::"):
        return cmd[0].split()[0]
    for c in cmd[:3]:
        base = os.path.basename(c)
        if base.endswith(".py"):
            return base
    return p.name()


class Phase:
    """Wall time, our CPU and the rest of the machine's CPU over a block."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __enter__(self) -> "Phase":
        self.cpu = TreeCpu().__enter__()
        self.t0, self.busy0, self.t0_epoch = time.perf_counter(), machine_busy_s(), time.time()
        self.load0 = os.getloadavg()[0]
        return self

    def stop(self, own_now: float | None = None) -> None:
        self.wall = time.perf_counter() - self.t0
        self.busy = machine_busy_s() - self.busy0
        self.own = self.cpu.total() if own_now is None else own_now
        self.cpu.__exit__()
        self.others = max(0.0, self.busy - self.own)
        self.free_share = max(0.05, 1.0 - self.others / (CORES * self.wall))
        self.load1 = os.getloadavg()[0]

    def __exit__(self, *exc) -> None:
        if not hasattr(self, "wall"):
            self.stop()

    def kinds(self) -> str:
        parts = sorted(self.cpu.by_kind().items(), key=lambda kv: -kv[1][1])
        return ", ".join(f"{k} x{n} {c:.1f} s" for k, (n, c) in parts if c >= 0.05)

    def line(self) -> str:
        return (f"{self.name}: wall {self.wall:.1f} s, own CPU {self.own:.1f} s, other jobs' CPU {self.others:.1f} s "
                f"({self.others / self.wall:.2f} of {CORES} cores busy with them), wall x free share "
                f"{self.wall * self.free_share:.1f} s; load average {self.load0:.1f} -> {self.load1:.1f}")


def make_sessions(root: Path, frames: int) -> list[Path]:
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim

    out = []
    for i, traj in enumerate(TRAJECTORIES, start=1):
        d = root / f"s{i}_{traj}"
        if not (d / "mav0").is_dir():
            record_sequence(open_sim(SimConfig(frames=frames, seed=i, trajectory=traj)), d,
                            config_dict={"source": "sim"})
        out.append(d)
    return out


def sequential(sessions, out: Path, settings: ReprocessSettings) -> Phase:
    with Phase("sequential") as ph:
        ph.per_session = []
        for s in sessions:
            c0, w0 = time.process_time(), time.perf_counter()
            reprocess_session(s.path, out / s.id, preset=settings.preset,
                              run=RunChoices(do_map=settings.do_map, map_preset=settings.map_preset, progress=False,
                                             force=True))
            ph.per_session.append(f"{s.id} wall {time.perf_counter() - w0:.1f} s CPU {time.process_time() - c0:.1f} s")
        ph.stop()
    return ph


def fleet_local(sessions, out: Path, settings: ReprocessSettings, on_update=None,
                poll_s: float = 0.5) -> tuple[Phase, object]:
    import shutil

    shutil.rmtree(out, ignore_errors=True)  # everything computed (a kept folder would be reused)
    with Phase("fleet (local Ray, 2 CPUs)") as ph:  # run_fleet starts and stops Ray (as the command does)
        res = run_fleet(sessions, out, settings, FleetOptions(num_cpus=2, poll_s=poll_s), on_update=on_update)
        ph.stop()
    return ph, res


ONE_THREAD = """
import json, sys, time
from stereopath.host.fleet.worker import limit_threads
from stereopath.host.reprocess.pipeline import RunChoices, reprocess_session
limit_threads(1)
c0, w0 = time.process_time(), time.perf_counter()
reprocess_session(sys.argv[1], sys.argv[2], preset=sys.argv[3],
                  run=RunChoices(do_map=sys.argv[4] == "1", map_preset=sys.argv[5], progress=False, force=True))
print(json.dumps({"cpu_s": time.process_time() - c0, "wall_s": time.perf_counter() - w0}))
"""


def one_thread_cpu(sessions, out: Path, settings: ReprocessSettings) -> list[float]:
    """Each session alone in a fresh process, every pool at one thread: CPU seconds of the pipeline
    call (the imports not counted, as in the sequential figures)."""
    import json

    cpu = []
    for s in sessions:
        r = subprocess.run([sys.executable, "-c", ONE_THREAD, str(s.path), str(out / s.id), settings.preset,
                            "1" if settings.do_map else "0", settings.map_preset],
                           capture_output=True, text=True, check=True, cwd=ROOT)
        cpu.append(json.loads(r.stdout.strip().splitlines()[-1])["cpu_s"])
    return cpu


def thread_cpu_s() -> dict[int, float]:
    """CPU seconds of each thread of this process (/proc/self/task)."""
    tck, out = os.sysconf("SC_CLK_TCK"), {}
    for t in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{t}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            out[int(t)] = (int(fields[11]) + int(fields[12])) / tck
        except OSError:
            pass
    return out


def profile(session, out: Path, settings: ReprocessSettings, threads: int | None) -> None:
    """One session through the one-session entry point: per stage, wall, CPU (all threads) and the
    CPU of each thread (the main one first) - where the time goes and how parallel each stage is."""
    import contextlib

    import cv2
    import scipy.linalg  # noqa: F401 - loaded, so that threadpoolctl limits its BLAS too
    from threadpoolctl import threadpool_limits

    marks = [("start", time.perf_counter(), time.process_time(), thread_cpu_s())]

    def hook(name: str) -> None:
        marks.append((name, time.perf_counter(), time.process_time(), thread_cpu_s()))

    cv_threads = cv2.getNumThreads()
    with threadpool_limits(limits=threads) if threads else contextlib.nullcontext():
        cv2.setNumThreads(threads or cv_threads)  # as a fleet task's limit_threads does
        reprocess_session(session.path, out, preset=settings.preset,
                          run=RunChoices(do_map=settings.do_map, map_preset=settings.map_preset, progress=False,
                                         force=True, after_stage=hook))
        hook("outputs")
    cv2.setNumThreads(cv_threads)
    print(f"  {session.id}, {threads or 'default'} thread(s) (OpenCV {threads or cv_threads}):")
    for (_, w0, c0, t0), (name, w1, c1, t1) in zip(marks, marks[1:]):
        per = sorted(((tid != os.getpid(), -(c - t0.get(tid, 0.0))) for tid, c in t1.items()))
        busy = " ".join(f"{-c:.1f}" for _, c in per if -c >= 0.05)
        print(f"    {name:8s} wall {w1 - w0:6.1f} s, CPU {c1 - c0:6.1f} s ({(c1 - c0) / (w1 - w0):.2f} cores); "
              f"CPU per thread: {busy} s ({len(t1)} threads)")
    w, c = marks[-1][1] - marks[0][1], marks[-1][2] - marks[0][2]
    print(f"    total    wall {w:6.1f} s, CPU {c:6.1f} s ({c / w:.2f} cores)")


def session_lines(res) -> list[str]:
    t0 = min((st.started for st in res.sessions if st.started), default=0.0)
    return [f"    {st.session.id}: {st.status}, {(st.result or {}).get('keyframes')} keyframes, from "
            f"{(st.started or t0) - t0:.1f} s to {(st.finished or t0) - t0:.1f} s after the first task, tasks' wall "
            f"{(st.result or {}).get('wall_s')} s, CPU {(st.result or {}).get('cpu_s')} s (with "
            f"{(st.result or {}).get('pieces')} pieces), node {st.node}" for st in res.sessions]


def check(ref: Path, out: Path, sessions) -> str:
    bad = {s.id: d for s in sessions if (d := differences(ref / s.id, out / s.id))}
    return "identical to the sequential outputs" if not bad else f"DIFFERENT: {bad}"


def ray_bin() -> str:
    return str(Path(sys.executable).with_name("ray"))


def start_node(args: list[str], tmp: Path, name: str) -> subprocess.Popen:
    log = open(tmp / f"{name}.log", "w")
    return subprocess.Popen([ray_bin(), "start", "--block", "--disable-usage-stats", *args],
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def stop_nodes(procs: list[subprocess.Popen]) -> None:
    """Stop the `ray start --block` processes started here and everything they started, by pid."""
    import psutil

    victims = []
    for p in procs:
        try:
            victims += [psutil.Process(p.pid), *psutil.Process(p.pid).children(recursive=True)]
        except psutil.NoSuchProcess:
            pass
    for v in victims:
        try:
            v.terminate()
        except psutil.NoSuchProcess:
            pass
    _, alive = psutil.wait_procs(victims, timeout=15)
    for v in alive:
        try:
            v.kill()
        except psutil.NoSuchProcess:
            pass


def two_node_cluster(sessions, ref: Path, tmp: Path, settings: ReprocessSettings) -> None:
    import ray


    port = 6400 + os.getpid() % 500
    addr = f"127.0.0.1:{port}"
    head_tmp, worker_tmp = Path(tempfile.mkdtemp(prefix="rh_")), Path(tempfile.mkdtemp(prefix="rw_"))
    procs = [start_node(["--head", f"--port={port}", "--node-ip-address=127.0.0.1", "--num-cpus=1",
                         "--include-dashboard=false", f"--temp-dir={head_tmp}"], tmp, "head")]
    try:
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 60:
            if subprocess.run([ray_bin(), "status", f"--address={addr}"], capture_output=True).returncode == 0:
                break
            time.sleep(1)
        procs.append(start_node([f"--address={addr}", "--node-ip-address=127.0.0.1", "--num-cpus=1",
                                 f"--temp-dir={worker_tmp}"], tmp, "worker"))
        ray.init(address=addr, log_to_driver=False, logging_level=logging.WARNING)
        t0 = time.perf_counter()
        while len([n for n in ray.nodes() if n.get("Alive")]) < 2 and time.perf_counter() - t0 < 60:
            time.sleep(0.5)
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        print(f"  cluster {addr}: {len(nodes)} nodes, "
              + ", ".join(f"{n['NodeID'][:8]} ({n['Resources'].get('CPU', 0):g} CPU)" for n in nodes))
        # the workers see the sessions through another path (a link): --path-map HERE=WORKER
        view = tmp / "worker_view"
        if not view.exists():
            view.symlink_to(sessions[0].path.parent, target_is_directory=True)
        out = tmp / "cluster_out"
        pm = PathMap.parse([f"{sessions[0].path.parent}={view}"])
        t = time.perf_counter()
        res = run_fleet(sessions, out, settings, FleetOptions(ray=addr, path_map=pm, poll_s=0.25))
        wall = time.perf_counter() - t
        ray.shutdown()
        for st in res.sessions:
            print(f"    {st.session.id}: {st.status} on node {st.node}, {st.result and st.result['wall_s']} s")
        import json

        srcs = {json.loads((out / s.id / "report.json").read_text())["source"] for s in sessions}
        print(f"  two-node wall {wall:.1f} s (Ray already running); {len({s.node for s in res.sessions})} nodes "
              f"used; workers read {sorted(srcs)[0].rsplit('/', 1)[0]}/...; results (labels aside) "
              f"{check_labels(ref, out, sessions)}")
    finally:
        if ray.is_initialized():
            ray.shutdown()
        stop_nodes(procs)


def check_labels(ref: Path, out: Path, sessions) -> str:
    """As :func:`check`, but the report's and model's ``source`` label names the worker's path."""
    bad = {s.id: d for s in sessions if (d := differences(ref / s.id, out / s.id, ignore_source=True))}
    return "identical to the sequential outputs" if not bad else f"DIFFERENT: {bad}"


def fault_run(sessions, ref: Path, tmp: Path, settings: ReprocessSettings) -> None:
    victim = sessions[1].id
    killed: dict[str, object] = {}

    def on_update(states):
        for st in states:
            if st.session.id == victim and st.status == "running" and st.stage == "ba" and not killed and st.pid:
                time.sleep(0.3)  # well inside the stage
                os.kill(st.pid, signal.SIGKILL)
                killed.update(pid=st.pid, stored=list(st.stored), at=time.perf_counter())

    out = tmp / "fault_out"
    ph, res = fleet_local(sessions, out, settings, on_update=on_update, poll_s=0.25)
    st = next(s for s in res.sessions if s.session.id == victim)
    print(f"  killed worker pid {killed.get('pid')} of {victim} during ba (stored then: {killed.get('stored')})")
    print(f"  {ph.line()}")
    print(f"  statuses: {[s.status for s in res.sessions]}; {victim}: attempts {st.attempts}, stages "
          f"{st.result and st.result['stages']}")
    print(f"  results {check(ref, out, sessions)}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100, help="frames per simulated session (default 100)")
    ap.add_argument("--runs", type=int, default=1, help="alternating sequential/fleet repetitions (medians)")
    ap.add_argument("--preset", default="standard")
    ap.add_argument("--skip-cluster", action="store_true")
    ap.add_argument("--skip-fault", action="store_true")
    ap.add_argument("--skip-ratio", action="store_true",
                    help="no fleet timing: one sequential run as the reference of the cluster and fault runs")
    ap.add_argument("--keep", default=None, help="work in this folder instead of a temporary one")
    ap.add_argument("--bound", action="store_true",
                    help="each run also times every session single-threaded: the lowest ratio any schedule could reach")
    ap.add_argument("--profile", action="store_true",
                    help="first: the costliest session (orbit) alone, per stage, with the default threads and with one")
    args = ap.parse_args()
    if not args.skip_cluster:
        # Ray 2.59+ turns token authentication on for a `ray start --head` it sees as local, while a driver
        # joining an address keeps it off: the same RAY_AUTH_MODE on every node and in this process before
        # Ray is first used (it reads the mode once), one token (~/.ray/auth_token, generated if missing)
        os.environ["RAY_AUTH_MODE"] = "token"
        subprocess.run([ray_bin(), "get-auth-token", "--generate"], capture_output=True)
    logging.basicConfig(level=logging.WARNING)
    settings = ReprocessSettings(preset=args.preset)

    with tempfile.TemporaryDirectory(prefix="bench_fleet_") as tmp_name:
        tmp = Path(args.keep) if args.keep else Path(tmp_name)
        tmp.mkdir(parents=True, exist_ok=True)
        paths = make_sessions(tmp / "sessions", args.frames)
        sessions = expand_sessions(paths)
        print(f"{len(sessions)} simulated sessions of {args.frames} frames ({', '.join(TRAJECTORIES)}; seeds 1-4), "
              f"preset {args.preset}, {CORES} cores")
        if args.profile:
            print("one session, per stage:")
            profile(sessions[2], tmp / "profile_default", settings, None)
            profile(sessions[2], tmp / "profile_one_thread", settings, 1)
        seq_ph, fl_ph, bounds = [], [], []
        if args.skip_ratio:
            ph = sequential(sessions, tmp / "seq0", settings)
            print(f"  reference: {ph.line()}")
        for r in range(0 if args.skip_ratio else args.runs):
            ph = sequential(sessions, tmp / f"seq{r}", settings)
            print(f"  run {r + 1}: {ph.line()}")
            print(f"    per session: {'; '.join(ph.per_session)}")
            seq_ph.append(ph)
            if args.bound:
                cpu = one_thread_cpu(sessions, tmp / f"one{r}", settings)
                bounds.append(sum(cpu) / CORES)
                each = " + ".join(f"{c:.1f}" for c in cpu)
                print(f"  run {r + 1}: one thread each, alone: CPU {each} = {sum(cpu):.1f} s; over {CORES} cores "
                      f"{bounds[-1]:.1f} s = {bounds[-1] / seq_ph[-1].wall:.2f} of the sequential wall (no schedule is faster)")
            ph, res = fleet_local(sessions, tmp / f"fleet{r}", settings)
            print(f"  run {r + 1}: {ph.line()}; {res.counts()['done']} done; {check(tmp / f'seq{r}', tmp / f'fleet{r}', sessions)}")
            print("\n".join(session_lines(res)))
            print(f"    CPU by process: {ph.kinds()}")
            fl_ph.append(ph)
        if seq_ph:
            report_ratio(seq_ph, fl_ph, bounds)
        ref = tmp / "seq0"
        if not args.skip_cluster:
            print("two-node cluster on loopback:")
            two_node_cluster(sessions, ref, tmp, settings)
        if not args.skip_fault:
            print("fault run (SIGKILL during ba):")
            fault_run(sessions, ref, tmp, settings)
    return 0


def report_ratio(seq_ph, fl_ph, bounds=()) -> None:
    med = statistics.median
    sw, fw = med(p.wall for p in seq_ph), med(p.wall for p in fl_ph)
    sn, fn = med(p.wall * p.free_share for p in seq_ph), med(p.wall * p.free_share for p in fl_ph)
    sc, fc = med(p.own for p in seq_ph), med(p.own for p in fl_ph)
    print(f"wall: sequential {sw:.1f} s, fleet {fw:.1f} s: ratio {fw / sw:.2f} (target <= 0.65)")
    print(f"CPU-normalised (wall x share of the cores other jobs left free): sequential {sn:.1f} s, "
          f"fleet {fn:.1f} s: ratio {fn / sn:.2f}")
    print(f"own CPU: sequential {sc:.1f} s, fleet {fc:.1f} s (x{fc / sc:.2f}: Ray's overhead and thread effects)")
    if bounds:
        b = med(bounds)
        print(f"lowest possible (one-thread CPU of the four over {CORES} cores): {b:.1f} s, ratio {b / sw:.2f}; "
              f"the fleet's wall is {fw / b:.2f}x that")


if __name__ == "__main__":
    sys.exit(main())
