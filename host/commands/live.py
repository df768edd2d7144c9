"""Receive a device's live poses and keyframes, show them, and store them.

Connects to the device (CURVE unless --insecure, which only allows loopback), shows a live
view on stderr (position, speed, tracking, rates, drops, link quality), optionally in rerun,
and writes into OUT, per device session: OUT/<session>/poses.tum (flushed as poses arrive),
OUT/<session>/keyframes/ (one file per keyframe plus index.csv), and OUT/receiver.json
(messages received, duplicates, pose seq gaps, rejected messages by reason).  Restarting with
the same OUT resumes: keyframes already stored are not received twice.

The device sends its rig once per session: it is stored as OUT/<session>/rig.yaml, and --map
maps each session with it (no --rig needed; a --rig that differs from the device's is named in a
warning and the device's is used).  Keyframes of an earlier device session that no host had
(the device was killed) arrive after the live ones, into their own OUT/<session>/; sessions
still missing keyframes are logged at start and at the end (and listed by `host sessions OUT`).

Exit status: 0; 1 when keyframes could not be stored or mapped, or no connection to the device
was made (a wrong address or port, or no device running); 2 when the device refused this host's key
or the handshake failed.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time

from stereopath.device.commands.arg_types import finite_number

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", required=True, metavar="ADDRESS",
                        help="device address HOST[:PORT] (pose port, default 5555; keyframes on PORT+1)")
    parser.add_argument("--keyframe-port", type=int, default=None, help="keyframe port if not PORT+1")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--keys", metavar="DIR", help="host key directory: one *.key_secret and device.key "
                        "(required unless --insecure; `stereopath keys generate`)")
    parser.add_argument("--device-key", metavar="FILE", help="the device's public key if not KEYS/device.key")
    parser.add_argument("--insecure", action="store_true", help="plain TCP without CURVE (loopback addresses only)")
    view = parser.add_mutually_exclusive_group()
    view.add_argument("--rerun", action="store_true", help="show the path, camera and keyframes in a rerun viewer")
    view.add_argument("--rerun-save", metavar="FILE.rrd", help="write the rerun recording to FILE.rrd")
    parser.add_argument("--rig", metavar="FILE.yaml",
                        help="rig calibration for the rerun camera frustum, and for --map when the device sends none")
    parser.add_argument("--duration", type=finite_number("seconds", allow_minimum=False), default=None, metavar="S", help="stop after S seconds")
    parser.add_argument("--window", type=int, default=8, help="keyframes in flight (credit window)")
    parser.add_argument("--no-fsync", action="store_true", help="do not fsync each stored keyframe")
    parser.add_argument("--map", action="store_true",
                        help="build the dense model as keyframes arrive (with the device's rig); mesh refreshed every "
                             "--map-every")
    parser.add_argument("--mcap", metavar="FILE.mcap", default=None,
                        help="also record the stream as it arrives into an MCAP file (poses, keyframe images, rig) "
                             "for Foxglove; complete when the command ends")
    parser.add_argument("--map-every", type=int, default=10, metavar="N", help="refresh the live mesh every N keyframes")


def run(args: argparse.Namespace) -> int:
    from stereopath.device.errors import ConfigError
    from stereopath.host.live.view import RerunView, TerminalView
    from stereopath.host.live.receiver import Receiver
    from stereopath.host.live.receiver_config import ReceiverConfig, endpoints_from_address

    from stereopath.device.formats.fileio import check_out_folder

    if args.duration is not None and args.duration <= 0:
        raise ConfigError(f"--duration must be positive, got {args.duration}")
    check_out_folder(args.out)
    if args.rerun_save:
        from stereopath.device.formats.fileio import check_out_file

        check_out_file(args.rerun_save, option="--rerun-save", example="live.rrd")
    pose_ep, kf_ep = endpoints_from_address(args.device, args.keyframe_port)
    config = ReceiverConfig(pose_endpoint=pose_ep, keyframe_endpoint=kf_ep, insecure=args.insecure,
                            keys_dir=args.keys, device_key=args.device_key, window=args.window,
                            fsync=not args.no_fsync)
    mcap_path = None
    if getattr(args, "mcap", None):
        from stereopath.device.formats.fileio import check_out_file

        mcap_path = check_out_file(args.mcap, option="--mcap", example="live.mcap")
        if mcap_path.exists():  # an earlier recording is never overwritten
            raise ConfigError(f"--mcap {mcap_path}: exists; give a new file name")
    rig = None
    if args.rig:
        from stereopath.device.formats.rig_files import load_rig_yaml

        rig = load_rig_yaml(args.rig)
    rerun_view = None
    if args.rerun or args.rerun_save:
        rerun_view = RerunView(save_path=args.rerun_save, spawn=args.rerun, rig=rig)
    mapper = None
    if args.map:
        from stereopath.host.live.live_map import LiveMapper

        mapper = LiveMapper(rig, args.out, every=args.map_every,
                            on_mesh=getattr(rerun_view, "on_mesh", None) if rerun_view else None,
                            rig_for=lambda sid: receiver.sessions.rig(sid))

    sink = None
    if mcap_path is not None:
        from stereopath.host.live.mcap_sink import McapSink

        sink = McapSink(mcap_path, rig_for=lambda sid: receiver.sessions.rig(sid) or rig)

    def on_keyframe(kf, new):
        if rerun_view is not None:
            rerun_view.on_keyframe(kf, new)
        if mapper is not None:
            mapper.on_keyframe(kf, new)
        if sink is not None:
            sink.on_keyframe(kf, new)

    def on_pose(pose):
        if rerun_view is not None:
            rerun_view.on_pose(pose)
        if sink is not None:
            sink.on_pose(pose)

    def on_rebase(msg):
        if rerun_view is not None:
            rerun_view.on_rebase(msg)
        if mapper is not None:
            mapper.on_rebase(msg)
        if sink is not None:
            sink.on_rebase(msg)
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set()) \
        if threading.current_thread() is threading.main_thread() else None
    term = TerminalView()
    receiver = Receiver(config, args.out,
                        on_pose=on_pose if (rerun_view or sink) else None,
                        on_keyframe=on_keyframe if (rerun_view or mapper or sink) else None,
                        on_rebase=on_rebase if (rerun_view or mapper or sink) else None)
    t0 = time.monotonic()
    before = _counts(receiver.stats)  # receiver.json's counters run on over restarts with the same OUT
    try:
        receiver.run(duration_s=args.duration, stop=stop, on_tick=term.update)
    except KeyboardInterrupt:
        pass
    finally:
        term.close()
        receiver.close()
        models = {}
        if mapper is not None:
            models = mapper.close()
            for session, folder in models.items():
                log.info("dense model of session %s: %s", session, folder)
        if rerun_view is not None:
            rerun_view.close()
        if sink is not None:
            counts = sink.close()
            log.info("--mcap %s: %d poses, %d keyframes recorded", mcap_path, counts["pose"], counts["cam0"])
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return _exit_status(receiver, mapper, models, args.device, time.monotonic() - t0, before)


def _counts(stats) -> dict[str, int]:
    """Messages of every kind received, and the link's counters (connects, refusals), so far."""
    return {"messages": stats.received.total(), **stats.link.to_json()}


def _exit_status(receiver, mapper, models, device: str = "", listened_s: float = 0.0,
                 before: dict[str, int] | None = None) -> int:
    """Log the totals; 1 if keyframes could not be stored or mapped, or this run never connected to the
    device, 2 if the device let nothing through (its key refused, or no handshake).  ``before``: the counters
    when this run started (:func:`_counts`)."""
    st = receiver.stats
    log.info("received %d poses, %d keyframes (%d duplicates), %d pose seq gaps, %d rejected; sessions: %s",
             st.received.pose, st.received.keyframe, st.duplicates, st.pose_seq_gaps, st.rejected,
             ", ".join(st.sessions) or "none")
    if receiver.storage_error is not None:
        print(f"stereopath: error: keyframes could not be stored on this host ({receiver.storage_error}); the "
              f"device keeps every keyframe not acknowledged and sends it to the next `host live` with space",
              file=sys.stderr)
        return 1
    if mapper is not None and mapper.rejected and not models:
        print(f"stereopath: error: --map: none of the {mapper.rejected} keyframe(s) could be mapped (see the "
              f"warnings above: no calibration matching their rig); no model written", file=sys.stderr)
        return 1
    now, before = _counts(st), before or {}
    run = {k: v - before.get(k, 0) for k, v in now.items()}  # this run's
    got = run["messages"]
    if got == 0 and run["auth_failures"]:
        print("stereopath: error: the device refused this host's key: nothing received (add this host's public "
              "key to the device's clients folder)", file=sys.stderr)
        return 2
    if got == 0 and run["handshake_failures"]:
        print("stereopath: error: no handshake with the device: nothing received (wrong device key, or CURVE "
              "on one side only?)", file=sys.stderr)
        return 2
    if got == 0 and run["connects"] == 0:
        print(f"stereopath: error: no connection to {device} in {listened_s:.1f} s: is `stereopath device run` "
              f"running there (`stereopath device status` on the box), and are the address and ports right?",
              file=sys.stderr)
        return 1
    if got == 0:
        log.warning("connected to %s, but nothing arrived in %.1f s, not even its status (sent every "
                    "service.status_interval_s)", device, listened_s)
    return 0
