"""Fleet reprocessing on Ray (`stereopath host reprocess S1 S2 ... --out DIR`): the same results
as the one-session command, a failing session reported, a killed worker resumed from its stored
stages, Ctrl-C and a rerun that recomputes nothing finished.  Ray runs locally with 2 CPUs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from stereopath.device.errors import ConfigError, DatasetError
from stereopath.host.fleet.compare import differences
from stereopath.host.fleet.runner import FleetOptions, ReprocessSettings, run_fleet
from stereopath.host.fleet.sessions import expand_sessions

ray = pytest.importorskip("ray")

SETTINGS = ReprocessSettings(preset="quick")


def _record(d: Path, frames: int, seed: int, trajectory: str = "arc") -> Path:
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim

    man = record_sequence(open_sim(SimConfig(frames=frames, seed=seed, trajectory=trajectory)), d,
                          config_dict={"source": "sim"})
    assert man["status"] == "closed"
    return d


@pytest.fixture(scope="module")
def local_ray():
    if ray.is_initialized():
        ray.shutdown()
    from stereopath.host.fleet.runner import keep_workers

    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False,
             _system_config=keep_workers(2))  # as run_fleet starts a local Ray
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> Path:
    """A folder of three sessions: two simulated ones (different seeds and trajectories) and a
    corrupt one (its images are gone)."""
    root = tmp_path_factory.mktemp("fleet") / "sessions"
    _record(root / "a", 30, seed=1)
    _record(root / "b", 14, seed=2, trajectory="line")
    bad = _record(root / "c", 4, seed=3)
    shutil.rmtree(bad / "mav0" / "cam1")
    return root


def _ids(root: Path) -> dict[str, str]:
    return {s.path.name: s.id for s in expand_sessions([root])}


@pytest.fixture(scope="module")
def fleet_run(local_ray, sessions, tmp_path_factory):
    out = tmp_path_factory.mktemp("fleet") / "out"
    updates: list[str] = []

    def on_update(states):
        from stereopath.host.fleet.progress import status_line

        updates.append(status_line(states))

    res = run_fleet(expand_sessions([sessions]), out, SETTINGS, FleetOptions(poll_s=0.2), on_update=on_update)
    return out, res, updates


@pytest.mark.slow
def test_sessions_from_folder_glob_and_ids(sessions, tmp_path):
    from_folder = expand_sessions([sessions])
    assert [s.path.name for s in from_folder] == ["a", "b", "c"]
    man = json.loads((sessions / "a" / "manifest.json").read_text())
    assert from_folder[0].id == man["session_id"]
    assert expand_sessions([str(sessions / "[ab]")]) == from_folder[:2]
    assert expand_sessions([sessions / "a", sessions / "a"]) == from_folder[:1]
    with pytest.raises(DatasetError, match="not found"):
        expand_sessions([sessions / "nope"])
    with pytest.raises(DatasetError, match="no session matches"):
        expand_sessions([str(sessions / "z*")])
    shutil.copytree(sessions / "a", tmp_path / "copy_of_a")
    with pytest.raises(ConfigError, match="two sessions have the id"):
        expand_sessions([sessions / "a", tmp_path / "copy_of_a"])


@pytest.mark.slow
def test_fleet_results_equal_the_one_session_command(fleet_run, sessions, tmp_path):
    import numpy as np

    from stereopath.host.fleet.compare import npz_contents
    from stereopath.host.reprocess.pipeline import RunChoices, reprocess_session

    out, res, updates = fleet_run
    ids = _ids(sessions)
    for name in ("a", "b"):
        one = tmp_path / name  # this process: the one-session command's default threads
        reprocess_session(sessions.absolute() / name, one, preset=SETTINGS.preset, run=RunChoices(progress=False))
        assert differences(one, out / ids[name]) == []
        assert (out / ids[name] / "report.html").is_file()
        # every stage's arrays byte for byte (the worker ran one thread of everything), records untimed
        for stage in ("estimate", "tracks", "ba"):
            x = npz_contents(one / "stages" / f"{stage}.npz")
            y = npz_contents(out / ids[name] / "stages" / f"{stage}.npz")
            assert sorted(x) == sorted(y)
            for k in x:
                assert x[k] == y[k] if isinstance(x[k], dict) else x[k].tobytes() == y[k].tobytes(), (stage, k)
        assert (one / "trajectory.tum").read_bytes() == (out / ids[name] / "trajectory.tum").read_bytes()
    # (where the pieces ran, here or as Ray tasks on idle CPUs, depends on timing: the same results;
    # test_pieces_go_out_only_to_idle_cpus covers the spreader itself)
    ba = npz_contents(tmp_path / "a" / "stages" / "ba.npz")
    assert len(ba["T_frames"]) == 30 and len(ba["point_xyz"]) > 0 and ba["stats"]["iterations"] > 0
    assert (out / ids["a"] / "mesh.ply").is_file()
    # the comparison does see a change: the last bit of one adjusted pose, a changed trajectory
    ba_raw = dict(np.load(tmp_path / "a" / "stages" / "ba.npz"))
    ba_raw["T_frames"][-1, 0, 3] = np.nextafter(ba_raw["T_frames"][-1, 0, 3], np.inf)
    np.savez(tmp_path / "a" / "stages" / "ba.npz", **ba_raw)
    (tmp_path / "a" / "trajectory.tum").write_text("0 0 0 0 0 0 0 1\n")
    assert differences(tmp_path / "a", out / ids["a"]) == ["trajectory.tum: bytes differ",
                                                          "stages/ba.npz: T_frames differs"]


def test_a_failing_session_is_reported_and_the_others_finish(fleet_run, sessions):
    out, res, updates = fleet_run
    ids = _ids(sessions)
    by_name = {s.session.path.name: s for s in res.sessions}
    assert [by_name[n].status for n in ("a", "b", "c")] == ["done", "done", "failed"]
    assert "DatasetError" in by_name["c"].error and "cam1" in by_name["c"].error
    assert res.counts() == {"done": 2, "running": 0, "failed": 1, "pending": 0, "interrupted": 0}
    summary = json.loads((out / "fleet.json").read_text())
    rows = {r["id"]: r for r in summary["sessions"]}
    a = rows[ids["a"]]
    assert a["status"] == "done" and a["attempts"] == 1
    assert a["ate_rmse_m"] > 0 and a["keyframes"] >= 1 and a["mesh_vertices"] > 0 and a["mesh_bytes"] > 0
    assert set(a["stages"]) == {"estimate", "tracks", "ba", "map"} and a["cpu_s"] > 0
    assert rows[ids["c"]]["status"] == "failed"
    assert summary["cluster"]["max_in_flight"] == 2 and summary["cluster"]["cpus"] == 2
    page = (out / "fleet.html").read_text()
    assert f"{ids['a']}/report.html" in page and "failed" in page
    assert any("running" in u and ": " in u for u in updates)  # the display saw sessions at a stage
    assert updates[-1].startswith("2/3 done, 0 running, 1 failed")


def test_rerun_recomputes_nothing_finished(fleet_run, sessions):
    out, _, _ = fleet_run
    ids = _ids(sessions)
    before = {p: p.stat().st_mtime_ns for p in out.glob("*/stages/*.npz")}
    res = run_fleet(expand_sessions([sessions / "a", sessions / "b"]), out, SETTINGS)
    assert [s.status for s in res.sessions] == ["done", "done"]
    for s in res.sessions:
        assert set(s.result["stages"].values()) == {"reused"}
    assert {p: p.stat().st_mtime_ns for p in out.glob("*/stages/*.npz")} == before
    assert (out / ids["c"]).exists() is False or not (out / ids["c"] / "stages" / "estimate.npz").exists()


@pytest.mark.slow
def test_worker_killed_during_ba_resumes_from_the_stored_stages(local_ray, fleet_run, sessions, tmp_path):
    ref_out, _, _ = fleet_run
    sid = _ids(sessions)["b"]
    out = tmp_path / "out"
    marker = tmp_path / "killed.json"

    def kill_once_after_tracks(name: str) -> None:  # runs in the worker: SIGKILL itself as ba starts
        import json as _json
        import os as _os
        import signal as _signal
        from pathlib import Path as _Path

        if name == "tracks" and not marker.exists():
            stages = out / sid / "stages"
            marker.write_text(_json.dumps({p.name: p.stat().st_mtime_ns for p in stages.glob("*.npz")}))
            _os.kill(_os.getpid(), _signal.SIGKILL)
        del _Path

    res = run_fleet(expand_sessions([sessions / "b"]), out, SETTINGS, after_stage=kill_once_after_tracks)
    st = res.sessions[0]
    assert marker.exists() and st.status == "done" and st.attempts == 2
    # the session's first task computed the estimate; the retry of its second task reused the
    # tracks stored before the kill and computed the rest
    assert st.result["stages"] == {"estimate": "computed", "tracks": "reused", "ba": "computed", "map": "computed"}
    stored = json.loads(marker.read_text())
    assert sorted(stored) == ["estimate.npz", "tracks.npz"]
    for name, mt in stored.items():
        assert (out / sid / "stages" / name).stat().st_mtime_ns == mt
    assert differences(ref_out / sid, out / sid) == []


@pytest.mark.slow
def test_ctrl_c_stops_cleanly_and_a_rerun_resumes(local_ray, fleet_run, sessions, tmp_path):
    ref_out, _, _ = fleet_run
    sid = _ids(sessions)["b"]
    out = tmp_path / "out"

    def interrupt_after_first_stage(states):
        if any(s.stored for s in states):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_fleet(expand_sessions([sessions / "b"]), out, SETTINGS, FleetOptions(poll_s=0.1),
                  on_update=interrupt_after_first_stage)
    summary = json.loads((out / "fleet.json").read_text())
    assert summary["interrupted"] is True and summary["sessions"][0]["status"] == "interrupted"
    assert "interrupted" in (out / "fleet.html").read_text()
    stored = {p.name: p.stat().st_mtime_ns for p in (out / sid / "stages").glob("*.npz")}
    assert "estimate.npz" in stored and not (out / sid / "trajectory.tum").exists()
    res = run_fleet(expand_sessions([sessions / "b"]), out, SETTINGS)
    st = res.sessions[0]
    assert st.status == "done"
    for name, mt in stored.items():  # finished stages were not recomputed
        assert st.result["stages"][name[:-4]] == "reused"
        assert (out / sid / "stages" / name).stat().st_mtime_ns == mt
    assert differences(ref_out / sid, out / sid) == []


def test_cli_fleet(local_ray, fleet_run, sessions, capsys):
    from stereopath.host.cli import main

    out, _, _ = fleet_run
    code = main(["-q", "host", "reprocess", str(sessions / "a"), str(sessions / "c"), "--out", str(out),
                 "--preset", "quick", "--no-progress"])
    text = capsys.readouterr().out
    assert code == 1  # one session failed
    assert "1 of 2 session(s) done, 1 failed" in text and "DatasetError" in text and "fleet.html" in text
    assert main(["-q", "host", "reprocess", str(sessions / "a"), "--ray", "auto", "--out", str(out),
                 "--preset", "quick", "--no-progress", "--task-cpus", "4"]) == 2  # cannot hold one task
    assert "cannot hold one task" in capsys.readouterr().err


def test_options_and_path_map_check_their_input():
    from stereopath.host.fleet.runner import capacity
    from stereopath.host.fleet.sessions import PathMap

    pm = PathMap.parse(["/data/scans=/mnt/scans", "/data=/srv/data"])
    assert pm.to_worker("/data/scans/s1") == "/mnt/scans/s1"
    assert pm.to_worker("/data/other") == "/srv/data/other"
    assert pm.to_worker("/data/scansX") == "/srv/data/scansX"  # whole components only
    assert pm.to_worker("/elsewhere/s") == "/elsewhere/s"
    for bad in ("nodelimiter", "relative=/x", "/x="):
        with pytest.raises(ConfigError):
            PathMap.parse([bad])
    with pytest.raises(ConfigError):
        FleetOptions(task_cpus=0)
    with pytest.raises(ConfigError):
        FleetOptions(max_in_flight=0)
    gb = 1024**3
    assert capacity({"CPU": 8.0, "memory": 3.5 * gb}, FleetOptions(task_memory_gb=1.0)) == 3  # memory bound
    assert capacity({"CPU": 8.0, "memory": 3.5 * gb}, FleetOptions()) == int(3.5 // FleetOptions().task_memory_gb)
    assert capacity({"CPU": 2.0, "memory": 16 * gb}, FleetOptions()) == 2  # CPU bound
    assert capacity({"CPU": 8.0, "memory": 16 * gb}, FleetOptions(max_in_flight=5)) == 5
    with pytest.raises(ConfigError, match="cannot hold one task"):
        capacity({"CPU": 2.0, "memory": 16 * gb}, FleetOptions(task_cpus=3))


def test_a_task_limits_every_thread_pool_of_its_worker():
    import subprocess
    import sys

    code = ("from stereopath.host.fleet.worker import limit_threads, limit_tbb\n"
            "import cv2, threadpoolctl\n"
            "limit_threads(1)\n"
            "print(cv2.getNumThreads(), {p['num_threads'] for p in threadpoolctl.threadpool_info()}, limit_tbb(1))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[-2] == "1 {1} True"  # limit_tbb checks the value TBB reports back


def test_fleet_html_escapes_names():
    from stereopath.host.fleet.summary import render_html

    page = render_html({"counts": {"done": 0, "failed": 1}, "wall_s": 1.0, "written_utc": "now",
                        "sessions": [{"id": "<x>", "status": "failed", "error": "DatasetError: <bad> & worse"}]})
    assert "<x>" not in page and "&lt;bad&gt; &amp; worse" in page


def test_compare_can_leave_out_the_session_path_a_worker_saw(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for d, src in ((a, "/data/s1"), (b, "/mnt/worker/s1")):
        d.mkdir()
        (d / "report.json").write_text(json.dumps({"source": src, "frames": 3, "wall_s": 1.0,
                                                   "extra": {"map": {"error": f"{src}: no surface"}}}))
    assert differences(a, b) == ["report.json: differs in extra, source"]
    assert differences(a, b, ignore_source=True) == []
    (b / "report.json").write_text(json.dumps({"source": "/mnt/worker/s1", "frames": 4,
                                               "extra": {"map": {"error": "/mnt/worker/s1: no surface"}}}))
    assert differences(a, b, ignore_source=True) == ["report.json: differs in frames"]


def test_pieces_go_out_only_to_idle_cpus(local_ray):
    """The fleet's spreader sends a piece to Ray only while a CPU is idle and runs the others in the
    calling task: with no idle CPU every piece runs here (nothing sent), with idle ones some go out;
    the results come back in the order of the items either way."""
    import operator

    from stereopath.host.fleet.worker import RaySpreader
    from stereopath.host.backend.parallel import parallel_map, spare_cores, spread_with

    items = list(range(1, 9))
    want = [3 * i for i in items]
    busy, idle = RaySpreader(idle_cpus=lambda: 0.0), RaySpreader(idle_cpus=lambda: 1.0)
    lead = RaySpreader(idle_cpus=lambda: 0.0, lead=True)  # the critical path queues pieces for freed CPUs
    for sp in (busy, idle, lead, RaySpreader()):  # the last asks Ray: this driver holds no CPU, both are idle
        with spread_with(sp):
            assert parallel_map(operator.mul, 3, items) == want
    assert busy.pieces == 0 and busy.cpu_s == 0.0
    assert 0 < idle.pieces < len(items)  # one out per piece run here while one CPU is idle
    assert 0 < lead.pieces < len(items)
    with spread_with(lead):
        assert spare_cores()
    with spread_with(busy):
        assert not spare_cores()
    with spread_with(idle):
        assert spare_cores()
    assert not spare_cores()


def _estimated(states, **offline_keyframes):
    for name, kf in offline_keyframes.items():
        states[name].first = {"keyframes": 3, "offline_keyframes": kf, "frames": 100}


def test_the_critical_session_leads_and_the_others_fill_its_serial_stages(local_ray, sessions, tmp_path):
    """Critical path first: the costliest estimated session, when it costs more than a slot's share of
    all the work, starts first and leads; while it is in its wide stage (tracks: independent pieces)
    on a cluster no wider than it can use, the other rests wait as far as its serial stages leave
    room for them (a task started then would hold a core for its whole run), and those beyond that
    room start now (held, they would run on after the lead); once the lead's tracks are stored the
    rest start.  On a wide cluster nobody waits."""
    from stereopath.host.fleet.runner import LEAD_WIDTH, SERIAL_SHARE, SessionState, _cost, _Scheduler

    states = {s.path.name: SessionState(s, tmp_path / s.id) for s in expand_sessions([sessions])}
    a, b, c = states["a"], states["b"], states["c"]
    _estimated(states, a=70, b=20, c=9)  # costs 71.8, 21.8, 10.8: a is more than half of the work
    sched = _Scheduler(local_ray, list(states.values()), SETTINGS, FleetOptions(), None)
    sched.first, sched.rest = [], [b, c, a]
    assert sched._next(2) == (a, "rest") and sched._leads(a, "rest", 2)
    sched.inflight["a"], a.stored = (a, "rest"), ["estimate"]
    sched.lead_refs.add("a")
    assert not sched._leads(b, "rest", 2)  # a, running, costs more
    room = SERIAL_SHARE * _cost(a)
    assert _cost(b) < room < _cost(b) + _cost(c)
    # b and c would not fit into a's serial stages: the cheapest whose start makes the other fit starts now
    assert sched._next(2) == (c, "rest")
    assert sched._next(2) is None  # b fits: it waits for a's wide stage
    assert sched._next(LEAD_WIDTH + 2) == (b, "rest")  # a wide cluster has cores for both
    sched.rest = [b]
    a.stored = ["estimate", "tracks"]
    assert sched._next(2) == (b, "rest")  # a's serial stages leave a core
    _estimated(states, b=25, c=24)  # neither alone makes the other fit: the costliest starts
    sched.rest, a.stored = [b, c], ["estimate"]
    assert _cost(c) > room and sched._next(2) == (b, "rest")


def test_in_a_batch_of_similar_sessions_nobody_leads(local_ray, sessions, tmp_path):
    """No session leads (no pieces queued ahead, nobody waits) when the costliest is less than a slot's
    share of the work; sessions not yet estimated count at the mean cost of the estimated ones."""
    from stereopath.host.fleet.runner import SessionState, _Scheduler

    states = {s.path.name: SessionState(s, tmp_path / s.id) for s in expand_sessions([sessions])}
    a, b, c = states["a"], states["b"], states["c"]
    _estimated(states, a=60, b=55, c=58)
    sched = _Scheduler(local_ray, list(states.values()), SETTINGS, FleetOptions(), None)
    sched.first, sched.rest = [], [b, c, a]
    assert not sched._leads(a, "rest", 2)
    assert sched._leads(a, "rest", 4)  # on four slots a third of the work is the critical path
    _estimated(states, a=70)
    sched.rest, sched.first = [a], [b, c]  # b and c still to estimate: each counted at a's cost
    assert not sched._leads(a, "rest", 2)
    sched.first = []  # a alone: its pieces have the other core
    assert sched._leads(a, "rest", 2) and not sched._leads(a, "first", 2)
    # a running session counts what it has left: after its tracks, its serial stages
    _estimated(states, b=50)
    sched.rest, sched.inflight["a"], a.stored = [b], (a, "rest"), ["estimate"]
    assert not sched._leads(b, "rest", 2)
    a.stored = ["estimate", "tracks"]
    assert sched._leads(b, "rest", 2)


def test_first_part_guesses_the_offline_keyframes(fleet_run, sessions):
    """The first task reports what the rest will cost: the offline keyframes guessed from cheap
    corners, close to the ones the tracks stage chose, and the frames."""
    import time

    import numpy as np

    from stereopath.host.fleet.worker import first_part, guess_offline_keyframes

    out, _, _ = fleet_run
    sid = _ids(sessions)["a"]
    r = first_part(sessions / "a", out / sid, SETTINGS.preset, time.perf_counter(), time.process_time())
    chosen = len(np.load(out / sid / "stages" / "tracks.npz")["kf_index"])
    assert r["frames"] == 30 and r["status"] == "estimated"
    assert chosen >= 3 and abs(r["offline_keyframes"] - chosen) <= max(2, 0.3 * chosen)
    assert r["cpu_s"] >= 0 and r["wall_s"] >= 0
    est = {"status": np.zeros(4, np.int8), "seq": np.arange(4), "T_world_cam": np.tile(np.eye(4), (4, 1, 1))}
    assert guess_offline_keyframes(sessions / "c", est, SETTINGS.preset) is None  # its right images are gone


def test_idle_cpus_are_asked_of_ray_at_most_every_quarter_second(local_ray, monkeypatch):
    """Every task asks between its pieces how many CPUs are idle: the answer is cached for a short
    while, so that a large cluster's tasks do not flood Ray's control store with the question."""
    from stereopath.host.fleet.worker import IdleCpus

    asked, clock = [], [100.0]
    monkeypatch.setattr(local_ray, "available_resources", lambda: asked.append(1) or {"CPU": 2.0 - len(asked)})
    idle = IdleCpus(max_age_s=0.25, clock=lambda: clock[0])
    assert idle() == 1.0 and idle() == 1.0 and len(asked) == 1
    clock[0] += 0.3
    assert idle() == 0.0 and len(asked) == 2


def test_compare_takes_meshes_equal_up_to_vertex_order_and_duplicate_vertices(tmp_path):
    """Marching cubes on several threads writes the vertices in another order, and a vertex it emits
    twice may be used through either copy: the same model.  A triangle moved to another vertex is not."""
    import numpy as np
    import open3d as o3d

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [1, 1, 0], [2, 1, 0]], float)  # 3 and 4 equal
    tri = np.array([[0, 1, 2], [1, 3, 2], [1, 5, 4]])

    def write(d, verts, tris):
        d.mkdir()
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris))
        assert o3d.io.write_triangle_mesh(str(d / "mesh.ply"), mesh)

    write(tmp_path / "a", v, tri)
    perm = np.array([5, 3, 4, 2, 1, 0])  # new vertex i is old vertex perm[i]
    new_index = np.argsort(perm)
    swapped = tri.copy()
    swapped[1, 1], swapped[2, 2] = 4, 3  # each triangle through the other copy of the duplicate
    write(tmp_path / "b", v[perm], new_index[swapped])
    assert (tmp_path / "a" / "mesh.ply").read_bytes() != (tmp_path / "b" / "mesh.ply").read_bytes()
    assert differences(tmp_path / "a", tmp_path / "b") == []
    moved = tri.copy()
    moved[2] = [1, 5, 2]
    write(tmp_path / "c", v, moved)
    assert differences(tmp_path / "a", tmp_path / "c") == ["mesh.ply: elements differ"]
    # a triangle written from another corner, through the other copy (same orientation); then reversed
    write(tmp_path / "d", v, np.array([[1, 3, 5], [0, 1, 2]]))
    write(tmp_path / "e", v, np.array([[0, 1, 2], [5, 1, 4]]))
    assert differences(tmp_path / "d", tmp_path / "e") == []
    write(tmp_path / "f", v, np.array([[0, 1, 2], [1, 5, 4]]))
    assert differences(tmp_path / "d", tmp_path / "f") == ["mesh.ply: elements differ"]
    # two copies of the smallest rank in one triangle: each rotation of it is the same triangle
    write(tmp_path / "g", v, np.array([[3, 4, 5]]))
    write(tmp_path / "h", v, np.array([[4, 5, 3]]))
    assert differences(tmp_path / "g", tmp_path / "h") == []
