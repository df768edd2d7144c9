"""Show the health the capture service publishes: state, rates, drops, disk, temperature, last error.

Reads the status file the service rewrites every status period (service.status_file,
default /run/stereopath/status.json; readable by every user).  Exit status 0 when the service
is running and its report is fresh, 1 otherwise (not running, stale, failed or no file).
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", default=None, metavar="FILE",
                        help="device TOML naming service.status_file (default: /etc/stereopath/device.toml "
                             "if present, else built-in defaults)")
    parser.add_argument("--status-file", default=None, metavar="PATH", help="read this status file instead")
    parser.add_argument("--json", action="store_true", help="print the raw status JSON")


def _status_path(args: argparse.Namespace) -> str:
    from stereopath.device.settings import config_or_installed, load_device_config

    if args.status_file is not None:
        return args.status_file
    return load_device_config(config_or_installed(args.config)).service.status_file


def _fmt(value, unit: str = "", digits: int = 1) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}f}{unit}"
    return f"{value}{unit}"


def render(status: dict, age_s: float) -> list[str]:
    """Human-readable lines of a status report."""
    free = status.get("disk_free_bytes")
    rec = status.get("recorder_counts") or {}
    drops = ", ".join(f"{k.replace('dropped_', '')} {v}" for k, v in (status.get("source_drops") or {}).items())
    if status.get("streaming"):
        streaming = (f"{status.get('hosts', 0)} host(s); poses {status.get('pose_endpoint')}, "
                     f"keyframes {status.get('keyframe_endpoint')} ({status.get('keyframes_spooled', 0)} spooled)")
    else:
        streaming = "off"
    if status.get("watchdog_s"):
        watchdog = (f"{status['watchdog_s']:g} s, {status.get('watchdog_pings', 0)} pings, "
                    f"data {'fresh' if status.get('data_fresh') else 'STALE'}")
    else:
        watchdog = "off (not under systemd)"
    lines = [
        f"state        {status.get('state')}  (pid {status.get('pid')}, report {age_s:.1f} s old)",
        f"session      {status.get('session_id')}  {status.get('session_dir') or ''}".rstrip(),
        f"source       {status.get('source')}, IMU {status.get('imu')}",
        f"frame rate   {_fmt(status.get('frame_rate_hz'), ' fps')}  ({status.get('frames', 0)} frames, "
        f"{status.get('frames_estimated', 0)} estimated, {status.get('keyframes', 0)} keyframes)",
        f"IMU rate     {_fmt(status.get('imu_rate_hz'), ' Hz', 0)}  ({status.get('imu_samples', 0)} samples)",
        f"drops        {status.get('dropped_frames', 0)} frames (timestamp gaps)"
        + (f"; source: {drops}" if drops else ""),
        f"IMU gaps     {status.get('imu_gaps', 0)}",
        f"tracking     {status.get('tracking') or '-'}  ({status.get('inliers', 0)} inliers, "
        f"{status.get('estimation_errors', 0)} estimation errors)",
        "pipeline     " + (", ".join(f"{k} {v:.1f} ms" for k, v in (status.get("stage_ms") or {}).items())
                               or "-") + " per frame",
        f"CPU          {_fmt(status.get('cpu_process_pct'), ' %', 0)} of one core (service), "
        f"system load {_fmt(status.get('cpu_load_pct'), ' %', 0)}",
        f"temperature  {_fmt(status.get('temperature_c'), ' C')}",
        f"disk free    {'n/a' if free is None else f'{free / 1e9:.2f} GB'}",
        f"recorder     {status.get('recorder_state')}  ({rec.get('frames', 0)} frames, {rec.get('poses', 0)} poses)",
        f"streaming    {streaming}",
        f"watchdog     {watchdog}",
        f"last error   {status.get('last_error') or 'none'}",
    ]
    if status.get("stop_reason"):
        lines.append(f"stop reason  {status['stop_reason']}")
    return lines


def run(args: argparse.Namespace) -> int:
    import json
    import sys
    import time
    from pathlib import Path

    from stereopath.device.formats.fileio import load_json

    path = Path(_status_path(args))
    if not str(path) or str(path) == ".":
        print("stereopath device status: service.status_file is empty (the service writes no status)", file=sys.stderr)
        return 1
    try:
        status = load_json(path)
    except FileNotFoundError:
        print(f"no status at {path}: the capture service is not running (systemctl status stereopath-capture)",
              file=sys.stderr)
        return 1
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        print(f"cannot read {path}: {exc}", file=sys.stderr)
        return 1
    if not isinstance(status, dict):
        print(f"{path}: not a status report", file=sys.stderr)
        return 1
    age = max(0.0, time.time() - float(status.get("updated_unix") or 0.0))
    if args.json:
        print(json.dumps(status, indent=1))
    else:
        for line in render(status, age):
            print(line)
    state = status.get("state")
    interval = float(status.get("status_interval_s") or 1.0)
    stale = age > 3 * interval + 2.0
    if state in ("running", "waiting", "starting") and stale:
        print(f"WARNING: the report is {age:.0f} s old: the service stopped updating it (hung or killed)",
              file=sys.stderr)
        return 1
    return 0 if state == "running" else 1
