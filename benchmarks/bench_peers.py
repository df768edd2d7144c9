"""Our `stereo` estimator side by side with ORB-SLAM3 on the same frames.  Prints figures.

    .venv/bin/python benchmarks/bench_peers.py --all [--runs 3]
    .venv/bin/python benchmarks/bench_peers.py [--runs 3] [--cases kitti06,kitti06_s2,kitti06_s3,sim,sim_handheld,euroc]
        [--kitti SEQDIR] [--kitti-frames N] [--euroc MAV0DIR] [--euroc-frames N] [--peer-mode stereo-imu]
        [--peer-venv DIR] [--vocab FILE] [--sim-frames N] [--threads N] [--rig RIG.yaml] [--json-out FILE]

Installs nothing.  ORB-SLAM3 runs only when its own environment exists (a virtual environment
with `pyorbslam3`, default `../peer-venv` or `../../peer-venv` beside the repository, or
$PEER_VENV) and the vocabulary (default ~/.cache/orbslam3-peer/vocab_generic.txt or
$PYORBSLAM3_VOCAB); `../shared/tools/peers/README.md` sets both up.  Without them only our rows
are printed.

Cases (all on the same frames for both systems, one process at a time):

* ``kitti06``: KITTI 06 frames 0-50 at full rate (``--kitti SEQDIR``: another KITTI odometry sequence
  in the same layout, ``--kitti-frames N``: its first N frames; the case keeps its name);
* ``kitti06_s2`` / ``kitti06_s3``: the same frames taken every 2nd / 3rd frame (fast motion),
  as a KITTI folder of links written to a temporary directory;
* ``sim``: the default simulated scan written by ``stereopath sim --out`` (an ASL session; ORB-SLAM3
  rectifies it with OpenCV, ours reads it as recorded, with its IMU);
* ``sim_handheld``: the simulator's stand-in for hand-held scans (``stereopath sim --trajectory handheld``:
  real recorded motion rescaled to a 1.5 m scan, switched on in motion, auto-exposure changes and
  motion blur), read the same way;
* ``euroc`` (default: the shared ``euroc_v1_01_head``, 95 nearly still frames; ``--euroc MAV0DIR`` adds
  the case with another recording): a stereo-inertial recording in the EuRoC/ASL layout with
  ground truth (``state_groundtruth_estimate0`` or ``mocap0``, read by ours and written as TUM for
  ORB-SLAM3's evaluation), its first ``--euroc-frames N`` frames if given.  Ours reads it with its IMU.
  The peer runner rectifies radial-tangential cameras from ``cam0``/``cam1`` ``sensor.yaml``
  only: for other recordings (a fisheye camchain) only our rows are printed.

``--all`` runs every case: KITTI 06 at steps 1, 2 and 3, the EuRoC V1_01 head of the shared data
(``euroc_v1_01_head``, unless ``--euroc`` names another recording) and both simulated scans.

``--peer-mode stereo-imu`` runs ORB-SLAM3 stereo-inertial instead of stereo (the ``sim``, ``sim_handheld``
and ``euroc`` cases; KITTI has no IMU and keeps stereo).

Ours runs as a user runs it: the command ``stereopath odometry SOURCE --out DIR`` in a process of its
own (BLAS at one thread, as on the device).  Per system and case the medians over ``--runs`` runs of:
end error (% of path), ATE RMSE (SE(3) alignment, ``stereopath eval``), median and p95 wall ms per
frame (the estimator's call only), CPU ms per frame (process CPU time of all threads over the frame
loop, image decoding included for both systems, divided by the frames) and frames tracked; for ours
also the CPU per frame without reading and decoding the images (what live frames cost: the
report's ``cpu_ms_per_frame.live_frames``) and the whole command's (the child process's CPU time,
imports, evaluation and plot included, divided by the frames).  Ratios ours / ORB-SLAM3 come from
the same run and compare the frame loops with decoding.  The last line is the score over all cases:
the geometric mean of the ratios for ATE, end error and CPU per frame, and the worst case of each.
For the simulated cases it also prints our position error (median, p95) over the first 2 s and
after them (a start in motion should be no worse than the rest).  For one-core figures run it under ``taskset -c 0`` with
``--threads 1`` (OpenCV at one thread in our process, through ``OPENCV_FOR_THREADS_NUM``; ORB-SLAM3
inherits the affinity); the table's "median CPU ms/frame, live" column is the median over the frames.  ``--rig`` runs ours with another
calibration of the same cameras (e.g. the ``rig_refined.yaml`` of ``stereopath host reprocess``);
ORB-SLAM3 keeps the source's; with ``--rig`` or ``--option`` ours runs in this process instead of
through the command (which has neither), and the command's CPU is not measured.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereopath.device.commands.blas_threads import BLAS_THREAD_VARIABLES, use_one_blas_thread  # noqa: E402

# ORB-SLAM3's process gets the environment this one started with
PEER_ENV = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}

CASES = ("kitti06", "kitti06_s2", "kitti06_s3", "euroc", "sim", "sim_handheld")
DEFAULT_CASES = ("kitti06", "kitti06_s2", "kitti06_s3", "sim")
SIM_TRAJECTORIES = {"sim": None, "sim_handheld": "handheld"}


def data_dir() -> Path:
    env = os.environ.get("STEREOPATH_DATA")
    if env:
        return Path(env)
    for cand in (ROOT.parent / "shared" / "data", ROOT.parent.parent / "shared" / "data"):  # repo or work tree
        if cand.is_dir():
            return cand
    return ROOT.parent / "shared" / "data"


def find_peer_python(arg: str | None) -> Path | None:
    cands = [Path(arg)] if arg else []
    if os.environ.get("PEER_VENV"):
        cands.append(Path(os.environ["PEER_VENV"]))
    cands += [ROOT.parent / "peer-venv", ROOT.parent.parent / "peer-venv"]
    for c in cands:
        py = c / "bin" / "python"
        if py.exists():
            r = subprocess.run([str(py), "-c", "import pyorbslam3"], capture_output=True)
            if r.returncode == 0:
                return py
    return None


def subsampled_kitti(src: Path, step: int, out: Path, frames: int | None = None) -> Path:
    """A KITTI odometry folder (sequences/NN + poses/NN.txt) with every ``step``-th frame of the first
    ``frames`` (all when None), as links."""
    name = src.name
    seq = out / "sequences" / name
    for cam in ("image_0", "image_1"):
        (seq / cam).mkdir(parents=True, exist_ok=True)
    times = (src / "times.txt").read_text().split()
    poses = (src.parent.parent / "poses" / f"{name}.txt").read_text().splitlines()
    n = min(len(times), len(list((src / "image_0").glob("*.png"))), frames or len(times))
    keep = list(range(0, n, step))
    for j, i in enumerate(keep):
        for cam in ("image_0", "image_1"):
            dst = seq / cam / f"{j:06d}.png"
            if not dst.exists():
                os.symlink(src / cam / f"{i:06d}.png", dst)
    (seq / "times.txt").write_text("\n".join(times[i] for i in keep) + "\n")
    shutil.copy(src / "calib.txt", seq / "calib.txt")
    (out / "poses").mkdir(exist_ok=True)
    (out / "poses" / f"{name}.txt").write_text("\n".join(poses[i] for i in keep) + "\n")
    return seq


# ------------------------------------------------------------------------------------ systems


def run_ours(spec: str, options: dict | None = None, rig_file: str | None = None, frames: int | None = None) -> dict:
    """One run of our `stereo` on ``spec`` (with ``rig_file``'s rig if given; its first ``frames`` frames
    if given); CPU time of the whole process over the frame loop."""

    from stereopath.device.estimation.base import run_estimator
    from stereopath.device.estimation.registry import make_estimator
    from stereopath.host.evaluation.evaluate import evaluate
    from stereopath.device.formats.source import open_source

    seq = open_source(spec)
    rig = seq.rig
    if rig_file:
        from stereopath.device.formats.rig_files import load_rig_yaml

        rig = load_rig_yaml(rig_file)
    est = make_estimator("stereo", rig, options=options)
    decode = [0.0]
    cpu0 = time.process_time()
    source = seq.frames() if frames is None else itertools.islice(seq.frames(), frames)
    run = run_estimator(est, _timed(source, decode), seq.imu)  # joins the keyframe worker before returning
    cpu = time.process_time() - cpu0
    m = evaluate(seq.groundtruth, run.trajectory)
    ms = sorted(run.frame_ms)
    return dict(end_pct=m["end_error_pct"], ate_m=m["ate_rmse_m"], median_ms=statistics.median(ms),
                p95_ms=ms[int(0.95 * (len(ms) - 1))], cpu_ms=1e3 * cpu / len(ms),
                cpu_live_ms=1e3 * (cpu - decode[0]) / len(ms), tracked=run.frames_tracked,
                frames=len(ms), keyframes=run.extra.get("keyframes"))


def run_command(spec: str, out: Path, frames: int | None = None, threads: int | None = None) -> dict:
    """One run of ``stereopath odometry SPEC --out OUT`` in its own process: the report's figures, and
    the process's CPU time (all threads, from start to exit) per frame."""
    cmd = [str(Path(sys.executable).parent / "stereopath"), "-q", "odometry", spec, "--out", str(out)]
    if frames is not None:
        cmd += ["--frames", str(frames)]
    with open(out.parent / f"{out.name}.log", "w") as log_file:
        env = dict(PEER_ENV, **({"OPENCV_FOR_THREADS_NUM": str(threads)} if threads else {}))
        proc = subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        tail = (out.parent / f"{out.name}.log").read_text(errors="replace")[-1500:]
        raise RuntimeError(f"stereopath odometry failed ({proc.returncode}): {tail}")
    r = json.loads((out / "report.json").read_text())
    cpu = r["extra"]["cpu_ms_per_frame"]
    n = r["frames"]
    return dict(end_pct=r["end_error_pct"], ate_m=r["ate_rmse_m"], median_ms=r["median_frame_ms"],
                p95_ms=r["p95_frame_ms"], cpu_ms=cpu["frame_loop"], cpu_live_ms=cpu["live_frames"],
                cpu_live_median_ms=cpu["live_median"], cpu_live_p95_ms=cpu["live_p95"],
                cpu_cmd_ms=1e3 * (usage.ru_utime + usage.ru_stime) / n, tracked=r["frames_tracked"], frames=n,
                keyframes=r["extra"]["estimator_stats"].get("keyframes"))


START_S = 2.0


def start_errors(groundtruth: Path, trajectory: Path) -> tuple[float, float, float, float] | None:
    """Position errors (ATE alignment) of the first :data:`START_S` seconds and of the rest:
    (median, p95 of the start, median, p95 of the rest), metres; None without poses in both."""
    import numpy as np

    from stereopath.device.formats.tum import read_tum
    from stereopath.host.evaluation.evaluate import associate_and_align

    a = associate_and_align(read_tum(groundtruth), read_tum(trajectory))
    err = np.linalg.norm(a.est_aligned.positions - a.gt.positions, axis=1)
    start = (a.gt.t_ns - a.gt.t_ns[0]) * 1e-9 < START_S
    if not start.any() or start.all():
        return None
    return (float(np.median(err[start])), float(np.percentile(err[start], 95)),
            float(np.median(err[~start])), float(np.percentile(err[~start], 95)))


def _timed(frames, spent: list):
    """The frames, with the CPU time of the reading thread spent producing them (reading and decoding
    the recorded images, which a live camera does not cost) added to ``spent[0]``."""
    it = iter(frames)
    while True:
        t0 = time.thread_time()
        try:
            frame = next(it)
        except StopIteration:
            return
        finally:
            spent[0] += time.thread_time() - t0
        yield frame


def run_orb(py: Path, runner: Path, source: str, out: Path, vocab: str | None, gt: tuple[str, str] | None,
            mode: str = "stereo", frames: int | None = None) -> dict:
    cmd = [str(py), str(runner), source, "--out", str(out), "--mode", mode]
    if frames is not None:
        cmd += ["--frames", str(frames)]
    if vocab:
        cmd += ["--vocab", vocab]
    if gt:
        cmd += ["--gt", gt[0]] + (["--gt-times", gt[1]] if gt[1] else [])
    env = dict(PEER_ENV, STEREOPATH=str(Path(sys.executable).parent / "stereopath"))
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise RuntimeError(f"ORB-SLAM3 run failed ({r.returncode}): {r.stderr[-1500:]}")
    s = json.loads((out / "summary.json").read_text())
    ev = s.get("eval") or {}
    return dict(end_pct=ev.get("end_error_pct"), ate_m=ev.get("ate_rmse_m"), median_ms=s["median_frame_ms"],
                p95_ms=s["p95_frame_ms"], cpu_ms=s["process_cpu_ms_per_frame"], tracked=s["frames_ok"],
                frames=s["frames"], keyframes=None)


def med(rows: list[dict], key: str):
    v = [r[key] for r in rows if r.get(key) is not None]
    return statistics.median(v) if v else None


def fmt(v, spec):
    return "-" if v is None else format(v, spec)


def _peer_rows(systems: dict) -> list | None:
    return next((rows for name, rows in systems.items() if name.startswith("ORB-SLAM3")), None)


RATIO_KEYS = (("ate_m", "ATE"), ("end_pct", "end error"), ("cpu_ms", "CPU/frame"))


def ratios(results: dict) -> dict[str, dict[str, float]]:
    """Per case, ours / ORB-SLAM3 of the medians for each of :data:`RATIO_KEYS` (cases with both)."""
    out: dict[str, dict[str, float]] = {}
    for case, systems in results.items():
        ours, orb = systems.get("stereo"), _peer_rows(systems)
        if not ours or not orb:
            continue
        for key, _ in RATIO_KEYS:
            a, b = med(ours, key), med(orb, key)
            if a is not None and b:
                out.setdefault(case, {})[key] = a / b
    return out


def _score(results: dict) -> dict[str, tuple[float, float, str]]:
    """Per ratio of :data:`RATIO_KEYS`: (geometric mean over the cases, worst ratio, worst case)."""
    import math

    per_case = ratios(results)
    out = {}
    for key, _ in RATIO_KEYS:
        vals = {case: r[key] for case, r in per_case.items() if r.get(key, 0) > 0}
        if vals:
            worst = max(vals, key=vals.get)
            out[key] = (math.exp(sum(math.log(v) for v in vals.values()) / len(vals)), vals[worst], worst)
    return out


def score_line(results: dict) -> str:
    """One line: the geometric mean over the cases of ours / ORB-SLAM3 for ATE, end error and CPU per
    frame, and the worst case of each."""
    score = _score(results)
    parts = [f"{label} {score[key][0]:.2f}x (worst {score[key][1]:.2f}x {score[key][2]})" if key in score
             else f"{label} -" for key, label in RATIO_KEYS]
    return f"score over {len(ratios(results))} cases, ours / ORB-SLAM3, geometric mean: " + "; ".join(parts)


def print_table(results: dict) -> None:
    print()
    print("| data | system | end error | ATE RMSE | median ms/frame | p95 ms | CPU ms/frame (all threads) | "
          "CPU ms/frame without image decoding | median CPU ms/frame, live | CPU ms/frame, whole command | tracked |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for case, systems in results.items():
        for name, rows in systems.items():
            if not rows:
                continue
            ate = med(rows, "ate_m")
            ate_s = "-" if ate is None else (f"{ate * 1000:.2f} mm" if ate < 0.01 else f"{ate:.3f} m")
            tracked = min(r["tracked"] for r in rows)
            print(f"| {case} | {name} | {fmt(med(rows, 'end_pct'), '.3f')} % | {ate_s} | "
                  f"{fmt(med(rows, 'median_ms'), '.1f')} | {fmt(med(rows, 'p95_ms'), '.1f')} | "
                  f"{fmt(med(rows, 'cpu_ms'), '.1f')} | {fmt(med(rows, 'cpu_live_ms'), '.1f')} | "
                  f"{fmt(med(rows, 'cpu_live_median_ms'), '.1f')} | "
                  f"{fmt(med(rows, 'cpu_cmd_ms'), '.1f')} | {tracked}/{rows[0]['frames']} |")
    print()
    for case, systems in results.items():
        ours, orb = systems.get("stereo"), _peer_rows(systems)
        if not ours or not orb:
            continue
        parts = []
        for key, label in (("end_pct", "end error"), ("ate_m", "ATE"), ("median_ms", "median ms"),
                           ("cpu_ms", "CPU ms")):
            a, b = med(ours, key), med(orb, key)
            parts.append(f"{label} {a / b:.2f}x" if a is not None and b else f"{label} -")
        print(f"{case}: ours / ORB-SLAM3: " + ", ".join(parts))
    for case, systems in results.items():
        ours = systems.get("stereo") or []
        if med(ours, "cpu_live_p95_ms") is not None:
            print(f"{case}: ours, CPU per live frame (without reading and decoding images): median "
                  f"{med(ours, 'cpu_live_median_ms'):.1f} ms, p95 {med(ours, 'cpu_live_p95_ms'):.1f} ms; "
                  f"estimator wall time p95 {med(ours, 'p95_ms'):.1f} ms")
    for case, systems in results.items():
        starts = [r["start_err"] for r in systems.get("stereo") or [] if r.get("start_err")]
        if starts:
            m = [statistics.median(v[i] for v in starts) * 1e3 for i in range(4)]
            print(f"{case}: ours, position error in the first {START_S:.0f} s median {m[0]:.2f} mm, p95 {m[1]:.2f} mm; "
                  f"after it median {m[2]:.2f} mm, p95 {m[3]:.2f} mm")


def json_figures(results: dict) -> dict:
    """Per case: our medians, frames lost, and the ratios ours / ORB-SLAM3 of the same run."""
    out: dict = {}
    for case, systems in results.items():
        ours, orb = systems.get("stereo"), _peer_rows(systems)
        if not ours:
            continue
        out[f"peers.{case}.end_error_pct"] = med(ours, "end_pct")
        out[f"peers.{case}.ate_m"] = med(ours, "ate_m")
        out[f"peers.{case}.median_ms"] = med(ours, "median_ms")
        out[f"peers.{case}.p95_ms"] = med(ours, "p95_ms")
        out[f"peers.{case}.cpu_ms"] = med(ours, "cpu_ms")
        out[f"peers.{case}.cpu_live_ms"] = med(ours, "cpu_live_ms")
        out[f"peers.{case}.cpu_command_ms"] = med(ours, "cpu_cmd_ms")
        out[f"peers.{case}.frames_lost"] = max(r["frames"] - r["tracked"] for r in ours)
        if orb:
            for key, name in (("ate_m", "ate_ratio"), ("end_pct", "end_error_ratio"), ("cpu_ms", "cpu_ratio")):
                a, b = med(ours, key), med(orb, key)
                out[f"peers.{case}.{name}"] = a / b if a is not None and b else None
    return out


def score_figures(results: dict) -> dict[str, float]:
    """The score line's figures: ``peers.score.{ate,end_error,cpu}_{gmean,worst}``."""
    names = {"ate_m": "ate", "end_pct": "end_error", "cpu_ms": "cpu"}
    out: dict[str, float] = {}
    for key, (gmean, worst, _) in _score(results).items():
        out[f"peers.score.{names[key]}_gmean"] = gmean
        out[f"peers.score.{names[key]}_worst"] = worst
    return out


def _positive(text: str) -> int:
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--all", action="store_true", help="every case: KITTI 06 at steps 1/2/3, the shared EuRoC "
                                                       "V1_01 head (or --euroc) and both simulated scans")
    ap.add_argument("--cases", default=None, help=f"comma-separated, of {', '.join(CASES)} (default: "
                                                  f"{', '.join(DEFAULT_CASES)}, and euroc with --euroc)")
    ap.add_argument("--kitti", default=None, help="KITTI odometry sequence folder for the kitti06 cases "
                                                 "(default: the shared KITTI 06; poses/NN.txt two levels up)")
    ap.add_argument("--kitti-frames", type=_positive, default=None, help="use only the first N frames of the sequence")
    ap.add_argument("--euroc", default=None, help="an EuRoC/ASL mav0 folder with ground truth: adds the euroc case")
    ap.add_argument("--euroc-frames", type=_positive, default=None, help="use only its first N frames")
    ap.add_argument("--peer-mode", default="stereo", choices=["stereo", "stereo-imu"],
                    help="ORB-SLAM3 stereo, or stereo-inertial on the cases with an IMU (sim, euroc)")
    ap.add_argument("--peer-venv", default=None)
    ap.add_argument("--vocab", default=None)
    ap.add_argument("--sim-frames", type=int, default=None, help="frames of the simulated scan (default: its own)")
    ap.add_argument("--threads", type=int, default=None, help="OpenCV threads in our process (1 = one core)")
    ap.add_argument("--no-peer", action="store_true", help="our rows only")
    ap.add_argument("--option", action="append", default=[], help="stereo config SECTION.KEY=VALUE (ours), e.g. klt.klt_window=21")
    ap.add_argument("--rig", default=None, help="rig YAML for ours instead of the source's (e.g. rig_refined.yaml)")
    ap.add_argument("--json-out", metavar="FILE", help="also write the medians and ratios as JSON "
                                                        "(benchmarks/write_table.py)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    use_one_blas_thread()  # before numpy is loaded, as the device path does
    import cv2

    if args.threads is not None:
        cv2.setNumThreads(args.threads)
    options: dict[str, dict] = {}
    for kv in args.option:
        k, _, v = kv.partition("=")
        section, _, key = k.partition(".")
        if not key:
            raise SystemExit(f"--option {kv!r}: name the section, SECTION.KEY=VALUE (e.g. klt.klt_window=21)")
        try:
            options.setdefault(section, {})[key] = json.loads(v)  # numbers, true/false
        except json.JSONDecodeError:
            options.setdefault(section, {})[key] = v
    D = data_dir()
    if args.all and args.cases:
        raise SystemExit("--all runs every case: give --all or --cases, not both")
    default = CASES if args.all else DEFAULT_CASES + (("euroc",) if args.euroc else ())
    cases = [c for c in (args.cases or ",".join(default)).split(",") if c]
    for c in cases:
        if c not in CASES:
            raise SystemExit(f"unknown case {c!r}; known: {', '.join(CASES)}")
    args.euroc = args.euroc or str(D / "euroc_v1_01_head")  # the shared recording's head by default
    in_process = bool(args.rig or options)  # the command has neither --rig nor --option

    runner = D.parent / "tools" / "peers" / "run_orbslam3.py"
    vocab = args.vocab or os.environ.get("PYORBSLAM3_VOCAB") or str(Path.home() / ".cache/orbslam3-peer/vocab_generic.txt")
    py = None if args.no_peer else find_peer_python(args.peer_venv)
    if py is None and not args.no_peer:
        print("ORB-SLAM3 peer: no environment with pyorbslam3 found (see ../shared/tools/peers/README.md); ours only")
    elif py is not None and (not Path(vocab).exists() or not runner.exists()):
        print(f"ORB-SLAM3 peer: missing {'vocabulary ' + vocab if not Path(vocab).exists() else runner}; ours only")
        py = None
    try:
        load = os.getloadavg()
        print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} CPUs; "
              f"affinity {sorted(os.sched_getaffinity(0))}; OpenCV threads {cv2.getNumThreads()}; runs {args.runs}")
    except (AttributeError, OSError):
        pass

    tmp = Path(tempfile.mkdtemp(prefix="bench_peers_"))
    results: dict[str, dict[str, list]] = {}
    try:
        kitti = Path(args.kitti) if args.kitti else D / "kitti_odometry" / "sequences" / "06"
        for case in cases:
            if case.startswith("kitti06"):
                if not kitti.is_dir():
                    print(f"{case}: no KITTI sequence at {kitti}; skipped")
                    continue
                step = 1 if case == "kitti06" else int(case[-1])
                seq_dir = kitti if step == 1 and not args.kitti_frames else subsampled_kitti(
                    kitti, step, tmp / case, args.kitti_frames)
                gt = (str(seq_dir.parent.parent / "poses" / f"{seq_dir.name}.txt"), str(seq_dir / "times.txt"))
                ours_spec, orb_source = f"kitti:{seq_dir}", f"kitti:{seq_dir}"
            elif case == "euroc":
                if not args.euroc or not Path(args.euroc).is_dir():
                    print(f"{case}: give an EuRoC/ASL mav0 folder with --euroc; skipped")
                    continue
                from stereopath.device.formats.source import open_source
                from stereopath.device.formats.tum import write_tum

                seq = open_source(f"euroc:{args.euroc}")
                if seq.groundtruth is None:
                    print(f"{case}: {args.euroc} has no ground truth; skipped")
                    continue
                write_tum(tmp / "euroc_groundtruth.tum", seq.groundtruth)
                gt = (str(tmp / "euroc_groundtruth.tum"), "")
                mav0 = Path(args.euroc) / "mav0" if (Path(args.euroc) / "mav0").is_dir() else Path(args.euroc)
                ours_spec, orb_source = f"euroc:{args.euroc}", f"euroc:{mav0}"  # the peer runner takes mav0 itself
            else:
                sess = tmp / case
                cmd = [str(Path(sys.executable).parent / "stereopath"), "sim", "--out", str(sess)]
                if args.sim_frames:
                    cmd += ["--frames", str(args.sim_frames)]
                if SIM_TRAJECTORIES[case]:
                    cmd += ["--trajectory", SIM_TRAJECTORIES[case]]
                r = subprocess.run(cmd, capture_output=True, text=True, env=PEER_ENV)
                if r.returncode != 0:
                    print(f"{case}: the simulator did not write the session; skipped: {r.stderr.strip()[-500:]}")
                    continue
                gt = (str(sess / "groundtruth.tum"), "")
                ours_spec, orb_source = f"session:{sess}", f"session:{sess}"
            mode = args.peer_mode if case in ("sim", "sim_handheld", "euroc") else "stereo"
            peer = "ORB-SLAM3 stereo-inertial" if mode == "stereo-imu" else "ORB-SLAM3 stereo"
            frames = args.euroc_frames if case == "euroc" else None
            results[case] = {peer: [], "stereo": []}
            peer_py = py
            for r in range(args.runs):
                if peer_py is not None:
                    try:
                        row = run_orb(peer_py, runner, orb_source, tmp / f"orb_{case}_{r}", vocab, gt, mode, frames)
                    except RuntimeError as exc:
                        # a recording the peer runner cannot take (a fisheye camchain), a crash (stereo-inertial)
                        print(f"{case}: {peer} did not run ({str(exc)[:300]})", flush=True)
                        if mode == "stereo-imu" and not results[case][peer]:
                            del results[case][peer]
                            mode, peer = "stereo", "ORB-SLAM3 stereo"
                            print(f"{case}: {peer} instead", flush=True)
                            results[case][peer] = []
                            try:
                                row = run_orb(peer_py, runner, orb_source, tmp / f"orb_{case}_{r}s", vocab, gt, mode,
                                              frames)
                            except RuntimeError as exc2:
                                print(f"{case}: {peer} did not run either ({str(exc2)[:300]}); ours only")
                                peer_py = None
                        else:
                            peer_py = None
                    if peer_py is not None:
                        results[case][peer].append(row)
                        print(f"{case} run {r}: ORB-SLAM3 {json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()})}", flush=True)
                if in_process:
                    row = run_ours(ours_spec, options, args.rig, frames)
                else:
                    row = run_command(ours_spec, tmp / f"ours_{case}_{r}", frames, args.threads)
                    if case in SIM_TRAJECTORIES:
                        row["start_err"] = start_errors(Path(gt[0]), tmp / f"ours_{case}_{r}" / "trajectory.tum")
                results[case]["stereo"].append(row)
                print(f"{case} run {r}: stereo    {json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()})}", flush=True)
        print_table(results)
        if args.json_out:
            from results_file import write_results

            write_results(args.json_out, "bench_peers.py", {**json_figures(results), **score_figures(results)})
        print("targets, every case: ATE <= 0.9x ORB-SLAM3's, end error <= 1.0x, CPU per frame <= 1.0x")
        print(score_line(results))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
