"""TSDF fusion speed and simulated-scan mesh accuracy (issue 5 targets).  Prints figures; asserts nothing.

    .venv/bin/python benchmarks/bench_fusion.py [--frames N] [--runs R] [--estimated] [--skip-speed]

1. Speed: TSDF integration of 640x480 stereo depth maps (object preset, 4 mm voxels, with and
   without colour; room preset, 2 cm), keyframes/s, median over R runs; the ratio against the
   stereo depth computation of the same keyframes (measured in the same process).
   Target: >= 20 keyframes/s.
2. Accuracy on the default simulated scan (ground-truth poses; ``--estimated`` also runs the
   on-board ``stereo`` estimator and maps with its poses, SE(3)-aligned onto the ground truth
   as for the ATE), depth limited to 0.4-1.5 m:
   * accuracy: distance from every mesh vertex to the nearest true surface (the scene's
     rectangles, exact): median and 90th percentile.  Targets <= 3 mm and <= 10 mm.
   * completeness: the true surfaces sampled every 5 mm; a sample counts as truly visible
     when the rig saw it (left and right rectified cameras, ground-truth depth, unoccluded) from
     at least 3 keyframes at 0.4-1.5 m; the fraction of visible samples within 10 mm of the mesh
     (exact point-to-mesh distance).  Target >= 90 %.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereopath.device.sim.session import SimConfig, open_sim  # noqa: E402
from stereopath.device.sim.scene import point_to_scene_distance, sample_surface_points  # noqa: E402
from stereopath.host.mapping.depth import StereoDepth  # noqa: E402
from stereopath.host.mapping.fusion import TsdfVolume  # noqa: E402
from stereopath.host.mapping.inputs import keyframes_from_sequence  # noqa: E402
from stereopath.host.mapping.mapper import build_map, map_preset  # noqa: E402

RANGE_M = (0.4, 1.5)


def bench_config(frames_stride: int | None = None):
    cfg = map_preset("object")
    depth = dataclasses.replace(cfg.depth, min_depth_m=RANGE_M[0], max_depth_m=RANGE_M[1])
    fusion = dataclasses.replace(cfg.fusion, max_depth_m=RANGE_M[1])
    kf = cfg.keyframes if frames_stride is None else dataclasses.replace(cfg.keyframes, stride=frames_stride)
    return dataclasses.replace(cfg, depth=depth, fusion=fusion, keyframes=kf, preview_size=(480, 360))


def speed(sess, runs: int) -> None:
    print("== TSDF integration speed (640x480 depth maps from the simulated scan)")
    idx = list(range(0, len(sess), max(1, len(sess) // 40)))[:40]
    sd = StereoDepth(sess.rig, map_preset("object").depth)
    depth_ms = []
    maps = []
    for i in idx:
        fr = sess.frame(i)
        t0 = time.perf_counter()
        dm = sd.compute(fr.left, fr.right)
        depth_ms.append(1000 * (time.perf_counter() - t0))
        maps.append((dm, fr.meta["T_world_cam0"]))
    d_ms = statistics.median(depth_ms)
    print(f"  stereo depth (SGBM + LR check): median {d_ms:.1f} ms/keyframe ({1000 / d_ms:.1f} keyframes/s)")
    for label, preset, color in (("object 4 mm, colour", "object", True), ("object 4 mm, no colour", "object", False),
                                 ("room 2 cm, colour", "room", True)):
        fcfg = dataclasses.replace(map_preset(preset).fusion, color=color)
        rates = []
        for _ in range(runs):
            vol = TsdfVolume(fcfg)
            t0 = time.perf_counter()
            for dm, T in maps:
                vol.integrate_depth_map(dm, T)
            rates.append(len(maps) / (time.perf_counter() - t0))
        r = statistics.median(rates)
        print(f"  {label:24s}: {r:6.1f} keyframes/s (median of {runs}; target >= 20)  "
              f"= {r * d_ms / 1000:.1f}x the depth rate")


def visible_samples(sess, keyframes, rect, samples: np.ndarray, min_views: int = 3) -> np.ndarray:
    """Boolean per sample: seen by both rectified cameras, unoccluded, at 0.4-1.5 m, in >= min_views keyframes."""
    from scipy.spatial import cKDTree

    rig = sess.rig
    w, h = rig.cam0.size
    tree = cKDTree(samples)
    count = np.zeros(len(samples), np.int32)
    R4 = np.eye(4)
    R4[:3, :3] = rect.R0.T
    rend = sess.renderer
    K = rect.K
    B = rect.baseline_m
    for kf in keyframes:
        T_rect = kf.T_world_cam0 @ R4
        # the farthest point of the view frustum at z = 1.5 m (image corner rays of up to ~45 deg)
        idx = np.asarray(tree.query_ball_point(T_rect[:3, 3], 1.5 * RANGE_M[1] + B), dtype=np.int64)
        if len(idx) == 0:
            continue
        pts = samples[idx].astype(np.float32)
        seen = np.ones(len(idx), bool)
        for eye in (0, 1):
            T = T_rect.copy()
            T[:3, 3] += T_rect[:3, 0] * (B * eye)  # the right rectified camera sits B along its x axis
            _, zgt = rend.render_view(K, (w, h), T)
            Tcw = np.linalg.inv(T).astype(np.float32)
            pc = pts @ Tcw[:3, :3].T + Tcw[:3, 3]
            z = pc[:, 2]
            ok = seen & (z > RANGE_M[0]) & (z < RANGE_M[1])
            zs = np.where(ok, z, 1.0)
            u = np.rint(K[0, 0] * pc[:, 0] / zs + K[0, 2]).astype(np.int64)
            v = np.rint(K[1, 1] * pc[:, 1] / zs + K[1, 2]).astype(np.int64)
            ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
            zz = np.zeros(len(idx), np.float32)
            zz[ok] = zgt[v[ok], u[ok]]
            ok &= np.abs(zz - z) < np.maximum(0.01, 0.01 * z)
            seen = ok
        count[idx] += seen
    return count >= min_views


def accuracy(sess, traj, label: str, cfg) -> None:
    import open3d as o3d

    inp = keyframes_from_sequence(sess, traj, cfg.keyframes, source=f"sim ({label} poses)")
    t0 = time.perf_counter()
    res = build_map(inp, cfg, progress=False)
    t_map = time.perf_counter() - t0
    mesh = res.mesh
    v = np.asarray(mesh.vertices)
    scene = sess.scene
    d = point_to_scene_distance(scene, v)
    samples = sample_surface_points(scene, 0.005)
    rect = sess.rig.rectification()
    vis = visible_samples(sess, inp.keyframes, rect, samples)
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    dist = rs.compute_distance(o3d.core.Tensor(samples[vis].astype(np.float32))).numpy()
    comp = float(np.mean(dist <= 0.010)) if len(dist) else float("nan")
    print(f"== mesh accuracy, {label} poses: {len(inp.keyframes)} keyframes of {len(sess)} frames, "
          f"voxel {cfg.fusion.voxel_m * 1000:.0f} mm, depth {RANGE_M[0]}-{RANGE_M[1]} m, mapped in {t_map:.1f} s")
    print(f"  vertices {len(v)}: distance to the true surfaces median {1000 * np.median(d):.2f} mm "
          f"(target <= 3), p90 {1000 * np.percentile(d, 90):.2f} mm (target <= 10), "
          f"p99 {1000 * np.percentile(d, 99):.1f} mm")
    print(f"  completeness: {100 * comp:.1f} % of {int(vis.sum())} truly visible surface samples (5 mm grid, "
          f"{vis.sum() * 25e-6:.2f} m^2) within 10 mm of the mesh (target >= 90 %); "
          f"median distance {1000 * np.median(dist):.2f} mm")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=400, help="simulated frames (default: the full 400-frame scan)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--estimated", action="store_true", help="also map with the stereo estimator's poses")
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument("--min-translation-m", type=float, default=None, help="keyframe spacing (default: the preset's)")
    ap.add_argument("--min-rotation-deg", type=float, default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    sess = open_sim(SimConfig(frames=args.frames, seed=args.seed))
    if not args.skip_speed:
        speed(sess, args.runs)
    if not args.skip_accuracy:
        cfg = bench_config()
        kf_changes = {k: v for k, v in (("min_translation_m", args.min_translation_m),
                                        ("min_rotation_deg", args.min_rotation_deg)) if v is not None}
        if kf_changes:
            cfg = dataclasses.replace(cfg, keyframes=dataclasses.replace(cfg.keyframes, **kf_changes))
        accuracy(sess, sess.groundtruth, "ground-truth", cfg)
        if args.estimated:
            from stereopath.host.evaluation.odometry import estimate_sequence

            t0 = time.perf_counter()
            run = estimate_sequence(sess, "stereo", progress=False)
            from stereopath.host.evaluation.evaluate import associate_and_align, evaluate

            m = evaluate(sess.groundtruth, run.trajectory)
            aligned = associate_and_align(sess.groundtruth, run.trajectory).est_aligned
            print(f"  (stereo estimator over {len(sess)} frames: {time.perf_counter() - t0:.0f} s, "
                  f"ATE RMSE {1000 * m['ate_rmse_m']:.1f} mm; its path is SE(3)-aligned onto the ground truth)")
            accuracy(sess, aligned, "estimated (stereo, aligned)", cfg)
    return 0


if __name__ == "__main__":
    sys.exit(main())
