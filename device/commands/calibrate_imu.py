"""Estimate the gyro bias and the gravity direction from a still period of IMU data.

SOURCE is a recorded sequence (euroc:DIR, session:DIR) or "live" (the configured IMU,
read for --seconds while the unit rests).  The window is the span of the recorded image
frames (--window frames, the default for recordings), an automatically detected still
stretch (--window auto) or explicit times in seconds (--window T0:T1).  A window in which the
unit moved is refused; when it was the default one (a hand-held scan's frames), the still
stretch --window auto finds is used instead, with a warning.  The gyro and accelerometer norms
with the window shaded are drawn to ``--plot FILE`` (by default ``<out>_still_window.png`` beside
``--out``).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from stereopath.device.commands.arg_types import finite_number

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", metavar="SOURCE", help="euroc:DIR, session:DIR or live")
    parser.add_argument("--window", default=None,
                        help="frames | auto | T0:T1 (seconds, same clock as the data); default frames, "
                             "or auto when the source has no frames")
    seconds = finite_number("seconds", allow_minimum=False)
    parser.add_argument("--min-still-s", type=seconds, default=2.0, help="shortest still window accepted (auto)")
    parser.add_argument("--seconds", type=seconds, default=5.0, help="live: how long to read")
    parser.add_argument("--config", default=None, help="device TOML (live: the [imu] section)")
    parser.add_argument("--imu", choices=("mpu6050", "emulated"), default=None, help="live: override imu.backend")
    parser.add_argument("--out", default=None, help="write the result as YAML here")
    parser.add_argument("--plot", default=None, metavar="FILE.png",
                        help="write the norms of gyro and accelerometer with the still window shaded here (default "
                             "with --out: <out>_still_window.png beside it; needs matplotlib, skipped without it)")
    parser.add_argument("--no-plot", action="store_true", help="do not write the plot")


def _window(samples, frames_t, spec: str, min_still_s: float):
    from stereopath.device.core.calibration import detect_still_window
    from stereopath.device.errors import CalibrationError

    if spec == "frames":
        if frames_t is None or len(frames_t) < 2:
            raise CalibrationError("--window frames: the source has no image frames")
        return int(frames_t[0]), int(frames_t[-1])
    if spec == "auto":
        return detect_still_window(samples, min_duration_s=min_still_s)
    from decimal import InvalidOperation

    from stereopath.device.formats.tum import seconds_to_ns

    parts = spec.split(":")
    try:
        if len(parts) != 2:
            raise InvalidOperation
        a, b = (seconds_to_ns(v.strip()) for v in parts)
    except InvalidOperation:
        raise CalibrationError(f"--window {spec!r}: expected frames, auto or T0:T1 in seconds") from None
    except ValueError:  # not finite, or beyond int64 nanoseconds
        raise CalibrationError(f"--window {spec!r}: T0 and T1 must be finite times (int64 nanoseconds)") from None
    if b <= a:
        raise CalibrationError(f"--window {spec!r}: T1 must be after T0")
    return a, b


def _live(args):
    import time

    from stereopath.device.core.frames import ImuSamples
    from stereopath.device.capture.imu import create_imu
    from stereopath.device.settings import load_device_config

    cfg = load_device_config(args.config)
    settings = cfg.imu
    if args.imu:
        from stereopath.device.core.config import replace

        settings = replace(settings, backend=args.imu)
    imu = create_imu(settings)
    if imu is None:
        from stereopath.device.errors import ConfigError

        raise ConfigError("imu.backend = 'none': nothing to calibrate")
    imu.open()
    blocks = []
    try:
        sleep = getattr(imu, "sleep", time.sleep)  # the emulator's simulated clock, or real time
        n = max(1, int(args.seconds * 1000 / settings.read_period_ms))
        for _ in range(n):
            sleep(settings.read_period_ms / 1000.0)
            blocks.append(imu.read())
    finally:
        imu.close()
    return ImuSamples.concat(blocks), None


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from stereopath.device.core.calibration import check_still, imu_still_calibration
    from stereopath.device.errors import CalibrationError, DatasetError

    from stereopath.device.formats.fileio import check_out_file

    out = check_out_file(args.out, example="imu_calibration.yaml") if args.out else None
    plot = None
    if not args.no_plot and (args.plot or out is not None):
        from stereopath.device.commands.calibration_plots import default_plot_path

        plot = check_out_file(args.plot or default_plot_path(out, "still_window"), option="--plot",
                              example="still_window.png")
    if args.source == "live":
        samples, frames_t = _live(args)
        window = args.window or "auto"
        if window == "frames":
            raise CalibrationError("--window frames needs a recorded source")
        if window == "auto" and len(samples):
            window = f"{samples.t_ns[0] / 1e9}:{samples.t_ns[-1] / 1e9 + 1e-9}"
    else:
        from stereopath.device.formats import open_source

        seq = open_source(args.source)
        samples = seq.imu
        if samples is None or not len(samples):
            raise DatasetError(f"{args.source}: the sequence has no IMU samples")
        frames_t = np.asarray(seq.t_ns) if len(seq) else None
        window = args.window or ("frames" if frames_t is not None and len(frames_t) >= 2 else "auto")
    t0, t1 = _window(samples, frames_t, window, args.min_still_s)
    still = samples.between(t0 - 1, t1)
    try:
        check_still(still, f"the window {window} ({(t1 - t0) / 1e9:.2f} s)")
    except CalibrationError as exc:
        if args.source == "live":
            raise CalibrationError(f"{exc}; hold the unit still and run again") from None
        if args.window is not None:
            raise CalibrationError(f"{exc}; give a still stretch with --window auto (--min-still-s S for a "
                                   f"shorter one) or --window T0:T1") from None
        try:  # the default window (the frames of a hand-held scan) moved: the still stretch the IMU holds
            t0, t1 = _window(samples, frames_t, "auto", args.min_still_s)
        except CalibrationError as auto_exc:
            raise CalibrationError(f"{exc}; and --window auto: {auto_exc} (--min-still-s S for a shorter "
                                   f"one, or --window T0:T1)") from None
        log.warning("%s; using the still stretch --window auto found instead", exc)
        window, still = "auto", samples.between(t0 - 1, t1)
    res = imu_still_calibration(still)
    deg = np.rad2deg
    print(f"window: {window}  {res.samples} samples over {res.duration_s:.2f} s")
    print("gyro bias:  [" + ", ".join(f"{v:+.5f}" for v in res.gyro_bias_rad_s) + "] rad/s  ("
          + ", ".join(f"{v:+.3f}" for v in deg(res.gyro_bias_rad_s)) + " deg/s)")
    print("gyro std:   [" + ", ".join(f"{v:.5f}" for v in res.gyro_std_rad_s) + "] rad/s")
    print("accel mean: [" + ", ".join(f"{v:+.4f}" for v in res.accel_mean_m_s2) + "] m/s^2")
    print(f"gravity:    {res.gravity_m_s2:.4f} m/s^2 ({res.gravity_error_m_s2:+.4f} vs 9.80665)")
    tilt = deg(np.arccos(np.clip(res.R_world_imu[2, 2], -1, 1)))
    print(f"R_world_imu (gravity-aligned, yaw 0): tilt of IMU z from vertical {tilt:.2f} deg")
    for row in res.R_world_imu:
        print("  [" + ", ".join(f"{v:+.6f}" for v in row) + "]")
    if out is not None:
        import yaml

        from stereopath.device.formats.fileio import write_atomic

        text = (f"# stereopath device calibrate-imu {args.source} (window {window})\n"
                + yaml.safe_dump(res.as_dict(), sort_keys=False, default_flow_style=None))
        out.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(out, text.encode("utf-8"))
        print(f"wrote {out}")
    if plot is not None:
        from stereopath.device.commands.calibration_plots import plot_still_window

        frames_span = (int(frames_t[0]), int(frames_t[-1])) if frames_t is not None and len(frames_t) >= 2 else None
        why_not = plot_still_window(plot, samples.t_ns, samples.gyro_rad_s, samples.accel_m_s2, (t0, t1), window,
                                    frames_span)
        print(f"plot skipped: {why_not}" if why_not else f"wrote {plot}")
    return 0
