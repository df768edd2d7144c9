"""Accuracy and speed of the estimators (issue 3 targets).  Prints figures; asserts nothing.

    .venv/bin/python benchmarks/bench_odometry.py [--frames N] [--runs R] [--skip-paper]

1. `stereo` on the default simulated scan: end-point error (% of path), ATE RMSE, median and
   p95 estimator time per frame (median over R runs), and the ratio against a SIFT-only run of
   the same estimator in the same process.
2. `stereo` on KITTI 06 frames 0-50.
3. The reference paper's Table 2 for this run: paper, stereo, sfm on the simulated scan.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereopath.device.commands.blas_threads import use_one_blas_thread  # noqa: E402

use_one_blas_thread()  # the device path's BLAS, set before numpy is loaded

from stereopath.device.estimation.base import run_estimator  # noqa: E402
from stereopath.host.evaluation.baselines import make_estimator  # noqa: E402
from stereopath.host.evaluation.evaluate import evaluate  # noqa: E402
from stereopath.device.formats.source import open_source  # noqa: E402

DATA = ROOT.parent / "shared" / "data"


class Cached:
    """Renders a sequence once so that repeated runs time only the estimator."""

    def __init__(self, seq, n=None):
        self.seq = seq
        self.rig = seq.rig
        self.imu = getattr(seq, "imu", None)
        self.groundtruth = getattr(seq, "groundtruth", None)
        frames = seq.frames()
        self.frames_list = [f for _, f in zip(range(n or len(seq)), frames)]

    def __len__(self):
        return len(self.frames_list)

    def frames(self):
        return iter(self.frames_list)


def run_once(seq, name, preset=None, options=None):
    est = make_estimator(name, seq.rig, preset=preset, groundtruth=seq.groundtruth, options=options)
    run = run_estimator(est, seq.frames(), seq.imu)
    m = evaluate(seq.groundtruth, run.trajectory)
    return run, m


def summary(label, runs):
    ms = [statistics.median(r.frame_ms) for r, _ in runs]
    p95 = [sorted(r.frame_ms)[int(0.95 * (len(r.frame_ms) - 1))] for r, _ in runs]
    r, m = runs[-1]
    print(f"{label:34s} end {m['end_error_m'] * 1000:8.2f} mm ({m['end_error_pct']:.3f} %)  "
          f"ATE {m['ate_rmse_m'] * 1000:7.2f} mm  tracked {r.frames_tracked}/{len(r.estimates)}  "
          f"median {statistics.median(ms):6.1f} ms  p95 {statistics.median(p95):6.1f} ms  "
          f"keyframes {r.extra.get('keyframes', '-')}")
    return statistics.median(ms), m


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--skip-paper", action="store_true")
    ap.add_argument("--paper-preset", default="paper", help="feature preset of the paper estimator")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    t = time.perf_counter()
    sim = Cached(open_source("sim:0", **({"frames": args.frames} if args.frames else {})))
    print(f"simulated scan: {len(sim)} frames, path {sim.groundtruth.path_length_m():.3f} m "
          f"(rendered in {time.perf_counter() - t:.1f} s)")
    stereo = [run_once(sim, "stereo") for _ in range(args.runs)]
    med, m_stereo = summary("stereo (onboard modified ASIFT)", stereo)
    sift = [run_once(sim, "stereo", preset="sift") for _ in range(args.runs)]
    med_sift, _ = summary("stereo (SIFT-only keyframes)", sift)
    print(f"time ratio stereo / SIFT-only stereo: {med / med_sift:.2f}")
    print(f"targets: end <= 0.05 % -> {m_stereo['end_error_pct']:.3f} %; ATE <= 3 mm -> "
          f"{m_stereo['ate_rmse_m'] * 1000:.2f} mm; median <= 100 ms -> {med:.1f} ms")

    kdir = DATA / "kitti_odometry/sequences/06"
    if kdir.is_dir():
        kitti = Cached(open_source(f"kitti:{kdir}"))
        k = [run_once(kitti, "stereo") for _ in range(max(1, args.runs - 2))]
        _, mk = summary("KITTI 06 0-50 stereo", k)
        print(f"targets: end <= 1 % -> {mk['end_error_pct']:.3f} %; ATE <= 0.3 m -> {mk['ate_rmse_m']:.3f} m")

    if not args.skip_paper:
        from stereopath.host.evaluation.paper_table import format_table

        reports = {}
        variants = (("paper", "paper", args.paper_preset, None),
                    ("paper-rc", "paper", args.paper_preset, {"rotation_compensated": True}),
                    ("stereo", "stereo", None, None), ("sfm", "sfm", None, None))
        for label, name, preset, opts in variants:
            run, m = run_once(sim, name, preset=preset, options=opts)
            reports[label] = {"end_error_m": m["end_error_m"], "ate_rmse_m": m["ate_rmse_m"],
                              "accuracy_pct": m["accuracy_pct"], "path_length_m": m["path_length_m"]}
            print(f"  {label}: {len(run.estimates)} poses, {sum(run.frame_ms) / 1000:.0f} s estimator time")
        print("paper-rc = the paper's pipeline with the rotation between positions removed from Eq. 4")
        print(format_table(reports))


if __name__ == "__main__":
    main()
