"""The main job on the built-in simulated rig (no hardware, no downloads).

Runs the device (simulated cameras and IMU -> on-board path estimation -> recording ->
streaming) and the host (live receiver) as two processes talking over loopback TCP with
freshly generated CURVE keys, then evaluates the path the host received against the
simulator's ground truth, and builds the dense model of the recorded session.  Writes
OUT/trajectory.tum, OUT/groundtruth.tum, OUT/report.json, OUT/path.png, the model (OUT/mesh.ply,
cloud.ply, model.png, map.json; unless --no-model), the device's recording in OUT/session/, the host's
store in OUT/live/ and both processes' logs in OUT/logs/.  A model that cannot be built (too little
depth) is reported and leaves the path's results as they are.
"""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo-out", help="output folder (default: demo-out)")
    p.add_argument("--frames", type=int, default=None, help="number of simulated frames (default: the full 5.12 m scan)")
    p.add_argument("--seed", type=int, default=0, help="simulation seed")
    p.add_argument("--no-model", action="store_true", help="skip the dense 3D model")


def still_demo_frames() -> int:
    """Frames of the simulated scan's still start (the frame at its last instant too)."""
    import math

    from stereopath.device.sim.session import SimConfig
    from stereopath.device.sim.trajectories import FIRST_FRAME_S, STILL_S

    return math.floor((STILL_S - FIRST_FRAME_S) * SimConfig().rate_hz + 1e-9) + 1


def min_demo_frames() -> int:
    """Frames the demo needs: the still start, then two poses that move (the evaluation aligns three
    positions that are not all the same)."""
    return still_demo_frames() + 2


def run(args: argparse.Namespace) -> int:
    from stereopath.device.errors import ConfigError
    from stereopath.device.formats.fileio import check_out_folder
    from stereopath.host.demo import run_demo

    if args.frames is not None and args.frames < (least := min_demo_frames()):
        raise ConfigError(f"--frames must be at least {least} (the simulated rig rests for its first "
                          f"{still_demo_frames()} frames, and the evaluation needs two poses that move), got {args.frames}")
    check_out_folder(args.out)
    res = run_demo(args.out, frames=args.frames, seed=args.seed, with_model=not args.no_model)
    r = res.report
    x = r.get("extra", {})

    def mm(v):
        return "n/a" if v is None else f"{v * 1000:.2f} mm"

    print("stereopath demo: device and host ran as two processes over CURVE-encrypted loopback TCP")
    print(f"  {r['frames']} frames estimated on the device, {r['frames_tracked']} tracked "
          f"({r['estimator']}, world frame {r['world_frame']}); host received {x.get('poses_received')} poses "
          f"and {x.get('keyframes_received')} keyframes, {x.get('pose_seq_gaps')} pose gaps")
    if r.get("path_length_m") is not None:
        print(f"  path {r['path_length_m']:.3f} m: end error {mm(r['end_error_m'])} ({r['end_error_pct']:.3f} %), "
              f"ATE RMSE {mm(r['ate_rmse_m'])}, accuracy {r['accuracy_pct']:.2f} %")
    print(f"  estimator time per frame: median {r['median_frame_ms']:.1f} ms, p95 {r['p95_frame_ms']:.1f} ms; "
          f"demo wall time {res.wall_s:.1f} s")
    model = x.get("model")
    built = bool(model) and "error" not in model  # (a model that failed was logged as a warning)
    files = "trajectory.tum, groundtruth.tum, report.json, path.png" + (", mesh.ply, cloud.ply, model.png, map.json"
                                                                         if built else "")
    print(f"  wrote {res.out}/: {files}; the device's recording in session/, the host's store in live/")
    return 0
