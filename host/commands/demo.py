"""The main job on the built-in simulated rig: simulate a scan, estimate its path, evaluate, report.

Writes OUT/trajectory.tum, OUT/groundtruth.tum, OUT/report.json and OUT/path.png.
No hardware and no downloads are needed.
"""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo-out", help="output folder (default: demo-out)")
    p.add_argument("--frames", type=int, default=None, help="number of simulated frames (default: the full scan)")
    p.add_argument("--seed", type=int, default=0, help="simulation seed")
    p.add_argument("--estimator", default="stereo", choices=["stereo", "paper", "sfm"])


def run(args: argparse.Namespace) -> int:
    import logging
    import time
    from pathlib import Path

    from device.trajfile import write_tum
    from host.odometry import estimate_sequence, write_outputs
    from host.sequences import open_sequence

    log = logging.getLogger("stereopath.demo")
    start = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seq = open_sequence(f"sim:{args.seed}", frames=args.frames)
    log.info("simulated scan: %d frames, %.2f m of camera travel", len(seq), seq.groundtruth.path_length_m())
    run_ = estimate_sequence(seq, args.estimator)
    write_tum(out / "groundtruth.tum", seq.groundtruth)
    report = write_outputs(out, run_, seq, f"sim:{args.seed}")
    wall = time.perf_counter() - start

    def mm(v):
        return "n/a" if v is None else f"{v * 1000:.2f} mm"

    print(f"stereopath demo: {report['frames']} frames, {report['frames_tracked']} tracked, "
          f"estimator {report['estimator']} ({report['world_frame']})")
    print(f"  path length {report['path_length_m']:.3f} m, end error {mm(report['end_error_m'])} "
          f"({report['end_error_pct']:.3f} %), ATE RMSE {mm(report['ate_rmse_m'])}, "
          f"accuracy {report['accuracy_pct']:.2f} %")
    print(f"  estimator time per frame: median {report['median_frame_ms']:.1f} ms, "
          f"p95 {report['p95_frame_ms']:.1f} ms; wall time {wall:.1f} s")
    print(f"  wrote {out}/trajectory.tum, groundtruth.tum, report.json, path.png")
    return 0
