"""Export a scan for other tools: COLMAP, nerfstudio (Gaussian splatting, NeRF) or MCAP (Foxglove, ROS 2).

RESULT is a `host reprocess` output (the refined keyframe poses, the bundle-adjusted points and their
observations; the images are read from the session its report.json names, or --session), a recorded
session (its on-board path) or a `host live` store (the keyframes as received).  colmap writes
OUT/sparse/0/*.bin (one rig of two pinhole cameras, a frame per keyframe, the points with their
observations and colours) and OUT/images/cam0|cam1/<t_ns>.png, undistorted; it needs points (a
reprocessed output).  nerfstudio writes OUT/transforms.json (OpenGL camera axes, per-frame
intrinsics), the same images and OUT/sparse_pc.ply (the points, splatfacto's initialisation).  mcap
writes OUT/scan.mcap: the path (/tf, /pose), both cameras' images, the IMU and the points in
Foxglove's schemas; with --ros2, a ROS 2 bag OUT/rosbag2/ in ROS 2 message types instead.  OUT must be
a new or empty folder (--force replaces it); it is written in a temporary folder beside it and
renamed when complete.
"""

from __future__ import annotations

import argparse

FORMATS = ("colmap", "nerfstudio", "mcap")  # stereopath.host.export.run.FORMATS (a test checks)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("result", metavar="RESULT", help="a `host reprocess` output, a recorded session or a `host live` store")
    p.add_argument("--format", required=True, choices=FORMATS, help="what to write")
    p.add_argument("--out", default=None, help="output folder (default: RESULT-<format> beside RESULT)")
    p.add_argument("--force", action="store_true", help="replace an existing non-empty --out")
    p.add_argument("--session", default=None,
                   help="the recorded session of a reprocessed RESULT (default: the one its report.json names)")
    p.add_argument("--text", action="store_true", help="colmap: write the model as text (.txt) instead of binary")
    p.add_argument("--ros2", action="store_true",
                   help="mcap: a ROS 2 bag (OUT/rosbag2/, MCAP storage) in ROS 2 types: sensor_msgs/Image, Imu, "
                        "nav_msgs/Odometry, tf2_msgs/TFMessage")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from stereopath.host.export.run import export_result

    out = args.out or str(Path(args.result).resolve().parent / f"{Path(args.result).resolve().name}-{args.format}")
    s = export_result(args.result, out, args.format, force=args.force, progress=False if args.no_progress else None,
                      session=args.session, text=args.text, ros2=args.ros2)
    if args.format == "mcap":
        counts = ", ".join(f"{k} {v}" for k, v in s["messages"].items())
        print(f"{s['source_kind']} {args.result} -> {out}/{s['file']}: {counts} messages")
    else:
        line = f"{s['source_kind']} {args.result} -> {out}: {s['keyframes']} keyframes, {s['images']} images, {s['points']} points"
        if s.get("mean_reprojection_error_px") is not None:
            line += f", COLMAP mean reprojection error {s['mean_reprojection_error_px']:.3f} px"
        print(line)
    return 0
