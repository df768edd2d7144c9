"""Evaluate an estimated trajectory against ground truth: ATE (SE(3) Umeyama, no scale), RPE per
frame, end-point error after first-pose alignment, ground-truth path length and the paper's
accuracy = 100 * (1 - end error / path length).  TUM or KITTI pose files; poses are associated
by timestamp (KITTI files get their times from --times, else 10 Hz)."""

from __future__ import annotations

import argparse
from pathlib import Path

ROWS = (
    ("n_associated", "associated poses", "{:d}"),
    ("path_length_m", "path length (gt)", "{:.3f} m"),
    ("ate_rmse_m", "ATE RMSE", "{:.4f} m"),
    ("ate_max_m", "ATE max", "{:.4f} m"),
    ("rpe_trans_rmse_m", "RPE translation RMSE", "{:.5f} m"),
    ("rpe_rot_rmse_deg", "RPE rotation RMSE", "{:.4f} deg"),
    ("end_error_m", "end-point error", "{:.4f} m"),
    ("end_error_pct", "end error / path", "{:.3f} %"),
    ("accuracy_pct", "accuracy (paper)", "{:.3f} %"),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gt", required=True, type=Path, help="ground-truth trajectory (TUM or KITTI)")
    parser.add_argument("--est", required=True, type=Path, help="estimated trajectory (TUM or KITTI)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--max-diff", type=float, default=0.01, metavar="S",
                        help="largest time difference of an associated pose pair in seconds (default 0.01)")
    parser.add_argument("--times", type=Path, default=None, metavar="FILE",
                        help="times (seconds, one a line, e.g. KITTI times.txt) for KITTI-format pose files")


def _is_kitti(path: Path) -> bool:
    """12 values on the first data line; DatasetError for a missing file, a folder or binary data."""
    from stereopath.device.formats.tum import pose_file_columns

    return pose_file_columns(path) == 12


def read_any(path: Path, times_ns=None):
    """TUM or KITTI file; KITTI rows take ``times_ns`` when given (else 10 Hz)."""
    from stereopath.device.formats.tum import read_kitti_poses, read_tum

    if _is_kitti(path):
        return read_kitti_poses(path, times_ns)
    return read_tum(path)


def run(args: argparse.Namespace) -> int:
    import json

    from stereopath.device.formats.kitti import read_times
    from stereopath.device.errors import DatasetError
    from stereopath.host.evaluation.evaluate import evaluate

    if not args.max_diff > 0:  # also refuses nan
        raise DatasetError(f"--max-diff must be positive, got {args.max_diff}")
    times = read_times(args.times) if args.times is not None else None
    gt = read_any(args.gt, times)
    est = read_any(args.est, times)
    res = evaluate(gt, est, max_diff_s=args.max_diff)
    if args.json:
        print(json.dumps({"gt": str(args.gt), "est": str(args.est), **res}, indent=2))
        return 0
    print(f"ground truth: {args.gt} ({res['n_gt']} poses)")
    print(f"estimate:     {args.est} ({res['n_est']} poses)")
    width = max(len(label) for _, label, _ in ROWS)
    for key, label, fmt in ROWS:
        v = res.get(key)
        print(f"  {label:<{width}}  {'n/a' if v is None else fmt.format(v)}")
    return 0
