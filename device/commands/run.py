"""Capture, estimate, record and stream: the capture service (what systemd runs at boot).

Everything comes from one configuration file (firmware_cfg/device.toml documents every key);
the options below override it.  The session is recorded in the EuRoC/ASL layout with the
estimated trajectory.tum and the keyframe spool; poses, keyframes and a ~1 Hz status go to
hosts over ZeroMQ (CURVE unless --insecure, which only allows loopback endpoints).  Under
systemd (Type=notify) it reports READY=1 once cameras, IMU and recorder work, pings the
watchdog only while frames and IMU samples keep arriving, stops cleanly on SIGTERM and
re-reads the configuration on SIGHUP.  Exit status: 0 after a stop or a bounded run, 1 on a
capture failure, 74 when the disk filled (the session is closed with what fitted), 78 on a bad
configuration.

Without hardware: --source sim --frames 100 --out /tmp/s1 --no-stream --status-file "" (or --insecure
with a configuration whose [stream] endpoints are loopback, e.g. tcp://127.0.0.1:5555; the status
file's default folder, /run/stereopath, is the service's).

The service runs BLAS at one thread (:mod:`stereopath.device.commands.blas_threads`).
"""

from __future__ import annotations

import argparse

from stereopath.device.commands.arg_types import finite_number


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", default=None, metavar="FILE",
                        help="device TOML (default: built-in defaults, see firmware_cfg/device.toml)")
    parser.add_argument("--source", default=None, metavar="SOURCE",
                        help="override source.backend: sim | replay:SPEC (e.g. replay:session:DIR) | picamera2 | "
                             "depthai; sim and replay use their own IMU unless --imu is given")
    parser.add_argument("--imu", choices=("mpu6050", "emulated", "source", "none"), default=None,
                        help="override imu.backend")
    parser.add_argument("--out", default=None, metavar="DIR",
                        help="session folder (must not exist or be empty; default: recorder.dir/<session id>)")
    parser.add_argument("--duration", type=finite_number("seconds", allow_minimum=False), default=None, metavar="S", help="stop after S seconds of capture")
    parser.add_argument("--frames", type=int, default=None, metavar="N", help="stop after N stereo pairs")
    parser.add_argument("--no-stream", action="store_true", help="do not stream (overrides stream.enabled)")
    parser.add_argument("--insecure", action="store_true",
                        help="stream without CURVE (refused unless both endpoints are loopback)")
    parser.add_argument("--status-file", default=None, metavar="PATH",
                        help='override service.status_file ("" = none)')
    parser.add_argument("--wait-for-host", type=finite_number("seconds"), default=0.0, metavar="S",
                        help="before capturing, wait up to S s for a host to connect (so it sees every pose)")
    parser.add_argument("--drain", type=finite_number("seconds"), default=None, metavar="S",
                        help="override stream.drain_s: wait up to S s at the end for a host to ack every keyframe")


def run(args: argparse.Namespace) -> int:
    import logging

    from stereopath.device.commands.blas_threads import use_one_blas_thread

    use_one_blas_thread()  # the entry point has done it before numpy was loaded; this covers direct callers

    from stereopath.device.errors import ConfigError
    from stereopath.device.service.journal import use_journal_format
    from stereopath.device.service.options import RunOptions
    from stereopath.device.service.main import run_service
    from stereopath.device.service.service import EXIT_CONFIG

    use_journal_format()
    try:
        options = RunOptions(source=args.source, imu=args.imu, out=args.out, duration_s=args.duration,
                             frames=args.frames, stream=False if args.no_stream else None,
                             insecure=True if args.insecure else None, status_file=args.status_file,
                             drain_s=args.drain, wait_for_host_s=args.wait_for_host)
    except ConfigError as exc:
        logging.getLogger("stereopath.device.service.service").error("configuration error: %s", exc)
        return EXIT_CONFIG
    return run_service(args.config, options)
