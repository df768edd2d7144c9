"""Reprocessing at growing scan lengths: wall, CPU, peak memory and accuracy per length, memory per stage.

    .venv/bin/python benchmarks/bench_scale.py [--frames 200,400,800,2000,4000] [--cache DIR]
        [--trajectory arc] [--preset standard] [--no-map] [--keep] [--record-only] [--stereopath CMD]
        [--tag TAG] [--json-out FILE]

For each length N, a simulated session (``stereopath sim --frames N``) is recorded once into the cache
folder (default ``$TMPDIR/stereopath_scale``; reused by later runs, so record the long ones ahead) and
reprocessed from scratch as a user would (``stereopath host reprocess SESSION --out OUT --no-progress``,
one child process at a time).  Printed per length: wall seconds, CPU seconds of the child (user +
sys, every thread), its peak resident set, CPU per frame and the ATE after reprocessing (mm; the
session's ground truth); then per stage: seconds, CPU seconds (all threads) and CPU per frame, the stage's own peak resident set and the size of
each structure it noted (images, keypoints and descriptors, tracks, observations, the GTSAM graph,
the TSDF volume: ``OUT/stages/manifest.json``, written by :mod:`stereopath.host.reprocess.memory`).
Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("estimate", "tracks", "ba", "map")


COMMAND: list[str] = []  # --stereopath: another build of the command (e.g. a copy of an earlier commit)


def stereopath_cmd() -> list[str]:
    if COMMAND:
        return list(COMMAND)
    exe = Path(sys.executable).with_name("stereopath")
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "stereopath"]


def session(cache: Path, frames: int, trajectory: str) -> Path:
    """The cached session of ``frames`` frames (recorded now when missing; a cut recording is redone)."""
    out = cache / f"sim-{trajectory}-{frames}"
    if (cache / f"sim-{trajectory}-{frames}.part" / "manifest.json").is_file() and not out.exists():
        part = cache / f"sim-{trajectory}-{frames}.part"
        if json.loads((part / "manifest.json").read_text()).get("status") == "closed":
            part.rename(out)
    if (out / "manifest.json").is_file() and json.loads((out / "manifest.json").read_text()).get("status") == "closed":
        return out
    part = cache / f"sim-{trajectory}-{frames}.part"
    shutil.rmtree(part, ignore_errors=True)
    t0 = time.perf_counter()
    subprocess.run(stereopath_cmd() + ["sim", "--frames", str(frames), "--trajectory", trajectory, "--out", str(part)],
                   check=True, stdout=subprocess.DEVNULL)
    part.rename(out)
    print(f"recorded {out} ({time.perf_counter() - t0:.0f} s)", flush=True)
    return out


def run_child(cmd: list[str]) -> tuple[int, float, float, float]:
    """(exit status, wall s, CPU s of user + sys, peak resident set MB) of one child process."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    err = p.stderr.read() if p.stderr else ""
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode:
        print(err[-3000:], file=sys.stderr)
    return p.returncode, wall, ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 1024.0


def reprocess(sess: Path, out: Path, preset: str, do_map: bool) -> dict:
    cmd = stereopath_cmd() + ["host", "reprocess", str(sess), "--out", str(out), "--preset", preset, "--no-progress",
                              "--force"]
    if not do_map:
        cmd.append("--no-map")
    rc, wall, cpu, peak = run_child(cmd)
    row = {"status": rc, "wall_s": wall, "cpu_s": cpu, "peak_rss_mb": peak, "ate_mm": None, "keyframes": None,
           "stages": {}}
    report = out / "report.json"
    if report.is_file():
        extra = json.loads(report.read_text())["extra"]
        ba = extra["before_after"]["bundle_adjusted"] or {}
        row["ate_mm"] = None if ba.get("ate_rmse_m") is None else 1000 * ba["ate_rmse_m"]
        row["keyframes"] = (extra.get("tracks") or {}).get("keyframes")
    man = out / "stages" / "manifest.json"
    if man.is_file():
        stages = json.loads(man.read_text())["stages"]
        row["stages"] = {s: {"seconds": e.get("seconds"), "cpu_seconds": e.get("cpu_seconds"),
                             "cpu_steps": e.get("cpu_steps", {}), **e.get("memory", {})}
                         for s, e in stages.items()}
    return row


def print_row(frames: int, r: dict) -> None:
    ate = "n/a" if r["ate_mm"] is None else f"{r['ate_mm']:.3f}"
    kf = r.get("keyframes")
    per_kf = f"{kf} | {r['cpu_s'] / kf:.2f}" if kf else "n/a | n/a"
    print(f"| {frames} | {r['wall_s']:.0f} | {r['cpu_s']:.0f} | {r['peak_rss_mb'] / 1024:.2f} | "
          f"{r['cpu_s'] / frames:.3f} | {per_kf} | {ate} |{'' if r['status'] == 0 else ' FAILED'}", flush=True)
    for s in STAGES:
        st = r["stages"].get(s)
        if st is None:
            continue
        held = ", ".join(f"{k[:-3]} {v:.0f} MB" for k, v in st.items() if k.endswith("_mb") and k not in
                         ("peak_rss_mb", "rss_mb", "start_rss_mb"))
        steps = "".join(f"; {k} {v / frames:.3f}" for k, v in st.get("cpu_steps", {}).items())
        cpu = "" if st.get("cpu_seconds") is None else \
            f" ({st['cpu_seconds']:.0f} s CPU, {st['cpu_seconds'] / frames:.3f} s/frame{steps})"
        print(f"|   {s}: {st['seconds']:.0f} s{cpu}, start {st.get('start_rss_mb', float('nan')):.0f} MB, "
              f"peak {st.get('peak_rss_mb', float('nan')):.0f} MB, after {st.get('rss_mb', float('nan')):.0f} MB; "
              f"held: {held or '-'} |", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", default="200,400,800,2000", help="comma-separated lengths (default 200,400,800,2000)")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "stereopath_scale",
                    help="folder of the recorded sessions (reused)")
    ap.add_argument("--trajectory", default="arc")
    ap.add_argument("--preset", default="standard")
    ap.add_argument("--no-map", action="store_true", help="skip the dense model")
    ap.add_argument("--keep", action="store_true", help="keep the reprocessing outputs (in the cache folder)")
    ap.add_argument("--record-only", action="store_true", help="record the sessions and stop")
    ap.add_argument("--json-out", type=Path)
    ap.add_argument("--stereopath", help="the stereopath command to run (default: this environment's)")
    ap.add_argument("--tag", default="", help="suffix of the output folders (runs of two builds side by side)")
    args = ap.parse_args()
    if args.stereopath:
        COMMAND[:] = args.stereopath.split()
    lengths = [int(x) for x in args.frames.split(",") if x.strip()]
    args.cache.mkdir(parents=True, exist_ok=True)
    sessions = {n: session(args.cache, n, args.trajectory) for n in lengths}
    if args.record_only:
        return 0
    print(f"preset {args.preset}, {'no map' if args.no_map else 'with map'}, trajectory {args.trajectory}, "
          f"{os.cpu_count()} cores")
    print("| frames | wall s | CPU s | peak RSS GB | CPU s/frame | keyframes | CPU s/keyframe | ATE mm |")
    print("|---|---|---|---|---|---|---|---|")
    rows = {}
    for n in lengths:
        out = args.cache / f"out-{args.trajectory}-{n}{'-' + args.tag if args.tag else ''}"
        shutil.rmtree(out, ignore_errors=True)
        rows[n] = reprocess(sessions[n], out, args.preset, not args.no_map)
        print_row(n, rows[n])
        if not args.keep:
            shutil.rmtree(out, ignore_errors=True)
    if len(lengths) >= 2:
        a, b = lengths[-2], lengths[-1]
        ra, rb = rows[a], rows[b]
        # a short session spends more of its frames in the still start and the speed ramps (fewer keyframes
        # per frame): the per-keyframe ratio tells the work per unit of scan apart from that
        kfa, kfb = ra.get("keyframes"), rb.get("keyframes")
        per_kf = f", per keyframe x{(rb['cpu_s'] / kfb) / (ra['cpu_s'] / kfa):.2f}" if kfa and kfb else ""
        print(f"peak RSS growth {a} -> {b} frames: {100 * (rb['peak_rss_mb'] / ra['peak_rss_mb'] - 1):+.1f} %; "
              f"CPU per frame x{(rb['cpu_s'] / b) / (ra['cpu_s'] / a):.2f}{per_kf}; "
              f"keyframes per frame {kfa / a if kfa else float('nan'):.3f} -> {kfb / b if kfb else float('nan'):.3f}")
    if args.json_out:
        args.json_out.write_text(json.dumps({str(k): v for k, v in rows.items()}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
