"""The on-board `stereo` estimator on one core: median CPU and p95 wall time per frame.  Prints figures.

    .venv/bin/python benchmarks/bench_onecore.py [--core 0] [--runs 2] [--nice 0,10] [--pace live,full]
        [--source sim] [--frames N]

The process pins itself to one core (as ``taskset -c CORE`` would), runs OpenCV and BLAS at one thread,
renders (or reads) every frame first, then hands them to the estimator as live frames: ``live`` at the
camera's rate (each frame handed over at its timestamp, the estimator idle in between, as on the
device), ``full`` back to back (a frame loop at full load: the keyframe worker gets only what the loop
leaves).  For each keyframe worker niceness of ``--nice`` (``keyframes.worker_nice``, which applies because the
process runs on one core: ``keyframes.worker_nice_max_cores``) and each pace, in
alternating runs: the median over the frames of the process CPU from a frame's hand-over to the next
one's (all threads: frame loop and keyframe worker), the p95 and maximum of the frame loop's wall time
per frame (``process`` only), the ATE against the source's ground truth, and the keyframe jobs run,
skipped and deferred.  The one-core targets of the device: median CPU <= 20 ms, p95 wall <= 50 ms.
"""

from __future__ import annotations

import argparse
import itertools
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TARGET_CPU_MS, TARGET_P95_WALL_MS = 20.0, 50.0


def one_run(seq, frames: list, nice: int, live: bool) -> dict:
    """One pass over ``frames`` with the worker at niceness ``nice``; ``live``: at the camera's rate."""
    from stereopath.device.estimation.registry import make_estimator
    from stereopath.device.estimation.base import EstimateRun
    from stereopath.host.evaluation.evaluate import evaluate

    est = make_estimator("stereo", seq.rig, options={"keyframes": {"worker_nice": nice}})
    imu = getattr(seq, "imu", None)
    estimates, wall_ms, cpu_ms = [], [], []
    prev_t = None
    t_start, t0_ns = time.perf_counter(), frames[0].t_ns
    cpu_prev = None
    for frame in frames:
        if live:  # hand the frame over at its time (never early), as a camera would
            delay = (frame.t_ns - t0_ns) * 1e-9 - (time.perf_counter() - t_start)
            if delay > 0:
                time.sleep(delay)
        block = None
        if imu is not None and len(imu):
            block = imu.between(int(imu.t_ns[0]) - 1 if prev_t is None else prev_t, frame.t_ns)
        cpu = time.process_time()
        if cpu_prev is not None:
            cpu_ms.append(1e3 * (cpu - cpu_prev))
        cpu_prev = cpu
        w = time.perf_counter()
        estimates.append(est.process(frame, block))
        wall_ms.append(1e3 * (time.perf_counter() - w))
        prev_t = frame.t_ns
    est.close()
    cpu_ms.append(1e3 * (time.process_time() - cpu_prev))
    stats = est.stats()
    run = EstimateRun(estimates, wall_ms, est.world_frame, est.name)
    m = evaluate(seq.groundtruth, run.trajectory) if seq.groundtruth is not None else {}
    wall = sorted(wall_ms)
    return dict(cpu_median_ms=statistics.median(cpu_ms), wall_p95_ms=wall[int(0.95 * (len(wall) - 1))],
                wall_max_ms=wall[-1], ate_mm=1e3 * m["ate_rmse_m"] if m else None,
                tracked=sum(e.status == "ok" for e in estimates), frames=len(frames),
                kf_jobs=stats["kf_jobs"], kf_skipped=stats["kf_jobs_skipped"], kf_deferred=stats["kf_jobs_deferred"],
                kf_corrections=stats["kf_corrections"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--core", type=int, default=0, help="the core to run on (-1: no pinning)")
    ap.add_argument("--runs", type=int, default=2, help="alternating runs of every configuration")
    ap.add_argument("--nice", default="0,10", help="keyframe worker niceness values to compare")
    ap.add_argument("--pace", default="live,full", help="live (camera rate) and/or full (back to back)")
    ap.add_argument("--source", default="sim", help="a source spec (sim[:SEED], kitti:DIR, euroc:DIR, ...)")
    ap.add_argument("--frames", type=int, default=None, help="its first N frames")
    args = ap.parse_args()

    from stereopath.device.commands.blas_threads import use_one_blas_thread

    use_one_blas_thread()  # before numpy is loaded
    if args.core >= 0:
        os.sched_setaffinity(0, {args.core})
    import cv2

    from stereopath.device.formats.source import open_source

    cv2.setNumThreads(1)
    seq = open_source(args.source)
    frames = list(itertools.islice(seq.frames(), args.frames))  # rendered / decoded before the clock starts
    nices = [int(v) for v in args.nice.split(",")]
    paces = [p.strip() for p in args.pace.split(",")]
    print(f"{args.source}: {len(frames)} frames; affinity {sorted(os.sched_getaffinity(0))}; OpenCV threads "
          f"{cv2.getNumThreads()}; load average {os.getloadavg()[0]:.2f}")
    rows: dict[tuple[str, int], list[dict]] = {}
    for r in range(args.runs):
        for pace in paces:
            for nice in nices:
                out = one_run(seq, frames, nice, pace == "live")
                rows.setdefault((pace, nice), []).append(out)
                print(f"run {r} {pace:4s} worker_nice={nice:2d}: " + ", ".join(
                    f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in out.items()), flush=True)
    print(f"\n| pace | worker_nice | median CPU ms/frame | p95 wall ms/frame | max wall ms | ATE mm | "
          f"ASIFT jobs run / skipped / deferred | corrections | tracked |")
    print("|---|---|---|---|---|---|---|---|---|")
    for (pace, nice), rs in rows.items():
        def med(key):
            v = [x[key] for x in rs if x[key] is not None]
            return statistics.median(v) if v else float("nan")
        print(f"| {pace} | {nice} | {med('cpu_median_ms'):.1f} | {med('wall_p95_ms'):.1f} | {med('wall_max_ms'):.1f} | "
              f"{med('ate_mm'):.2f} | {med('kf_jobs'):.0f} / {med('kf_skipped'):.0f} / {med('kf_deferred'):.0f} | "
              f"{med('kf_corrections'):.0f} | {med('tracked'):.0f}/{rs[0]['frames']} |")
    print(f"targets on one core: median CPU <= {TARGET_CPU_MS:.0f} ms, p95 wall <= {TARGET_P95_WALL_MS:.0f} ms")


if __name__ == "__main__":
    main()
