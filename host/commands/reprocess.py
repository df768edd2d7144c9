"""Reprocess a recorded session offline: re-estimate the path, refine it by bundle adjustment, map.

SESSION is a folder written by the recorder or `stereopath sim` (mav0/ inside).  Stages: the
stereo estimator again (estimate), modified-ASIFT keypoints at every keyframe matched into
tracks (tracks), bundle adjustment of keyframe poses and points on the reprojection error in
both cameras plus a refinement of the frames between keyframes (ba), and the dense model with
the refined path (map; --no-map skips it).  Each finished stage is stored in OUT/stages/ and
reused by a later run with the same input and settings, so an interrupted run (Ctrl-C) resumes
where it stopped; --force recomputes everything.

OUT gets trajectory.tum (the refined path), report.json (before/after figures: the session's
on-board path, the re-estimate and the adjusted path, with errors when the session has ground
truth), path.png, errors.png (with ground truth), mesh.ply, cloud.ply, model.png, map.json and
report.html (open it in a browser); when the bundle adjustment applied a disparity offset, also
rig_refined.yaml: the session's rig with the right principal point corrected, for the device's
later sessions of the same rig (source.rig_file).

Several sessions (SESSION may also be a folder of sessions or a glob pattern) are reprocessed as
a fleet on Ray (pip install 'stereopath[fleet]'): each session's stages and outputs go into
OUT/<session id>/ exactly as the one-session command writes them, sessions run in parallel
(--ray auto, the default with more than one session, starts a local Ray with the machine's
cores; --ray ADDRESS joins a running cluster), a failing session is reported while the others
finish, a worker that dies is retried from its session's last stored stage, and Ctrl-C stops
cleanly: the same command resumes.  OUT/fleet.json and OUT/fleet.html summarise the run.
"""

from __future__ import annotations

import argparse
import sys

from stereopath.device.commands.arg_types import finite_number
from stereopath.host.commands.map import MAP_PRESET_CHOICES
from stereopath.host.reprocess.preset_names import DEFAULT_PRESET, PRESET_ABOUT

PRESET_NAMES = tuple(PRESET_ABOUT)  # REPROCESS_PRESETS' names (a test checks), without importing the pipeline


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("session", metavar="SESSION", nargs="+",
                   help="recorded session folder (with mav0/); several, a folder of sessions or a glob: a fleet run")
    p.add_argument("--out", required=True,
                   help="output folder (created; stages are kept in OUT/stages, or OUT/<session id>/stages in a fleet)")
    p.add_argument("--preset", default=DEFAULT_PRESET, choices=PRESET_NAMES,
                   help="reprocessing settings: " + "; ".join(f"{k}: {v}" for k, v in PRESET_ABOUT.items()))
    p.add_argument("--no-map", action="store_true", help="skip the dense model")
    p.add_argument("--map-preset", default="auto", choices=MAP_PRESET_CHOICES,
                   help="depth range and voxel size of the model: object scans (4 mm), rooms (2 cm), large rooms "
                        "(5 cm), or auto: chosen from the keyframes' stereo depth (default: auto; map.json says why)")
    p.add_argument("--imu-priors", action="store_true",
                   help="add gyro-integrated rotations between keyframes to the bundle adjustment")
    p.add_argument("--force", action="store_true", help="recompute every stage even when stored ones match")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--strict", action="store_true",
                   help="stop at the first unreadable frame (default: skip it, counted in the report)")
    f = p.add_argument_group("fleet (several sessions, on Ray)")
    f.add_argument("--ray", default=None, metavar="auto|ADDRESS",
                   help="'auto' starts a local Ray (the default with several sessions); HOST:PORT joins a cluster")
    f.add_argument("--cpus", type=int, default=None, metavar="N", help="CPUs of the local Ray (default: all)")
    f.add_argument("--task-cpus", type=finite_number("CPUs", allow_minimum=False), default=1.0, metavar="N", help="CPUs declared per session (default 1)")
    f.add_argument("--task-memory-gb", type=finite_number("GB"), default=None, metavar="GB",
                   help="memory declared per session (default 1.5 with the dense model, 1.2 without: the peaks benchmarks/bench_scale.py measures up to 800 frames)")
    f.add_argument("--max-in-flight", type=int, default=None, metavar="N",
                   help="sessions at a time (default: what the cluster's CPUs and memory hold)")
    f.add_argument("--retries", type=int, default=3, metavar="N",
                   help="re-runs of a session whose worker or node died (default 3)")
    f.add_argument("--path-map", action="append", default=[], metavar="HERE=WORKER",
                   help="a path prefix on this machine and where cluster workers see it (repeatable)")


def _is_fleet(args: argparse.Namespace) -> bool:
    if args.ray is not None or len(args.session) > 1:
        return True
    from pathlib import Path

    from stereopath.host.fleet.sessions import looks_like_session

    one = args.session[0]
    if any(c in one for c in "*?["):
        return True
    d = Path(one)
    return d.is_dir() and not looks_like_session(d) and any(looks_like_session(c) for c in d.iterdir())


def run(args: argparse.Namespace) -> int:
    if _is_fleet(args):
        return run_fleet_command(args)
    args.session = args.session[0]
    return run_one(args)


def run_fleet_command(args: argparse.Namespace) -> int:
    from pathlib import Path

    from stereopath.host.fleet.progress import FleetProgress
    from stereopath.host.fleet.runner import FleetOptions, ReprocessSettings, run_fleet
    from stereopath.host.fleet.state import TASK_MEMORY_GB, TASK_MEMORY_NO_MAP_GB
    from stereopath.host.fleet.sessions import PathMap, expand_sessions

    from stereopath.device.formats.fileio import check_out_folder

    sessions = expand_sessions(args.session)
    check_out_folder(args.out)
    for s in sessions:  # DIR/<session id>/ is the session itself when DIR is the folder holding the sessions
        check_out_folder(Path(args.out) / s.id, option=f"--out {args.out}: session {s.id}'s output folder",
                         inputs=[s.path], not_a_session=True, instead=Path(args.out).resolve().parent / "reprocessed")
    settings = ReprocessSettings(preset=args.preset, do_map=not args.no_map, map_preset=args.map_preset,
                                 imu_priors=args.imu_priors, force=args.force,
                                 strict=bool(getattr(args, "strict", False)))
    memory = (args.task_memory_gb if args.task_memory_gb is not None
              else TASK_MEMORY_GB if settings.do_map else TASK_MEMORY_NO_MAP_GB)
    options = FleetOptions(ray=args.ray or "auto", num_cpus=args.cpus, task_cpus=args.task_cpus,
                           task_memory_gb=memory, max_in_flight=args.max_in_flight, retries=args.retries,
                           path_map=PathMap.parse(args.path_map), ray_logs=args.verbose > 0)
    progress = None if args.no_progress else FleetProgress()
    print(f"{len(sessions)} session(s) into {args.out}/<session id>/ on Ray ({options.ray})")
    try:
        res = run_fleet(sessions, args.out, settings, options, on_update=progress)
    except KeyboardInterrupt:
        if progress is not None:
            progress.close()
        print(f"interrupted: finished stages are kept in {args.out}/<session id>/stages and the summary in "
              f"{args.out}/fleet.json; run the same command again to resume", file=sys.stderr)
        return 130
    if progress is not None:
        progress.close()
    c = res.counts()
    print(f"{c['done']} of {len(sessions)} session(s) done, {c['failed']} failed; wall time {res.wall_s:.1f} s "
          f"({res.cluster.get('nodes')} node(s), {res.cluster.get('cpus')} CPUs)")
    for st in res.sessions:
        r = st.result or {}
        if st.status == "done":
            ate = r.get("ate_rmse_m")
            print(f"  {st.session.id}: done, {r.get('keyframes')} keyframes, "
                  f"ATE {'n/a' if ate is None else f'{ate * 1000:.3f} mm'}, {r.get('wall_s', 0):.1f} s"
                  + (f", {st.attempts} attempts" if st.attempts > 1 else ""))
        else:
            print(f"  {st.session.id}: {st.status}" + (f": {st.error}" if st.error else ""))
    print(f"wrote {args.out}/fleet.json, {args.out}/fleet.html")
    return 0 if c["failed"] == 0 else 1


def run_one(args: argparse.Namespace) -> int:
    import time

    from stereopath.host.reprocess.pipeline import RunChoices, reprocess_session

    from stereopath.device.formats.fileio import check_out_folder

    check_out_folder(args.out, inputs=[args.session], not_a_session=True)
    start = time.perf_counter()
    try:
        choices = RunChoices(do_map=not args.no_map, map_preset=args.map_preset, force=args.force,
                             imu_priors=args.imu_priors, progress=False if args.no_progress else None)
        res = reprocess_session(args.session, args.out, preset=args.preset, run=choices,
                                strict=bool(getattr(args, "strict", False)))
    except KeyboardInterrupt:
        print(f"interrupted: finished stages are kept in {args.out}/stages; run the same command again to resume",
              file=sys.stderr)
        return 130
    wall = time.perf_counter() - start
    ba = res.report["extra"]["before_after"]

    def mm(m):
        v = None if not m else m.get("ate_rmse_m")
        return "n/a" if v is None else f"{v * 1000:.3f} mm"

    stages = ", ".join(f"{k} {v}" + (f" {res.seconds[k]:.1f} s" if v == "computed" else "")
                       for k, v in res.stages.items())
    print(f"reprocessed {res.report['frames']} frames ({stages}); wall time {wall:.1f} s")
    if any(m and m.get("ate_rmse_m") is not None for m in (ba["reestimated"], ba["bundle_adjusted"])):
        line = f"ATE: re-estimated {mm(ba['reestimated'])}, bundle adjusted {mm(ba['bundle_adjusted'])}"
        if ba["onboard"]:
            line = f"ATE: on-board {mm(ba['onboard'])}, " + line[5:]
        if ba["ate_ratio_vs_onboard"] is not None:
            line += f" (x{ba['ate_ratio_vs_onboard']:.2f} of on-board)"
        elif ba["ate_ratio_vs_reestimated"] is not None:
            line += f" (x{ba['ate_ratio_vs_reestimated']:.2f})"
        print(line)
    if res.report["extra"].get("frames_skipped"):
        print(f"warning: skipped {res.report['extra']['frames_skipped']} unreadable frame(s) "
              f"(indexes in report.json; --strict stops instead)", file=sys.stderr)
    if res.report["extra"].get("groundtruth_error"):
        print(f"warning: ground truth not used: {res.report['extra']['groundtruth_error']}", file=sys.stderr)
    print(f"wrote {args.out}/" + ", ".join(res.files))
    return 0
