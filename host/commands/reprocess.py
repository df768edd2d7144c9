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
report.html (open it in a browser).
"""

from __future__ import annotations

import argparse

# stereopath.host.reprocess.pipeline.REPROCESS_PRESETS (kept here so that building the parser imports nothing heavy;
# a test checks they agree)
PRESET_NAMES = ("standard", "quick", "paper", "full")
DEFAULT_PRESET = "standard"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("session", metavar="SESSION", help="recorded session folder (with mav0/)")
    p.add_argument("--out", required=True, help="output folder (created; stages are kept in OUT/stages)")
    p.add_argument("--preset", default=DEFAULT_PRESET, choices=PRESET_NAMES,
                   help=f"reprocessing settings (default {DEFAULT_PRESET}; see README)")
    p.add_argument("--no-map", action="store_true", help="skip the dense model")
    p.add_argument("--map-preset", default="object", choices=["object", "room"],
                   help="depth range and voxel size of the model: object scans (4 mm) or rooms (2 cm)")
    p.add_argument("--imu-priors", action="store_true",
                   help="add gyro-integrated rotations between keyframes to the bundle adjustment")
    p.add_argument("--force", action="store_true", help="recompute every stage even when stored ones match")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--strict", action="store_true",
                   help="stop at the first unreadable frame (default: skip it, counted in the report)")


def run(args: argparse.Namespace) -> int:
    import time

    from stereopath.host.reprocess.pipeline import reprocess_session

    from stereopath.device.formats.fileio import check_out_folder

    check_out_folder(args.out)
    start = time.perf_counter()
    try:
        res = reprocess_session(args.session, args.out, preset=args.preset, do_map=not args.no_map,
                                map_preset=args.map_preset, force=args.force, imu_priors=args.imu_priors,
                                progress=False if args.no_progress else None,
                                strict=bool(getattr(args, "strict", False)))
    except KeyboardInterrupt:
        print(f"interrupted: finished stages are kept in {args.out}/stages; run the same command again to resume")
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
              f"(indexes in report.json; --strict stops instead)")
    if res.report["extra"].get("groundtruth_error"):
        print(f"warning: ground truth not used: {res.report['extra']['groundtruth_error']}")
    print(f"wrote {args.out}/" + ", ".join(res.files))
    return 0
