"""Stereo depth accuracy and speed (issue 5 targets).  Prints figures; asserts nothing.

    .venv/bin/python benchmarks/bench_depth.py [--runs R] [--frames N] [--middlebury DIR] [--skip-sim]

1. Every Middlebury scene in ``--middlebury DIR`` (default ../shared/data/middlebury: ``cones``
   and ``teddy``; the 2001/2003 layout with ``datasets.xml`` scale factors and the 2014 layout
   with PFM ground truth, :mod:`stereopath.host.evaluation.middlebury`).  The pairs are already
   rectified, so SGBM runs on them directly (grey images, the scene's disparity range rounded up
   to 16, the same left-right check and speckle filter as for keyframes).  Per scene: the bad-pixel rate (|d - gt| > 2 px) over all known pixels of the left
   image, holes filled from the background side (Middlebury's convention for sparse methods;
   target <= 15 %), plus the rate over the pixels we do match, the rate counting holes as bad,
   and the density.
2. The simulated scan: per-keyframe depth against the simulator's ground-truth depth
   (``depth0``, camera-0 frame, re-projected into the rectified camera): median relative error,
   90th percentile, valid fraction, at 0.4-1.5 m.
3. Speed at 640x480 (object and room presets): median ms per keyframe over R runs, and the ratio
   against one SGBM pass without the left-right check (reference, same process).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereopath.device.errors import StereopathError  # noqa: E402
from stereopath.host.evaluation.middlebury import Scene, find_scenes, read_scene  # noqa: E402
from stereopath.host.mapping.depth import (  # noqa: E402
    DEPTH_PRESETS, DepthConfig, StereoDepth, compute_disparity, fill_holes_background, make_matcher,
)

DATA = ROOT.parent / "shared" / "data"
MIDDLEBURY_CONFIG = DepthConfig(max_disparity_px=63, block_size=3, edge_max_rel_step=0.0)


def middlebury_scene(scene: Scene, config: DepthConfig = MIDDLEBURY_CONFIG) -> dict[str, float]:
    """Bad-pixel figures of one Middlebury scene (see the module doc)."""
    nd = scene.num_disparities
    config = dataclasses.replace(config, max_disparity_px=nd - 1)
    disp = compute_disparity(scene.left, scene.right, config, nd)
    gt = scene.gt
    known = np.isfinite(gt)
    matched = np.isfinite(disp)
    err = np.abs(np.where(matched, disp, 0.0) - np.where(known, gt, 0.0))
    filled = fill_holes_background(disp)
    return {
        "bad_filled": float(np.mean(np.abs(filled - gt)[known] > 2.0)),
        "bad_matched": float(np.mean(err[known & matched] > 2.0)),
        "bad_holes_as_bad": float(np.mean(((err > 2.0) | ~matched)[known])),
        "density": float(np.mean(matched[known])),
    }


def middlebury(root: Path) -> None:
    print(f"== Middlebury scenes in {root} (bad pixels: |d - gt| > 2 px over known pixels of the left image)")
    dirs = find_scenes(root)
    if not dirs:
        print(f"  no scenes found in {root}")
    for d in dirs:
        try:
            scene = read_scene(d)
        except StereopathError as exc:
            print(f"  {d.name}: skipped: {exc}")
            continue
        t0 = time.perf_counter()
        r = middlebury_scene(scene)
        ms = 1e3 * (time.perf_counter() - t0)
        print(f"  {scene.name:10s} {scene.left.shape[1]}x{scene.left.shape[0]}, {scene.num_disparities} disparities: "
              f"bad {100 * r['bad_filled']:5.2f} % (holes background-filled; target <= 15 %) | "
              f"matched pixels only {100 * r['bad_matched']:5.2f} % at density {100 * r['density']:.1f} % | "
              f"holes counted as bad {100 * r['bad_holes_as_bad']:5.2f} % | {ms:.0f} ms")


def gt_depth_in_rect(depth0: np.ndarray, K0: np.ndarray, rect) -> np.ndarray:
    """Forward-project the camera-0 ground-truth depth into the rectified left camera (z-buffered)."""
    h, w = depth0.shape
    v, u = np.nonzero(depth0 > 0)
    z = depth0[v, u].astype(float)
    P = np.stack([(u - K0[0, 2]) * z / K0[0, 0], (v - K0[1, 2]) * z / K0[1, 1], z], axis=1)
    Pr = P @ np.asarray(rect.R0).T
    Kr = rect.K
    ur = np.rint(Kr[0, 0] * Pr[:, 0] / Pr[:, 2] + Kr[0, 2]).astype(int)
    vr = np.rint(Kr[1, 1] * Pr[:, 1] / Pr[:, 2] + Kr[1, 2]).astype(int)
    ok = (ur >= 0) & (ur < w) & (vr >= 0) & (vr < h) & (Pr[:, 2] > 0)
    out = np.full((h, w), np.inf, np.float32)
    np.minimum.at(out, (vr[ok], ur[ok]), Pr[ok, 2].astype(np.float32))
    out[~np.isfinite(out)] = 0.0
    return out


def sim_accuracy(frames: int) -> None:
    from stereopath.device.sim.session import SimConfig, open_sim

    sess = open_sim(SimConfig(frames=400, with_depth=True))
    cfg = dataclasses.replace(DEPTH_PRESETS["object"], min_depth_m=0.4, max_depth_m=1.5)
    sd = StereoDepth(sess.rig, cfg)
    rect = sd.rect
    rel_all, valid = [], []
    for i in np.linspace(0, len(sess) - 1, frames).astype(int):
        fr = sess.frame(int(i))
        dm = sd.compute(fr.left, fr.right)
        gt = gt_depth_in_rect(fr.meta["depth0"], sess.rig.cam0.K, rect)
        # drop pixels next to a ground-truth depth edge (the forward projection is nearest-pixel)
        lo = cv2.erode(np.where(gt > 0, gt, 1e9).astype(np.float32), np.ones((3, 3), np.uint8))
        hi = cv2.dilate(gt, np.ones((3, 3), np.uint8))
        smooth = (gt > 0) & ((hi - lo) < 0.02 * gt)
        m = dm.valid & smooth
        rel_all.append(np.abs(dm.depth_m[m] - gt[m]) / gt[m])
        in_range = smooth & (gt >= 0.4) & (gt <= 1.5)
        valid.append(np.count_nonzero(dm.valid & in_range) / max(1, np.count_nonzero(in_range)))
    rel = np.concatenate(rel_all)
    print(f"== simulated scan, {frames} frames, object preset at 0.4-1.5 m, against ground-truth depth0")
    print(f"  relative depth error: median {100 * np.median(rel):.2f} % (test bound < 1 %), "
          f"p90 {100 * np.percentile(rel, 90):.2f} %, p99 {100 * np.percentile(rel, 99):.1f} %; "
          f"valid {100 * np.mean(valid):.1f} % of ground-truth pixels in range")


def speed(runs: int) -> None:
    from stereopath.device.sim.session import SimConfig, open_sim

    sess = open_sim(SimConfig(frames=400))
    pairs = [sess.frame(i) for i in (50, 150, 250, 350)]
    print("== speed at 640x480 (median over runs of 4 keyframes)")
    for name in ("object", "room"):
        sd = StereoDepth(sess.rig, DEPTH_PRESETS[name])
        rect = sd.rect
        rects = [rect.rectify(f.left, f.right) for f in pairs]
        ref = make_matcher(DEPTH_PRESETS[name], sd.num_disparities)
        t_full, t_ref = [], []
        for _ in range(runs):
            t0 = time.perf_counter()
            for f in pairs:
                sd.compute(f.left, f.right)
            t_full.append((time.perf_counter() - t0) / len(pairs))
            t0 = time.perf_counter()
            for lr, rr in rects:
                ref.compute(lr, rr)
            t_ref.append((time.perf_counter() - t0) / len(pairs))
        a, b = statistics.median(t_full), statistics.median(t_ref)
        print(f"  {name:6s} ({sd.num_disparities} disparities, block {DEPTH_PRESETS[name].block_size}): "
              f"{1000 * a:6.1f} ms/keyframe ({1 / a:.1f} keyframes/s) = {a / b:.2f}x one plain SGBM pass "
              f"({1000 * b:.1f} ms)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=12, help="simulated frames for the depth-error figure")
    ap.add_argument("--skip-sim", action="store_true")
    ap.add_argument("--middlebury", default=str(DATA / "middlebury"), help="folder of Middlebury scenes")
    args = ap.parse_args()
    middlebury(Path(args.middlebury))
    if not args.skip_sim:
        sim_accuracy(args.frames)
        speed(args.runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
