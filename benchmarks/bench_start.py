"""Position error of the ``stereo`` estimator at the start of a session against the rest.  Prints figures.

    .venv/bin/python benchmarks/bench_start.py [--cases sim_handheld,sim] [--runs 1] [--start-s 2]
        [--session DIR] [--keep DIR] [--json-out FILE]

Per case: the simulator writes the session (``stereopath sim --out``; ``sim_handheld`` with
``--trajectory handheld``: switched on in motion, auto-exposure changes and blur; ``sim``: the
default scan, which starts still), the command ``stereopath odometry session:DIR --out OUT`` estimates
it in a process of its own (BLAS at one thread, as on the device), and the trajectory is aligned to the
ground truth once (SE(3), the alignment of ``stereopath eval``).  It prints the position error's median,
p90 and maximum over the first ``--start-s`` seconds and over the rest (mm), those of the first seconds
aligned on themselves (the start's own shape, whatever drift came after it), the world frame the estimator
ended in and its on-board start (the gyro bias and gravity solved from the path), medians over ``--runs``.
``--session DIR`` estimates that session instead of simulating one (its case name is ``session``);
``--keep DIR`` keeps the simulated sessions there and reuses them on the next call; ``--json-out``
writes the figures as the other benchmarks do (``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SIM_TRAJECTORIES = {"sim_handheld": "handheld", "sim": None}
QUANTITIES = ("median", "p90", "max")


def simulate(case: str, out: Path) -> Path:
    """The case's simulated session in ``out`` (kept when it is already there)."""
    if (out / "groundtruth.tum").is_file():
        return out
    cmd = [str(Path(sys.executable).parent / "stereopath"), "sim", "--out", str(out)]
    if SIM_TRAJECTORIES[case]:
        cmd += ["--trajectory", SIM_TRAJECTORIES[case]]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return out


def estimate(session: Path, out: Path) -> dict:
    """``stereopath odometry`` on the session: its report."""
    cmd = [str(Path(sys.executable).parent / "stereopath"), "odometry", f"session:{session}", "--out", str(out)]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads((out / "report.json").read_text())


def start_and_rest(groundtruth: Path, trajectory: Path, start_s: float) -> dict[str, dict[str, float]]:
    """Position errors (m) after one SE(3) alignment: median, p90 and max of the first ``start_s``
    seconds and of the rest; and ``start_own``: those of the first seconds aligned on themselves (how
    well the start's own shape was measured, whatever drift came after it)."""
    import numpy as np

    from stereopath.device.formats.tum import Trajectory, read_tum
    from stereopath.host.evaluation.evaluate import associate_and_align

    a = associate_and_align(read_tum(groundtruth), read_tum(trajectory))
    err = np.linalg.norm(a.est_aligned.positions - a.gt.positions, axis=1)
    start = (a.gt.t_ns - a.gt.t_ns[0]) * 1e-9 < start_s
    out = {}
    for name, sel in (("start", start), ("rest", ~start)):
        e = err[sel]
        out[name] = {"median": float(np.median(e)), "p90": float(np.percentile(e, 90)), "max": float(np.max(e))}
    own = associate_and_align(Trajectory(a.gt.t_ns[start], a.gt.T_world_cam[start]),
                              Trajectory(a.est.t_ns[start], a.est.T_world_cam[start]))
    e = np.linalg.norm(own.est_aligned.positions - own.gt.positions, axis=1)
    out["start_own"] = {"median": float(np.median(e)), "p90": float(np.percentile(e, 90)), "max": float(np.max(e))}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="sim_handheld,sim")
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--start-s", type=float, default=2.0)
    ap.add_argument("--session", help="estimate this recorded session (with groundtruth.tum) instead")
    ap.add_argument("--keep", help="keep (and reuse) the simulated sessions in this folder")
    ap.add_argument("--json-out", help="also write the figures to this JSON file")
    args = ap.parse_args(argv)

    tmp = Path(tempfile.mkdtemp(prefix="bench_start_"))
    figures: dict[str, float | None] = {}
    try:
        cases = ["session"] if args.session else [c for c in args.cases.split(",") if c]
        for case in cases:
            if case != "session" and case not in SIM_TRAJECTORIES:
                raise SystemExit(f"unknown case {case!r}; cases: {', '.join(SIM_TRAJECTORIES)}")
            if case == "session":
                sess = Path(args.session)
            else:
                sess = simulate(case, (Path(args.keep) if args.keep else tmp) / case)
            rows = []
            for r in range(args.runs):
                rep = estimate(sess, tmp / f"out_{case}_{r}")
                rows.append((start_and_rest(sess / "groundtruth.tum", tmp / f"out_{case}_{r}" / "trajectory.tum",
                                            args.start_s), rep))
            world = rows[-1][1].get("world_frame")
            stats = rows[-1][1].get("extra", {}).get("estimator_stats", {})
            ates = ", ".join(f"{r[1]['ate_rmse_m'] * 1e3:.2f}" for r in rows)
            print(f"{case}: world frame {world}; on-board start solved at frame {stats.get('start_solved_frame', '-')}; "
                  f"ATE {statistics.median(r[1]['ate_rmse_m'] for r in rows) * 1e3:.2f} mm (runs {ates}), end error "
                  f"{statistics.median(r[1]['end_error_pct'] for r in rows):.3f} % of the path")
            print(f"{'':14s} {'median mm':>10s} {'p90 mm':>8s} {'max mm':>8s}")
            for part, label in (("start", f"first {args.start_s:g} s"), ("rest", "the rest"),
                                ("start_own", f"first {args.start_s:g} s *")):
                vals = [statistics.median(r[0][part][q] for r in rows) * 1e3 for q in QUANTITIES]
                print(f"{label:14s} {vals[0]:10.2f} {vals[1]:8.2f} {vals[2]:8.2f}")
                for q, v in zip(QUANTITIES, vals):
                    figures[f"start.{case}.{part}.{q}_mm"] = round(v, 3)
            print(f"* aligned on themselves (the start's own shape)")
            figures[f"start.{case}.gravity_aligned"] = float(world == "gravity_aligned")
        if args.json_out:
            from results_file import write_results

            write_results(args.json_out, "bench_start.py", figures)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
