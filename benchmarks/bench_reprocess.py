"""Offline reprocessing (issues 5 and 13): ATE after reprocessing on the GTSAM back end, vision only and with the IMU.

    .venv/bin/python benchmarks/bench_reprocess.py [--runs R] [--preset NAME] [--skip-kitti] [--ablations]
        [--imu-from-first-frame] [--json-out FILE]

1. The default simulated session (`stereopath sim`: 400 frames, written once into a temporary
   folder, not timed): ATE of the on-board `stereo` estimator (run in this process), then
   `host reprocess` end to end (re-estimate, tracks, bundle adjustment, frame refinement, dense
   model, reports) once; then the `ba` stage alone (keyframe bundle adjustment and frame
   refinement, no map) in each variant ("gtsam": vision only, "gtsam+imu": with IMU
   preintegration factors, the default), R times each, alternating, on the same stored estimate
   and tracks: median ATE, median wall and CPU seconds (all threads) of the stage, the ratios to
   the first variant, and the IMU biases estimated against the simulator's truth.
   (The hand-written solver GTSAM replaced: its figures are in CHANGELOG.md.)
2. KITTI 06 frames 0-50 (no map): the vision-only variant (KITTI has no IMU).
   Then (both sequences) the tracks and ba stages with the earlier offline keyframes and keyframe-match
   check (the estimator's keyframes, no depth allowance) and today's (keyframes by
   viewpoint change, matches allowed their stereo depth's uncertainty), on the same re-estimate.
3. --loop N: a session on the `loop` trajectory (N frames): on-board ATE and end-to-start error
   (target >= 10 mm; --loop-seed picks the session's seed, --loop-seeds S adds the on-board figures
   of in-memory sessions with the other seeds up to S), then
   `host reprocess` (GTSAM with loop closure): the loops accepted, how many of them are false
   (their relative pose more than 20 mm or 1 deg off the ground truth's), ATE and end-to-start
   error after (targets: end-to-start <= 1 mm, ATE <= 0.5x on-board, 0 false loops).
4. --ablations: GTSAM without the disparity offset, without the frame refinement, and the
   `quick` preset (tracks without affine views), on both sequences.
5. --imu-from-first-frame: the simulated session recorded with its IMU cut at the first frame (no
   still block before it, as EuRoC's): the preintegration's gyro bias, gravity and velocities then come
   from the path (`device/estimation/inertial_init.py`).
Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import dataclasses
import logging
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereopath.host.evaluation.evaluate import evaluate  # noqa: E402
from stereopath.host.evaluation.odometry import estimate_sequence  # noqa: E402
from stereopath.host.reprocess.pipeline import REPROCESS_PRESETS, RunChoices, reprocess_sequence, reprocess_session  # noqa: E402
from stereopath.device.formats.source import open_source  # noqa: E402

DATA = Path(os.environ.get("STEREOPATH_DATA", ROOT.parent / "shared" / "data"))
KITTI = DATA / "kitti_odometry" / "sequences" / "06"


def mm(v: float | None) -> str:
    return "n/a" if v is None else f"{v * 1000:.3f} mm"


def onboard_ate(seq) -> tuple[float, float]:
    t = time.perf_counter()
    run = estimate_sequence(seq, "stereo", progress=False)
    return evaluate(seq.groundtruth, run.trajectory)["ate_rmse_m"], time.perf_counter() - t


def ba_stage(seq, stages: Path, preset):
    """The ba stage alone on the estimate and tracks stored in ``stages``: (ATE, wall s, CPU s, stats)."""
    import json

    from stereopath.device.formats.tum import Trajectory
    from stereopath.host.reprocess import stage_ba
    from stereopath.host.reprocess.config import StageInputs
    from stereopath.host.reprocess.store import load_npz

    results = {name: load_npz(stages / f"{name}.npz") for name in ("estimate", "tracks")}
    t, c = time.perf_counter(), time.process_time()  # process time: CPU of all threads
    out = stage_ba.run(preset, StageInputs(seq, False, results))
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    ate = evaluate(seq.groundtruth, Trajectory(results["estimate"]["t_ns"], out["T_frames"]))["ate_rmse_m"]
    return ate, wall, cpu, json.loads(str(out["stats"]))


VARIANTS = {"gtsam": False, "gtsam+imu": True}  # variant -> IMU factors


def compare_solvers(name: str, seq, stages: Path, base, runs: int, ate_on: float, unit: float,
                    unit_name: str, variants: tuple[str, ...] = ("gtsam",), bias_truth=None) -> None:
    """The ba stage in each variant on the same stored estimate and tracks, ``runs`` times each, alternating."""
    fig: dict[str, dict[str, list]] = {s: {"ate": [], "wall": [], "cpu": []} for s in variants}
    stats = {}
    for _ in range(runs):
        for v in variants:
            ate, wall, cpu, st = ba_stage(seq, stages, dataclasses.replace(base, ba=dataclasses.replace(base.ba, imu=VARIANTS[v])))
            fig[v]["ate"].append(ate)
            fig[v]["wall"].append(wall)
            fig[v]["cpu"].append(cpu)
            stats[v] = st
    med = {s: {k: statistics.median(v) for k, v in f.items()} for s, f in fig.items()}
    for s in variants:
        st = stats[s]
        print(f"  {name} {s:9s}: ATE {med[s]['ate'] * unit:.4f} {unit_name} (x{med[s]['ate'] / ate_on:.3f} of "
              f"on-board), ba stage {med[s]['wall']:.1f} s wall, {med[s]['cpu']:.1f} s CPU (bundle adjustment "
              f"{st['ba_seconds']:.1f} s, frame refinement {st['frame_refinement_seconds']:.1f} s); "
              f"{st['poses']} kf, {st['points']} points, {st['observations']} obs, rms "
              f"{st['rms_before_px']:.3f} -> {st['rms_after_px']:.3f} px, {st['iterations']} iterations, "
              f"disparity offset {st['disparity_offset_px']}")
    for s in variants[1:]:
        print(f"  {name} {s} / {variants[0]}: ATE x{med[s]['ate'] / med[variants[0]]['ate']:.3f}, ba stage CPU "
              f"x{med[s]['cpu'] / med[variants[0]]['cpu']:.2f}, wall x{med[s]['wall'] / med[variants[0]]['wall']:.2f} "
              f"(medians of {runs} run(s) each)")
    if "gtsam+imu" in stats and stats["gtsam+imu"].get("imu") and bias_truth is not None:
        print_bias_recovery(name, stats["gtsam+imu"]["imu"], *bias_truth)


# the earlier offline keyframes and match check (issue 13): the estimator's keyframes,
# a keyframe match verified against its stereo point's position only (no depth allowance)
def tracks_before(tracks):
    """The earlier offline keyframes and match check of a track config."""
    return dataclasses.replace(tracks, keyframe_parallax_deg=0.0,
                               match=dataclasses.replace(tracks.match, verify_depth_sigmas=0.0))


def compare_tracks(name: str, seq, tmp: Path, base, ate_on: float, unit: float, unit_name: str, runs: int) -> None:
    """The tracks and ba stages with the earlier offline keyframes and match check, then today's, on
    the same stored re-estimate (``tmp/name``), ``runs`` times each, alternating: ATE, keyframes, CPU."""
    import json
    import shutil

    variants = {"before": dataclasses.replace(base, tracks=tracks_before(base.tracks)),
                "after": base}
    fig = {v: {"ate": [], "cpu": []} for v in variants}
    stats = {}
    for r in range(runs):
        for v, preset in variants.items():
            out = tmp / f"{name}_tracks_{v}"
            shutil.rmtree(out, ignore_errors=True)
            (out / "stages").mkdir(parents=True)
            for f in ("estimate.npz", "manifest.json"):
                shutil.copy(tmp / name / "stages" / f, out / "stages" / f)
            c = time.process_time()
            res = reprocess_sequence(seq, out, preset=preset, run=RunChoices(do_map=False, progress=False))
            fig[v]["cpu"].append(time.process_time() - c)
            fig[v]["ate"].append(res.report["ate_rmse_m"])
            ba = json.loads(str(np.load(out / "stages" / "ba.npz")["stats"]))
            trk = json.loads(str(np.load(out / "stages" / "tracks.npz")["stats"]))
            stats[v] = (trk, ba)
    med = {v: {k: statistics.median(x) for k, x in f.items()} for v, f in fig.items()}
    for v in variants:
        trk, ba = stats[v]
        print(f"  {name} tracks {v:6s}: ATE {med[v]['ate'] * unit:.4f} {unit_name} (x{med[v]['ate'] / ate_on:.3f} of "
              f"on-board), tracks + ba stages {med[v]['cpu']:.1f} s CPU; {trk['keyframes']} kf, {trk['matches']} matches, "
              f"{trk['tracks']} tracks (mean length {trk['mean_track_length']:.2f} kf), rms {ba['rms_before_px']:.3f} -> "
              f"{ba['rms_after_px']:.3f} px, disparity offset {ba['disparity_offset_px']}")
    print(f"  {name} tracks after / before: ATE x{med['after']['ate'] / med['before']['ate']:.3f}, CPU "
          f"x{med['after']['cpu'] / med['before']['cpu']:.2f} (medians of {runs} run(s))")


def print_bias_recovery(name: str, imu: dict, t_ns, accel_true, gyro_true) -> None:
    """The estimated keyframe biases against the simulator's (interpolated at the keyframes)."""
    import numpy as np

    b = imu["biases"]
    t = np.asarray(b["t_ns"], float)
    for label, est, true in (("accel", b["accel_m_s2"], accel_true), ("gyro", b["gyro_rad_s"], gyro_true)):
        est = np.asarray(est)
        tr = np.column_stack([np.interp(t, t_ns, true[:, a]) for a in range(3)])
        per_kf = np.linalg.norm(est - tr, axis=1) / np.linalg.norm(tr, axis=1)
        mean_err = np.linalg.norm(est.mean(0) - tr.mean(0)) / np.linalg.norm(tr.mean(0))
        print(f"  {name} {label} bias: estimated mean {np.round(est.mean(0), 5).tolist()}, true "
              f"{np.round(tr.mean(0), 5).tolist()}: error {mean_err * 100:.1f} % of the true (mean over keyframes); "
              f"per keyframe median {np.median(per_kf) * 100:.1f} %, max {per_kf.max() * 100:.1f} % (target <= 10 %)")


def false_loops(seq, stages: Path) -> tuple[int, float, float]:
    """Accepted loops whose relative pose is > 20 mm or 1 deg off the truth; the largest errors (mm, deg)."""
    import numpy as np

    from stereopath.device.core.geometry import invert_pose, rotation_angle_deg
    from stereopath.host.backend.loops import loops_from_array

    trk, est = np.load(stages / "tracks.npz"), np.load(stages / "estimate.npz")
    gt = seq.groundtruth
    t_gt = np.asarray(gt.t_ns)
    G = np.array([gt.T_world_cam[np.argmin(np.abs(t_gt - t))] for t in est["t_ns"][trk["kf_index"]]])
    errs = [(1000 * np.linalg.norm(rel[:3, 3] - lp.T_ci_cj[:3, 3]), rotation_angle_deg(rel[:3, :3].T @ lp.T_ci_cj[:3, :3]))
            for lp in loops_from_array(trk["loops"]) for rel in [invert_pose(G[lp.i]) @ G[lp.j]]]
    if not errs:
        return 0, 0.0, 0.0
    e = np.array(errs)
    return int(np.sum((e[:, 0] > 20.0) | (e[:, 1] > 1.0))), float(e[:, 0].max()), float(e[:, 1].max())


def loop_gaps(frames: int, seeds: int, skip: int) -> None:
    """On-board end-to-start error of in-memory `loop` sessions with seeds 0..seeds but ``skip``."""
    from stereopath.device.sim.session import SimConfig, open_sim
    from stereopath.host.reprocess.outputs import end_to_start_error

    for seed in (s for s in range(seeds + 1) if seeds > 0 and s != skip):
        seq = open_sim(SimConfig(trajectory="loop", frames=frames, seed=seed))
        run = estimate_sequence(seq, "stereo", progress=False)
        print(f"loop seed {seed}: on-board ATE {mm(evaluate(seq.groundtruth, run.trajectory)['ate_rmse_m'])}, "
              f"end-to-start error {mm(end_to_start_error(seq.groundtruth, run.trajectory))} (target: >= 10 mm)")


def loop_figures(tmp: Path, frames: int, base, seed: int = 0) -> None:
    """Record a loop session, reprocess it with loop closure, print the loop figures."""
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim
    from stereopath.host.reprocess.outputs import end_to_start_error

    suffix = f"_seed{seed}" if seed else ""
    session, out = tmp / f"loop_session{suffix}", tmp / f"loop_out{suffix}"
    if not (session / "mav0").is_dir():
        record_sequence(open_sim(SimConfig(trajectory="loop", frames=frames, seed=seed)), session,
                        config_dict={"source": "sim"})
    seq = open_source(f"session:{session}")
    run = estimate_sequence(seq, "stereo", progress=False)
    ate_on = evaluate(seq.groundtruth, run.trajectory)["ate_rmse_m"]
    gap_on = end_to_start_error(seq.groundtruth, run.trajectory)
    print(f"loop session (seed {seed}): {len(seq)} frames, {seq.groundtruth.path_length_m():.2f} m; on-board ATE {mm(ate_on)}, "
          f"end-to-start error {mm(gap_on)} (target: >= 10 mm)")
    t = time.perf_counter()
    res = reprocess_sequence(seq, out, preset=base, run=RunChoices(do_map=False, progress=False), onboard=run.trajectory)
    lp = res.report["extra"]["loops"]
    after = res.report["ate_rmse_m"]
    err = lp["end_to_start_error_m"]
    pairs = ", ".join(f"{a['kf_i']}-{a['kf_j']}/{a['inliers']}" for a in lp["accepted"][:12])
    more = " ..." if len(lp["accepted"]) > 12 else ""
    print(f"  reprocess (GTSAM, loop closure) {time.perf_counter() - t:.1f} s: {len(lp['accepted'])} loops accepted "
          f"(keyframe pairs / inliers: {pairs}{more})")
    n_false, e_mm, e_deg = false_loops(seq, out / "stages")
    print(f"  false loops: {n_false} (target 0); largest disagreement of a loop with the truth {e_mm:.2f} mm, "
          f"{e_deg:.3f} deg")
    print(f"  ATE after {mm(after)} = x{after / ate_on:.3f} of on-board (target <= 0.5); end-to-start error: "
          f"re-estimated {mm(err['reestimated'])}, after {mm(err['bundle_adjusted'])} (target <= 1 mm)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="ba-stage runs per back end (median)")
    ap.add_argument("--preset", default="standard", choices=list(REPROCESS_PRESETS))
    ap.add_argument("--tracks-runs", type=int, default=1,
                    help="runs of the tracks + ba stages per offline keyframe / match setting (median)")
    ap.add_argument("--skip-kitti", action="store_true")
    ap.add_argument("--skip-sim", action="store_true")
    ap.add_argument("--ablations", action="store_true")
    ap.add_argument("--loop", type=int, default=0, metavar="FRAMES", help="also the loop trajectory with this many frames")
    ap.add_argument("--only-loop", action="store_true", help="only the loop figures")
    ap.add_argument("--loop-seed", type=int, default=0, help="with --loop: the seed of the reprocessed session")
    ap.add_argument("--loop-seeds", type=int, default=0, metavar="S",
                    help="with --loop: also the on-board end-to-start error of seeds 0..S (but --loop-seed)")
    ap.add_argument("--reuse", action="store_true",
                    help="with --keep: compare the solvers on stages already stored there (no end-to-end run)")
    ap.add_argument("--keep", default=None, help="write into this folder instead of a temporary one")
    ap.add_argument("--imu-from-first-frame", action="store_true",
                    help="the simulated session recorded with its IMU cut at the first frame (no still start)")
    ap.add_argument("--json-out", metavar="FILE",
                    help="also write the simulated session's figures (on-board and reprocessed ATE, end-to-end "
                         "time) as JSON (benchmarks/write_table.py)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    figures: dict = {}
    base = REPROCESS_PRESETS[args.preset]

    with tempfile.TemporaryDirectory(prefix="bench_reprocess_") as tmp_name:
        tmp = Path(args.keep) if args.keep else Path(tmp_name)
        tmp.mkdir(parents=True, exist_ok=True)
        if args.loop:
            loop_figures(tmp, args.loop, base, args.loop_seed)
            loop_gaps(args.loop, args.loop_seeds, args.loop_seed)
        if args.only_loop:
            return 0
        sequences = []
        if not args.skip_sim:
            sequences.append(sim_figures(tmp, args, base, figures))
        if not args.skip_kitti:
            if KITTI.is_dir():
                kseq = open_source(f"kitti:{KITTI}")
                k_on, _ = onboard_ate(kseq)
                print(f"KITTI 06 frames 0-{len(kseq) - 1}: on-board stereo ATE {k_on:.4f} m")
                if not (args.reuse and (tmp / "kitti" / "stages" / "tracks.npz").is_file()):
                    reprocess_sequence(kseq, tmp / "kitti", preset=base, run=RunChoices(do_map=False, progress=False, force=True))
                compare_solvers("kitti", kseq, tmp / "kitti" / "stages", base, args.runs, k_on, 1, "m")
                compare_tracks("kitti", kseq, tmp, base, k_on, 1, "m", args.tracks_runs)
                sequences.append(("kitti", kseq, k_on))
            else:
                print(f"KITTI data not found at {KITTI}: skipped")
        if args.ablations:
            ablations(tmp, base, sequences)
    if args.json_out:
        from results_file import write_results

        write_results(args.json_out, "bench_reprocess.py", figures)
    return 0


class ImuFromFirstFrame:
    """A sequence whose IMU starts with its first frame (EuRoC's layout, or a box switched on in the hand)."""

    def __init__(self, seq) -> None:
        from stereopath.device.core.frames import ImuSamples

        self._seq = seq
        m = seq.imu.t_ns >= seq.t_ns[0]
        self.imu = ImuSamples(seq.imu.t_ns[m], seq.imu.gyro_rad_s[m], seq.imu.accel_m_s2[m])

    def __len__(self) -> int:
        return len(self._seq)

    def __getattr__(self, name: str):
        return getattr(self._seq, name)


def up_error(path: Path, gt) -> str:
    """How far the reprocessed path's vertical is from the ground truth's at each frame (z up in both)."""
    import numpy as np

    from stereopath.device.formats.tum import read_tum

    est = read_tum(path)
    idx = np.searchsorted(gt.t_ns, est.t_ns).clip(0, len(gt) - 1)
    ok = gt.t_ns[idx] == est.t_ns
    up = np.array([0.0, 0.0, 1.0])
    a = np.degrees(np.arccos(np.clip(np.sum((est.T_world_cam[ok, :3, :3].transpose(0, 2, 1) @ up)
                                             * (gt.T_world_cam[idx[ok], :3, :3].transpose(0, 2, 1) @ up), 1), -1, 1)))
    return f"its up against the ground truth's over {int(ok.sum())} frames: median {np.median(a):.3f}, max {a.max():.3f} deg"


def sim_figures(tmp: Path, args, base, figures: dict):
    """The default simulated session: on-board ATE, end-to-end reprocessing, the solver comparison.
    The first two go into ``figures`` too (for --json-out)."""
    from stereopath.device.sim.session import SimConfig, open_sim

    cut = args.imu_from_first_frame
    session = tmp / ("session_imu_from_first_frame" if cut else "session")
    if not (session / "mav0").is_dir():
        from stereopath.device.formats.recorder import record_sequence

        sim = open_sim(SimConfig())
        record_sequence(ImuFromFirstFrame(sim) if cut else sim, session, config_dict={"source": "sim"})
    seq = open_source(f"session:{session}")
    print(f"simulated session: {len(seq)} frames, {seq.groundtruth.path_length_m():.2f} m"
          + (", its IMU from the first frame on (no still block before it)" if cut else ""))
    ate_on, t_on = onboard_ate(seq)
    print(f"  on-board stereo ATE {mm(ate_on)} ({t_on:.1f} s)")
    key = "reprocess.sim_imu_from_first_frame" if cut else "reprocess.sim"
    figures[f"{key}.ate_onboard_m"] = ate_on
    if not (args.reuse and (tmp / "sim" / "stages" / "tracks.npz").is_file()):
        t = time.perf_counter()
        res = reprocess_session(session, tmp / "sim", preset=base, run=RunChoices(progress=False, force=True))
        st = res.seconds
        wall = time.perf_counter() - t
        if args.preset == "standard":
            figures.update({f"{key}.ate_after_m": res.report["ate_rmse_m"], f"{key}.end_to_end_s": wall,
                            f"{key}.ate_ratio": res.report["ate_rmse_m"] / ate_on})
        print(f"  reprocess --preset {args.preset} end to end (GTSAM): {wall:.1f} s (estimate "
              f"{st['estimate']:.1f}, tracks {st['tracks']:.1f}, ba {st['ba']:.1f}, map {st['map']:.1f} s), "
              f"ATE {mm(res.report['ate_rmse_m'])}; target <= 180 s")
        print(f"  world frame {res.report['world_frame']}; {up_error(tmp / 'sim' / 'trajectory.tum', seq.groundtruth)}")
    sim = open_sim(SimConfig())
    truth = (sim.imu.t_ns, sim.imu_biases.accel_m_s2, sim.imu_biases.gyro_rad_s)
    compare_solvers("sim", seq, tmp / "sim" / "stages", base, args.runs, ate_on, 1000, "mm",
                    ("gtsam", "gtsam+imu"), truth)
    compare_tracks("sim", seq, tmp, base, ate_on, 1000, "mm", args.tracks_runs)
    return ("sim", seq, ate_on)


def ablations(tmp: Path, base, sequences) -> None:
    variants = {
        "no disparity offset": dataclasses.replace(base, ba=dataclasses.replace(base.ba, disparity_offset=False)),
        "no frame refinement": dataclasses.replace(base, refine_frames=False),
        "quick preset (no affine views)": REPROCESS_PRESETS["quick"],
    }
    for name, s, ref in sequences:
        for vname, preset in variants.items():
            r = reprocess_sequence(s, tmp / f"abl_{name}", preset=preset, run=RunChoices(do_map=False, progress=False))
            a = r.report["ate_rmse_m"]
            print(f"  ablation {name:5s} {vname:32s}: ATE {a * 1000:.3f} mm, ratio {a / ref:.3f}")


if __name__ == "__main__":
    sys.exit(main())
