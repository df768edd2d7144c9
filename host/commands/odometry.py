"""Estimate the camera path of a source and write trajectory.tum, report.json and path.png.

SOURCE is sim[:SEED], kitti:SEQDIR, euroc:MAV0DIR or session:DIR.  With
--compare paper,stereo,sfm every named estimator runs (each in OUT/<name>) and
the reference paper's Table 2 is printed for this run next to the paper's
own numbers.

It prints the CPU time per frame it used: the whole command (the process so far: imports, reading
and decoding the images, estimation, evaluation and the plot), the frame loop, and the frame loop
without reading and decoding the images (what live frames cost).  BLAS runs at one thread
(:mod:`stereopath.device.commands.blas_threads`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time


def add_arguments(p: argparse.ArgumentParser) -> None:
    from stereopath.host.evaluation.baselines import ESTIMATORS

    p.add_argument("source", help="sim[:SEED] | kitti:SEQDIR | euroc:MAV0DIR | session:DIR")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--estimator", default="stereo", choices=list(ESTIMATORS),
                   help="stereo: ours (the on-board estimator); paper: the reference paper's method; sfm: a "
                        "two-view baseline scaled by the ground truth")
    p.add_argument("--preset", default=None, help="feature preset (see `stereopath features --list-presets`)")
    p.add_argument("--frames", type=int, default=None, help="use only the first N frames")
    p.add_argument("--compare", default=None, help="comma-separated estimators to run and tabulate")
    p.add_argument("--json", action="store_true", help="print the report(s) as JSON")
    p.add_argument("--strict", action="store_true",
                   help="stop at the first unreadable frame (default: skip it, counted in the report)")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from stereopath.host.evaluation.odometry import estimate_sequence, write_outputs
    from stereopath.host.evaluation.paper_table import format_table
    from stereopath.device.formats.source import open_source

    from stereopath.device.formats.fileio import check_out_folder

    check_out_folder(args.out, inputs=[args.source.split(":", 1)[1]] if ":" in args.source else [],
                     not_a_session=True)
    if args.frames is not None and args.frames < 2:
        from stereopath.device.errors import ConfigError

        raise ConfigError(f"--frames must be at least 2 (a path needs two frames), got {args.frames}")
    names = [n.strip() for n in args.compare.split(",")] if args.compare else [args.estimator]
    reports = {}
    for name in names:
        sim_frames = {"frames": args.frames} if args.frames and args.source.startswith("sim") else {}
        seq = open_source(args.source, **sim_frames)
        if hasattr(seq, "skipped_frames"):
            seq.strict = bool(getattr(args, "strict", False))
        run_ = estimate_sequence(seq, name, preset=args.preset, max_frames=args.frames)
        out = Path(args.out) / name if len(names) > 1 else Path(args.out)
        reports[name] = write_outputs(out, run_, seq, args.source)
    if args.json:
        print(json.dumps(reports if len(names) > 1 else reports[names[0]], indent=2))
    else:
        for name, r in reports.items():
            print(f"{name}: frames {r['frames']} (tracked {r['frames_tracked']}), "
                  f"ATE {r['ate_rmse_m']} m, end error {r['end_error_m']} m, "
                  f"median {r['median_frame_ms']:.1f} ms/frame")
            if r["extra"].get("frames_skipped"):
                print(f"warning: {name}: skipped {r['extra']['frames_skipped']} unreadable frame(s) "
                      f"(indexes in report.json; --strict stops instead)", file=sys.stderr)
        if len(names) > 1:
            print(format_table(reports))
        for name, r in reports.items():
            cpu = r["extra"].get("cpu_ms_per_frame")
            if cpu:
                print(f"{name}: CPU ms/frame: frame loop {cpu['frame_loop']:.1f}, without reading and decoding "
                      f"the images {cpu['live_frames']:.1f} (median {cpu['live_median']:.1f}, "
                      f"p95 {cpu['live_p95']:.1f})")
        frames = sum(r["frames"] for r in reports.values())
        if frames:
            print(f"CPU ms/frame of the whole command: {1e3 * time.process_time() / frames:.1f}")
    return 0
