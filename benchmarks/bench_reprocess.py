"""Offline reprocessing (issue 5 targets): ATE before/after bundle adjustment, end-to-end time.

    .venv/bin/python benchmarks/bench_reprocess.py [--runs R] [--preset NAME] [--skip-kitti] [--ablations]

1. The default simulated session (`stereopath sim`: 400 frames, written once into a temporary
   folder, not timed): ATE of the on-board `stereo` estimator (run in this process on the same
   session), then `host reprocess` end to end (re-estimate, tracks, bundle adjustment, frame
   refinement, dense model, reports) into a fresh folder, R times: median wall time, ATE after,
   ratio after / on-board (target <= 0.8; time target <= 180 s).
2. KITTI 06 frames 0-50 (no map): on-board ATE, ATE after reprocessing, ratio.
3. --ablations: the same bundle adjustment without the disparity offset, without the frame
   refinement, and the `quick` preset (tracks without affine views), on both sequences.
Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereopath.host.evaluation.evaluate import evaluate  # noqa: E402
from stereopath.host.evaluation.odometry import estimate_sequence  # noqa: E402
from stereopath.host.reprocess.pipeline import REPROCESS_PRESETS, reprocess_sequence, reprocess_session  # noqa: E402
from stereopath.device.formats.source import open_source  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
KITTI = DATA / "kitti_odometry" / "sequences" / "06"


def mm(v: float | None) -> str:
    return "n/a" if v is None else f"{v * 1000:.3f} mm"


def onboard_ate(seq) -> tuple[float, float]:
    t = time.perf_counter()
    run = estimate_sequence(seq, "stereo", progress=False)
    return evaluate(seq.groundtruth, run.trajectory)["ate_rmse_m"], time.perf_counter() - t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1, help="end-to-end runs on the simulated session (median)")
    ap.add_argument("--preset", default="standard", choices=list(REPROCESS_PRESETS))
    ap.add_argument("--skip-kitti", action="store_true")
    ap.add_argument("--ablations", action="store_true")
    ap.add_argument("--keep", default=None, help="write into this folder instead of a temporary one")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    with tempfile.TemporaryDirectory(prefix="bench_reprocess_") as tmp_name:
        tmp = Path(args.keep) if args.keep else Path(tmp_name)
        tmp.mkdir(parents=True, exist_ok=True)
        session = tmp / "session"
        if not (session / "mav0").is_dir():
            from stereopath.device.formats.recorder import record_sequence
            from stereopath.device.sim.session import SimConfig, open_sim

            record_sequence(open_sim(SimConfig()), session, config_dict={"source": "sim"})
        seq = open_source(f"session:{session}")
        print(f"simulated session: {len(seq)} frames, {seq.groundtruth.path_length_m():.2f} m")
        ate_on, t_on = onboard_ate(seq)
        ate_sim0, _ = onboard_ate(open_source("sim:0"))
        print(f"  on-board stereo ATE {mm(ate_on)} on the session ({t_on:.1f} s), {mm(ate_sim0)} on sim:0 directly")
        times, ates = [], []
        res = None
        for r in range(args.runs):
            out = tmp / f"out{r}"
            t = time.perf_counter()
            res = reprocess_session(session, out, preset=args.preset, progress=False, force=True)
            times.append(time.perf_counter() - t)
            ates.append(res.report["ate_rmse_m"])
        st = res.seconds
        ba = res.report["extra"]["bundle_adjustment"]
        print(f"  reprocess --preset {args.preset} end to end: median {statistics.median(times):.1f} s over "
              f"{args.runs} run(s) (estimate {st['estimate']:.1f}, tracks {st['tracks']:.1f}, ba {st['ba']:.1f}, "
              f"map {st['map']:.1f} s); target <= 180 s")
        print(f"  ATE after bundle adjustment {mm(statistics.median(ates))} -> ratio "
              f"{statistics.median(ates) / ate_on:.3f} of on-board (target <= 0.8); "
              f"{ba['poses']} keyframes, {ba['points']} points, {ba['observations']} observations, "
              f"rms {ba['rms_before_px']:.3f} -> {ba['rms_after_px']:.3f} px, disparity offset "
              f"{ba['disparity_offset_px'] if ba['disparity_offset_px'] is not None else 'off'}")
        sequences = [("sim", seq, ate_on, True)]
        if not args.skip_kitti:
            if KITTI.is_dir():
                kseq = open_source(f"kitti:{KITTI}")
                k_on, _ = onboard_ate(kseq)
                t = time.perf_counter()
                kres = reprocess_sequence(kseq, tmp / "kitti", preset=args.preset, do_map=False, progress=False,
                                          force=True)
                k_after = kres.report["ate_rmse_m"]
                kb = kres.report["extra"]["bundle_adjustment"]
                print(f"KITTI 06 frames 0-{len(kseq) - 1}: on-board stereo ATE {k_on:.4f} m, after reprocessing "
                      f"{k_after:.4f} m -> ratio {k_after / k_on:.3f} (target <= 0.8); "
                      f"{time.perf_counter() - t:.1f} s, disparity offset {kb['disparity_offset_px']}")
                sequences.append(("kitti", kseq, k_on, False))
            else:
                print(f"KITTI data not found at {KITTI}: skipped")
        if args.ablations:
            base = REPROCESS_PRESETS[args.preset]
            variants = {
                "no disparity offset": dataclasses.replace(base, ba_disparity_offset=False),
                "no frame refinement": dataclasses.replace(base, refine_frames=False),
                "quick preset (no affine views)": REPROCESS_PRESETS["quick"],
            }
            for name, s, ref, _ in sequences:
                for vname, preset in variants.items():
                    out = tmp / f"abl_{name}"
                    r = reprocess_sequence(s, out, preset=preset, do_map=False, progress=False)
                    a = r.report["ate_rmse_m"]
                    print(f"  ablation {name:5s} {vname:32s}: ATE {a * 1000:.3f} mm, ratio {a / ref:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
