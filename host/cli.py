"""The ``stereopath`` command line: one entry point, subcommands in ``host/commands``.

Known errors (:class:`stereopath.device.errors.StereopathError`) are printed on one line
and give exit code 2; a read or write the system refused (:data:`REFUSED_IO`: disk full, read-only
file system, no permission, a failing disk) is printed on one line with exit code 74 (``EX_IOERR``; its
traceback with ``-vv``); anything else is a bug and keeps its traceback.

The commands of the device path (``odometry``, ``sim``, ``device run``) run BLAS at one thread, set
before numpy is loaded (:mod:`stereopath.device.commands.blas_threads`); the other commands keep the
libraries' defaults.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import importlib.util
import logging
import sys

from stereopath.device.errors import StereopathError

# the system refused a read or write: disk full, quota, read-only, permission, a failing disk
REFUSED_IO = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO})

# name -> (module, one-line help).  Groups map to a nested table.
COMMANDS: dict[str, tuple[str, str] | dict[str, tuple[str, str]]] = {
    "demo": ("stereopath.host.commands.demo", "simulate a scan, estimate the path and report (the main job)"),
    "sim": ("stereopath.host.commands.sim", "write a simulated stereo-inertial session (ASL layout)"),
    "eval": ("stereopath.host.commands.eval", "evaluate an estimated trajectory against ground truth"),
    "odometry": ("stereopath.host.commands.odometry", "estimate the camera path of a source and report"),
    "features": ("stereopath.host.commands.features", "count keypoints, matches and correct matches of two images"),
    "keys": {
        "generate": ("stereopath.host.commands.keys", "write a CURVE key pair"),
    },
    "host": {
        "live": ("stereopath.host.commands.live", "receive poses and keyframes from a device and show them live"),
        "map": ("stereopath.host.commands.map", "dense 3D model (mesh, cloud, preview) from a session or stored keyframes"),
        "reprocess": ("stereopath.host.commands.reprocess", "re-estimate a recorded session offline, bundle adjust, and map"),
        "sessions": ("stereopath.host.commands.sessions", "list the sessions `host live` stored and which are incomplete"),
        "export": ("stereopath.host.commands.export", "export a scan for COLMAP, nerfstudio / Gaussian splatting or MCAP (Foxglove)"),
    },
    "device": {
        "selftest": ("stereopath.device.commands.selftest", "check the configured sensors and print pass/fail"),
        "calibrate-stereo": ("stereopath.device.commands.calibrate_stereo", "chessboard pairs -> rig YAML"),
        "calibrate-imu": ("stereopath.device.commands.calibrate_imu", "still-period gyro bias and gravity alignment"),
        "run": ("stereopath.device.commands.run", "capture, estimate, record and stream (the capture service)"),
        "install": ("stereopath.device.commands.install", "install the capture service (user, venv, keys, systemd unit)"),
        "status": ("stereopath.device.commands.status", "show the status the capture service publishes"),
    },
}

GROUP_HELP = {
    "keys": "CURVE key pairs that encrypt and authenticate the link between a device and its hosts",
    "host": "the laptop's side: live poses and keyframes, dense models, offline reprocessing, stored sessions",
    "device": "the scanner box: the capture service, its installation and status, sensor checks and calibration",
}


class _DefaultsFormatter(argparse.HelpFormatter):
    """Each option's default after its help, unless the help already names it (or there is none to name)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if (not action.option_strings or any(action.default is v for v in (None, False, argparse.SUPPRESS))
                or action.default in ([], ()) or "default" in text.lower()):
            return action.help
        return f"{text} (default: %(default)s)".lstrip()


def _add(sub: argparse._SubParsersAction, name: str, module: str, help_text: str) -> None:
    if importlib.util.find_spec(module) is None:  # command not built in this version
        return
    mod = importlib.import_module(module)
    p = sub.add_parser(name, help=help_text, description=(mod.__doc__ or help_text).strip(),
                       formatter_class=_DefaultsFormatter)
    mod.add_arguments(p)
    p.set_defaults(_run=mod.run)


def build_parser() -> argparse.ArgumentParser:
    from stereopath.device import __version__

    parser = argparse.ArgumentParser(prog="stereopath", description="Handheld stereo-inertial 3D scanner.")
    parser.add_argument("--version", action="version", version=f"stereopath {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="stereopath's debug messages too (-vv: the libraries' as well)")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, entry in COMMANDS.items():
        if isinstance(entry, dict):
            grp = sub.add_parser(name, help=GROUP_HELP[name], description=GROUP_HELP[name])
            gsub = grp.add_subparsers(dest=f"{name}_command", metavar="COMMAND")
            for sname, (module, help_text) in entry.items():
                _add(gsub, sname, module, help_text)
            grp.set_defaults(_group=grp)
        else:
            _add(sub, name, *entry)
    return parser


def setup_logging(verbose: int, quiet: bool) -> None:
    """Info by default; ``-q`` warnings and errors; ``-v`` stereopath's debug messages; ``-vv`` everyone's."""
    level = logging.WARNING if quiet else (logging.DEBUG if verbose > 1 else logging.INFO)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    logging.getLogger("stereopath").setLevel(logging.DEBUG if verbose and not quiet else logging.NOTSET)


def main(argv: list[str] | None = None) -> int:
    from stereopath.device.commands.blas_threads import runs_device_path, use_one_blas_thread

    if runs_device_path(sys.argv[1:] if argv is None else argv):
        use_one_blas_thread()  # before the parser's imports load numpy
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "_run"):
        (getattr(args, "_group", None) or parser).print_help()
        return 2
    setup_logging(args.verbose, args.quiet)
    try:
        return int(args._run(args) or 0)
    except StereopathError as exc:
        print(f"stereopath: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.errno not in REFUSED_IO:  # anything else (a missing file we should have checked...) is a bug
            raise
        logging.getLogger("stereopath").debug("system error", exc_info=True)
        print(f"stereopath: error: {exc}", file=sys.stderr)
        return 74  # EX_IOERR
    except KeyboardInterrupt:
        print("stereopath: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
