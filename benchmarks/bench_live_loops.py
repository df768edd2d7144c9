"""The live map's pose graph (issue 13): iSAM2 as keyframes and loops arrive vs the batch solve at every loop.

    .venv/bin/python benchmarks/bench_live_loops.py [--keyframes N] [--turns T] [--loop-every K] [--runs R]

A long hand-held scan as `host live --map` sees it: N keyframes walking T turns around a table
(radius 1.5 m), each reported relative motion a little off (2 mrad and 2 mm of noise, as an
on-board estimate drifts), and from the second turn on a verified loop every K keyframes back to
the same place one turn earlier (its relative pose the true one).  Fed in arrival order to

* ``isam2``: :class:`stereopath.host.backend.pose_graph.LivePoseGraph` (what the live map uses):
  one iSAM2 update per keyframe, a loop settled by a few more;
* ``batch``: the whole graph re-solved by Levenberg-Marquardt
  (:func:`stereopath.host.backend.gtsam_ba.pose_graph`) at every loop (what it did before).

Per variant: CPU seconds of the whole feed (process time, all threads), the time from a loop's
arrival to its corrected poses (median, p95, max over the loops), the last loop's, and the final
poses' largest distance from the graph's optimum (Levenberg-Marquardt to machine precision).
Medians over R runs; the ratio isam2 / batch from the same run.  Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereopath.device.core.geometry import invert_pose, make_pose, so3_exp  # noqa: E402
from stereopath.host.backend.pose_graph import LivePoseGraph  # noqa: E402
from stereopath.host.backend import gtsam_ba  # noqa: E402
from stereopath.host.backend.loops import Loop  # noqa: E402


def scan(n: int, turns: int, every: int, seed: int = 0):
    """(true poses, on-board poses, loops by the keyframe that closes them)."""
    rng = np.random.default_rng(seed)
    a = 2 * np.pi * turns * np.arange(n) / n
    T_true = np.array([make_pose(so3_exp([0, -x, 0]), [1.5 * np.sin(x), 0.0, 1.5 * np.cos(x)]) for x in a])
    T_on = [T_true[0].copy()]
    for k in range(1, n):
        noise = make_pose(so3_exp(rng.normal(0, 2e-3, 3)), rng.normal(0, 2e-3, 3))
        T_on.append(T_on[-1] @ invert_pose(T_true[k - 1]) @ T_true[k] @ noise)
    per_turn = n // turns
    loops: dict[int, Loop] = {}
    for j in range(per_turn, n, every):
        i = j - per_turn
        loops[j] = Loop(i, j, invert_pose(T_true[i]) @ T_true[j], 100, 200, 1e-3, 2e-3, 0.0)
    return T_true, np.array(T_on), loops


def optimum(T_on: np.ndarray, loops: list) -> np.ndarray:
    """The graph's optimum: Levenberg-Marquardt to machine precision."""
    return gtsam_ba.pose_graph(T_on, loops, max_iterations=200, tol=1e-14)


def feed_isam2(T_on, loops):
    g, lat = LivePoseGraph(), []
    for k, T in enumerate(T_on):
        g.add(T)
        if k in loops:
            t = time.perf_counter()
            g.add_loop(loops[k])
            g.poses()
            lat.append(time.perf_counter() - t)
    return g.poses(), lat


def feed_batch(T_on, loops):
    seen, lat, P = [], [], np.array(T_on)
    for k in range(len(T_on)):
        if k in loops:
            t = time.perf_counter()
            seen.append(loops[k])
            P_now = gtsam_ba.pose_graph(T_on[: k + 1], seen)
            lat.append(time.perf_counter() - t)
            P = np.concatenate([P_now, P_now[-1] @ invert_pose(T_on[k]) @ T_on[k + 1:]])
    return P, lat


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keyframes", type=int, default=2000)
    ap.add_argument("--turns", type=int, default=3)
    ap.add_argument("--loop-every", type=int, default=10)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    T_true, T_on, loops = scan(args.keyframes, args.turns, args.loop_every)
    best = optimum(T_on, list(loops.values()))
    print(f"{args.keyframes} keyframes, {args.turns} turns, {len(loops)} loops (one every {args.loop_every} "
          f"keyframes from the second turn on); medians of {args.runs} runs")
    figures: dict[str, dict[str, list[float]]] = {}
    for _ in range(args.runs):
        for name, feed in (("isam2", feed_isam2), ("batch", feed_batch)):
            c = time.process_time()
            P, lat = feed(T_on, loops)
            f = figures.setdefault(name, {"cpu": [], "median": [], "p95": [], "max": [], "last": [], "off": []})
            f["cpu"].append(time.process_time() - c)
            f["median"].append(float(np.median(lat)))
            f["p95"].append(float(np.percentile(lat, 95)))
            f["max"].append(float(np.max(lat)))
            f["last"].append(lat[-1])
            f["off"].append(float(np.abs(P[:, :3, 3] - best[:, :3, 3]).max()))
    med = {n: {k: statistics.median(v) for k, v in f.items()} for n, f in figures.items()}
    err = lambda P: float(np.sqrt(np.mean(np.sum((P[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))
    print(f"  on-board path error (RMS) {1000 * err(T_on):.1f} mm, with every loop {1000 * err(best):.1f} mm")
    for name, m in med.items():
        print(f"  {name:5s}: CPU {m['cpu']:.2f} s for the whole scan; loop to corrected poses median "
              f"{1000 * m['median']:.1f} ms, p95 {1000 * m['p95']:.1f} ms, max {1000 * m['max']:.1f} ms, last "
              f"{1000 * m['last']:.1f} ms; largest distance from the optimum {1000 * m['off']:.3f} mm")
    i, b = med["isam2"], med["batch"]
    print(f"  isam2 / batch: CPU x{i['cpu'] / b['cpu']:.3f}, loop latency median x{i['median'] / b['median']:.3f}, "
          f"last loop x{i['last'] / b['last']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
