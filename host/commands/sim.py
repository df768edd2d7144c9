"""Write a simulated stereo-inertial session (the embedded default rig, no hardware) in our
recording layout: EuRoC/ASL mav0/ (PNG images, IMU CSV, sensor.yaml, rig.yaml) plus
groundtruth.tum and manifest.json, readable back with the source spec session:DIR."""

from __future__ import annotations

import argparse
from pathlib import Path

from stereopath.device.commands.arg_types import finite_number


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="session folder to create (must not exist or be empty)")
    parser.add_argument("--frames", type=int, default=None, metavar="N", help="number of stereo frames (default: the whole trajectory)")
    parser.add_argument("--seed", type=int, default=None, metavar="S", help="random seed of scene, noise and shake")
    from stereopath.device.sim.trajectories import TRAJECTORIES

    parser.add_argument("--trajectory", default=None, choices=sorted(TRAJECTORIES),
                        help="camera trajectory of the simulator (default: arc, the hand-held table-top scan; handheld: "
                             "real recorded motion as a 1.5 m scan, started in motion, with auto-exposure and blur)")
    parser.add_argument("--reserve-mb", type=finite_number("megabytes"), default=256.0, metavar="MB",
                        help="free disk space to keep; the recorder refuses to start or stops below it (default 256)")


def run(args: argparse.Namespace) -> int:
    import dataclasses
    import time

    from stereopath.device.errors import ConfigError
    from stereopath.device.formats.fileio import check_out_folder
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim

    if args.frames is not None and args.frames < 1:
        raise ConfigError(f"--frames must be at least 1, got {args.frames}")
    check_out_folder(args.out)
    chosen = {k: v for k, v in (("frames", args.frames), ("seed", args.seed), ("trajectory", args.trajectory))
              if v is not None}
    cfg = SimConfig(**chosen)
    sess = open_sim(cfg)
    config = {"source": "sim", "sim": dataclasses.asdict(cfg) if dataclasses.is_dataclass(cfg) else chosen}
    t0 = time.perf_counter()
    manifest = record_sequence(sess, args.out, config_dict=config, reserve_bytes=int(args.reserve_mb * 2**20))
    dt = time.perf_counter() - t0
    c = manifest["counts"]
    print(f"wrote session {manifest['session_id']} to {args.out}: {c['frames']} stereo frames, "
          f"{c['imu_samples']} IMU samples, ground truth; status {manifest['status']} ({dt:.1f} s)")
    return 0 if manifest["status"] == "closed" else 1
