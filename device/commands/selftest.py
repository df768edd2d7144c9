"""Check the configured sensors and print a pass/fail table (exit code 1 on any failure, 78 on a bad configuration).

Opens the stereo source and captures a few pairs (pairing, frame rate; for two CSI cameras
also the software sync: the multicast route, frames until SyncReady, the skew; and which
camera was taken as left, which ``--cover-left`` checks from the image brightness), opens the IMU
(WHO_AM_I, sample rate, gaps) and reads a still period (gyro bias and noise, gravity
magnitude: keep the unit still), and checks the free disk space of the recorder folder.
On a machine without the hardware use --source sim: simulator frames with the emulated
MPU-6050 (unless --imu says otherwise).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from stereopath.device.capture.imu.base import ImuSource
    from stereopath.device.capture.sources.base import SourceStats, StereoSource
    from stereopath.device.settings import DeviceConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", default=None, metavar="FILE",
                        help="device TOML (default: /etc/stereopath/device.toml if present, else built-in defaults)")
    parser.add_argument("--source", default=None, metavar="SOURCE",
                        help="override source.backend: picamera2 | depthai | sim (simulator frames with the emulated "
                             "MPU-6050) | replay:SPEC (a recording, with its own IMU)")
    parser.add_argument("--imu", choices=("mpu6050", "emulated", "source", "none"), default=None,
                        help="override imu.backend")
    parser.add_argument("--frames", type=int, default=None, help="stereo pairs to capture (selftest.frames)")
    parser.add_argument("--cover-left", action="store_true",
                        help="hold a hand over the LEFT lens during the test: passes only if the left image is the "
                             "darker one (catches swapped cameras)")


@dataclass
class Check:
    name: str
    ok: bool
    value: str
    limit: str = ""


def _free_disk_check(path: str, reserve_mb: float) -> Check:
    import shutil
    from pathlib import Path

    want = p = Path(path).absolute()
    try:
        while not p.exists() and p != p.parent:
            p = p.parent
        if not p.is_dir():  # sessions are folders made in it: a file there (or above it) takes none
            return Check("free disk", False, f"{p} is not a folder" + ("" if p == want else f" (above {want})"),
                         "recorder.dir: a folder")
        free_mb = shutil.disk_usage(p).free / 1e6
    except OSError as exc:
        return Check("free disk", False, f"{want}: {exc.strerror or exc}", "recorder.dir: a folder")
    where = f"{free_mb:.0f} MB at {p}" + ("" if p == want else f" ({want} does not exist yet)")
    return Check("free disk", free_mb >= reserve_mb, where, f">= {reserve_mb:.0f} MB")


COVERED_RATIO = 0.6  # --cover-left: the covered image's mean grey level below this share of the other's


def _sync_check(cfg: DeviceConfig, source: StereoSource, stats: SourceStats) -> Check | None:
    """The picamera2 software sync: route, frames to SyncReady per camera, skew (None for other sources)."""
    state = getattr(source, "sync_state", None)
    if state is None:
        return None
    if state.mode != "software":
        return Check("camera sync", True, f"off ({cfg.source.picamera2.sync}; no SyncMode or sync = \"off\")")
    route = "no route" if state.route is None else ("route unknown" if state.route == "?" else f"route via {state.route}")
    ready = ["-" if n is None else str(n) for n in state.frames_to_ready]
    skew_us = stats.max_skew_ns / 1000
    ok = state.route is not None and None not in state.frames_to_ready  # (the skew is shown: pairs beyond
    return Check("camera sync", ok,                                      #  the tolerance are never made)
                 f"software, {route}, SyncReady after {ready[0]} / {ready[1]} frames (SyncFrames {state.sync_frames}), "
                 f"max skew {skew_us:.0f} us of the {cfg.source.pair_tolerance_us} us pairing tolerance",
                 "both cameras SyncReady, a route")


def _left_check(source: StereoSource, luma: list[list[float]], cover_left: bool) -> Check | None:
    """Which camera is left; with ``cover_left`` the left image must be the darker one."""
    ids = getattr(source, "camera_ids", None)
    named = ""
    if ids is not None:
        from stereopath.device.capture.sources.csi import connector_of

        def say(camera_id: str) -> str:
            where = connector_of(camera_id)
            return camera_id + (f" ({where})" if where else "")

        named = f"left {say(ids[0])}, right {say(ids[1])}"
    if not cover_left:
        return None if ids is None else Check("left camera", True, named, "--cover-left checks it")
    if not luma[0] or not luma[1]:
        return Check("left camera", False, (named + "; " if named else "") + "no frames to compare", "")
    left, right = sum(luma[0]) / len(luma[0]), sum(luma[1]) / len(luma[1])
    grey = f"mean grey left {left:.0f}, right {right:.0f}"
    if left < COVERED_RATIO * right:
        verdict, ok = "left image darker: left is left", True
    elif right < COVERED_RATIO * left:
        verdict, ok = "RIGHT image darker: left and right are swapped (swap source.picamera2.left_id/right_id)", False
    else:
        verdict, ok = "neither image darker: was the left lens covered?", False
    value = "; ".join(x for x in (named, grey, verdict) if x)
    return Check("left camera", ok, value, f"covered < {COVERED_RATIO:.0%} of the other")


def _camera_checks(cfg: DeviceConfig, source: StereoSource, frames_wanted: int, imu_blocks: list,
                   cover_left: bool = False) -> list[Check]:
    import numpy as np

    from stereopath.device.errors import StereopathError

    st = cfg.selftest
    checks: list[Check] = []
    t: list[int] = []
    luma: list[list[float]] = [[], []]
    shapes_ok = True
    try:
        source.open()
    except StereopathError as exc:
        return [Check("camera open", False, str(exc))]
    try:
        checks.append(Check("camera open", True, f"{source.name}"))
        err = None
        try:
            for frame in source:
                t.append(int(frame.t_ns))
                shapes_ok &= frame.left.shape == frame.right.shape and frame.left.size > 0
                if cover_left:
                    luma[0].append(float(np.mean(frame.left)))
                    luma[1].append(float(np.mean(frame.right)))
                imu = getattr(source, "imu", None)
                if imu is not None:
                    imu_blocks.append(imu.read())
                if len(t) >= frames_wanted:
                    break
        except StereopathError as exc:
            err = exc
        stats = source.stats
    finally:
        source.close()
    received = stats.frames_left + stats.frames_right
    ratio = stats.dropped_unpaired / received if received else 1.0
    ok = err is None and len(t) >= min(frames_wanted, 2) and shapes_ok and ratio <= st.max_unpaired_ratio
    value = f"{len(t)} pairs, {stats.dropped_unpaired} unpaired ({100 * ratio:.1f} %)"
    if err is not None:
        value += f"; {err}"
    if not shapes_ok:
        value += "; left/right shapes differ"
    checks.append(Check("frame pairing", ok, value, f"<= {100 * st.max_unpaired_ratio:.0f} % unpaired"))
    if len(t) >= 3:
        dts = np.diff(np.asarray(t, np.int64))
        observed = (len(t) - 1) * 1e9 / (t[-1] - t[0]) if t[-1] > t[0] else 0.0
        if cfg.source.backend in ("picamera2", "depthai"):
            nominal = cfg.source.fps
        else:  # recorded or simulated: the sequence's own rate
            nominal = 1e9 / float(np.median(dts)) if np.median(dts) > 0 else 0.0
        ok = nominal > 0 and abs(observed - nominal) <= st.rate_tolerance * nominal and bool(np.all(dts > 0))
        checks.append(Check("camera rate", ok, f"{observed:.2f} fps",
                            f"{nominal:.2f} fps +-{100 * st.rate_tolerance:.0f} %"))
    else:
        checks.append(Check("camera rate", False, f"only {len(t)} frames", ""))
    for extra in (_sync_check(cfg, source, stats), _left_check(source, luma, cover_left)):
        if extra is not None:
            checks.append(extra)
    return checks


def _imu_checks(cfg: DeviceConfig, imu: ImuSource | None, blocks_from_source: list) -> list[Check]:
    import time

    import numpy as np

    from stereopath.device.core.calibration import imu_still_calibration
    from stereopath.device.errors import StereopathError
    from stereopath.device.core.frames import ImuSamples
    from stereopath.device.capture.imu.mpu6050 import WHO_AM_I_CLONES, WHO_AM_I_MPU6050

    st, s = cfg.selftest, cfg.imu
    checks: list[Check] = []
    if imu is None and not blocks_from_source:
        return [Check("IMU", s.backend == "none", "none configured" if s.backend == "none" else "no IMU data")]
    gaps = 0
    if imu is not None and s.backend != "source":
        try:
            imu.open()
        except StereopathError as exc:
            return [Check("IMU open", False, str(exc))]
        try:
            who = getattr(imu, "who_am_i", None)
            if who is not None:
                ok = who == WHO_AM_I_MPU6050 or who in WHO_AM_I_CLONES
                note = f" ({WHO_AM_I_CLONES[who]} clone)" if who in WHO_AM_I_CLONES else ""
                checks.append(Check("IMU WHO_AM_I", ok, f"{who:#04x}{note}", "0x68 (0x70/0x71 clones)"))
            sleep = getattr(imu, "sleep", time.sleep)
            blocks = []
            n = 0
            polls = int(st.still_s * 1000 / s.read_period_ms) + 2
            try:
                for _ in range(polls):
                    sleep(s.read_period_ms / 1000.0)
                    b = imu.read()
                    blocks.append(b)
                    n += len(b)
            except StereopathError as exc:
                checks.append(Check("IMU read", False, str(exc)))
                return checks
            gaps = len(getattr(imu, "gaps", []))
        finally:
            imu.close()
        samples = ImuSamples.concat(blocks)
        expected_hz = s.rate_hz
    else:
        samples = ImuSamples.concat(blocks_from_source)
        expected_hz = None
    if len(samples) < 10:
        checks.append(Check("IMU samples", False, f"{len(samples)} samples", ">= 10"))
        return checks
    span = (samples.t_ns[-1] - samples.t_ns[0]) / 1e9
    hz = (len(samples) - 1) / span if span > 0 else 0.0
    if expected_hz:
        ok = abs(hz - expected_hz) <= st.imu_rate_tolerance * expected_hz
        checks.append(Check("IMU rate", ok, f"{hz:.1f} Hz", f"{expected_hz:g} Hz +-{100 * st.imu_rate_tolerance:.0f} %"))
    else:
        checks.append(Check("IMU rate", hz > 0, f"{hz:.1f} Hz", "> 0"))
    checks.append(Check("IMU gaps", gaps == 0, str(gaps), "0"))
    cal = imu_still_calibration(samples)
    bias = float(np.max(np.abs(np.rad2deg(cal.gyro_bias_rad_s))))
    noise = float(np.max(np.rad2deg(cal.gyro_std_rad_s)))
    checks.append(Check("gyro still", noise <= st.max_gyro_std_dps, f"std {noise:.3f} deg/s",
                        f"<= {st.max_gyro_std_dps:g} deg/s (unit must rest)"))
    checks.append(Check("gyro bias", bias <= st.max_gyro_bias_dps, f"{bias:.3f} deg/s (largest axis)",
                        f"<= {st.max_gyro_bias_dps:g} deg/s"))
    checks.append(Check("gravity magnitude", abs(cal.gravity_error_m_s2) <= st.gravity_tolerance_m_s2,
                        f"{cal.gravity_m_s2:.3f} m/s^2", f"9.807 +- {st.gravity_tolerance_m_s2:g} m/s^2"))
    return checks


def run_selftest(cfg: DeviceConfig, source: StereoSource | None = None, imu: ImuSource | None = None, cover_left: bool = False) -> list[Check]:
    """All checks; ``source``/``imu`` (unopened) may be injected, otherwise built from ``cfg``."""
    from stereopath.device.errors import StereopathError
    from stereopath.device.capture.imu import create_imu
    from stereopath.device.capture.sources import create_source

    checks: list[Check] = []
    if source is None:
        try:
            source = create_source(cfg.source)
        except StereopathError as exc:
            checks.append(Check("camera open", False, str(exc)))
        except OSError as exc:  # a source.rig_file or recording path the system cannot look at
            checks.append(Check("camera open", False, f"{exc.strerror or exc}: {str(exc.filename)[:100]}"))
    imu_blocks: list = []
    if source is not None:
        checks += _camera_checks(cfg, source, cfg.selftest.frames, imu_blocks, cover_left)
    if imu is None and cfg.imu.backend not in ("none", "source"):
        try:
            imu = create_imu(cfg.imu)
        except StereopathError as exc:
            checks.append(Check("IMU open", False, str(exc)))
    checks += _imu_checks(cfg, imu, imu_blocks if cfg.imu.backend == "source" else [])
    checks.append(_free_disk_check(cfg.recorder.dir, cfg.recorder.reserve_mb))
    return checks


def format_table(checks: list[Check]) -> str:
    w = max(len(c.name) for c in checks)
    v = max(len(c.value) for c in checks)
    lines = [f"{'check':<{w}}  result  {'value':<{v}}  limit"]
    for c in checks:
        lines.append(f"{c.name:<{w}}  {'PASS' if c.ok else 'FAIL':<6}  {c.value:<{v}}  {c.limit}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    import logging
    import sys

    from stereopath.device.core.config import replace
    from stereopath.device.errors import ConfigError
    from stereopath.device.service.service import EXIT_CONFIG
    from stereopath.device.service.options import RunOptions, apply_options, check_rig_file
    from stereopath.device.settings import config_or_installed, load_device_config

    cfg_path = config_or_installed(args.config)
    logging.getLogger(__name__).info("configuration: %s", cfg_path or "built-in defaults")
    try:
        base = load_device_config(cfg_path)
        cfg = apply_options(base, RunOptions(source=args.source, imu=args.imu))  # as `device run` applies them
        check_rig_file(cfg)
    except ConfigError as exc:  # the exit status `device run` gives a bad configuration (EX_CONFIG)
        print(f"stereopath: configuration error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    src, imu_s, st = cfg.source, cfg.imu, cfg.selftest
    if args.source == "sim" and not args.imu and base.imu.backend == "mpu6050":
        # not the simulator's own samples (what `device run` takes): the emulated chip, through the driver checked
        imu_s = replace(imu_s, backend="emulated")
        logging.getLogger(__name__).info("--source sim: using the emulated MPU-6050")
    if args.frames:
        st = replace(st, frames=args.frames)
    if src.backend == "sim" and src.sim.frames < st.frames:
        src = replace(src, sim=replace(src.sim, frames=st.frames))
    cfg = replace(cfg, source=src, imu=imu_s, selftest=st)
    checks = run_selftest(cfg, cover_left=args.cover_left)
    print(format_table(checks))
    failed = [c.name for c in checks if not c.ok]
    print(f"{len(checks) - len(failed)}/{len(checks)} checks passed" + (f"; FAILED: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0
