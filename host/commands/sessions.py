"""List the device sessions a `host live` store holds, and which are incomplete.

For each OUT/<session>/: the keyframes stored here, the number the device reported (its session
message and status), how many are missing, and whether the device's rig.yaml is there.  A
session is incomplete while keyframes the device reported are not on this host: they may still
be on the device (a killed run's keyframes are offered again by its next run) or lost with it.
Exit status: 0 when every session is complete, 1 when one is incomplete, 2 on a bad OUT.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", metavar="OUT", help="the --out folder of `host live`")
    parser.add_argument("--incomplete", action="store_true", help="list only the incomplete sessions")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from stereopath.device.errors import ConfigError
    from stereopath.host.live.receiver_sessions import session_states

    if (Path(args.out) / "mav0").is_dir():
        raise ConfigError(f"{args.out} is a session the device recorded, not the --out folder of `host live` "
                          f"(read it with `stereopath host reprocess {args.out} --out DIR`)")
    states = session_states(args.out)
    shown = [s for s in states if s.state == "incomplete"] if args.incomplete else states
    if not shown:
        print("no incomplete sessions" if args.incomplete else f"no sessions in {args.out}")
    width = max((len(s.session_id) for s in shown), default=7)
    if shown:
        print(f"{'session'.ljust(width)}  state       stored  on device  missing  rig")
    for s in shown:
        dev = "?" if s.on_device is None else str(s.on_device)
        print(f"{s.session_id.ljust(width)}  {s.state.ljust(10)}  {s.stored:6d}  {dev:>9}  {s.missing:7d}  {s.rig}")
    return 1 if any(s.state == "incomplete" for s in states) else 0
