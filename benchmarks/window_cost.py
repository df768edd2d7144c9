"""The local window's solve: NumPy (what the device runs) against GTSAM on the same synthetic windows.

    .venv/bin/python benchmarks/window_cost.py [--keyframes 6] [--points 400] [--fixed 3] [--repeat 10]

A sideways sweep that turns, points 1.5-4 m away, 0.3 px noise on the rectified (u, v, disparity)
observations, the free poses perturbed by 1 cm and 0.6 degrees.  Both solve the same problem: the
held keyframes fixed, the others and the points free, Huber at 1 px.  GTSAM: one
``GenericStereoFactor3D`` per observation, Levenberg-Marquardt from the same start.  Prints each
one's CPU milliseconds per window (this thread) and the free poses' error after the solve.
GTSAM must be installed (``pip install stereopath[gtsam]``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def scene(K: int, n: int, seed: int = 0):
    from stereopath.device.core.geometry import make_pose, so3_exp

    rng = np.random.default_rng(seed)
    poses = [make_pose(so3_exp(np.array([0.0, 0.03 * k, 0.01 * k])), np.array([0.08 * k, 0.01 * k, 0.0]))
             for k in range(K)]
    X = np.column_stack([rng.uniform(-1.0, 1.5, n), rng.uniform(-0.8, 0.8, n), rng.uniform(1.5, 4.0, n)])
    return poses, X, rng


def observe(cam, T_world_cam, X, rng, noise_px):
    T_cw = np.linalg.inv(T_world_cam)
    Xr = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = Xr[:, 2]
    u, v = cam.f * Xr[:, 0] / z + cam.cx, cam.f * Xr[:, 1] / z + cam.cy
    ok = (z > 0.2) & (u > 0) & (u < 640) & (v > 0) & (v < 480)
    obs = np.column_stack([u, v, cam.fb / z])[ok]
    return np.flatnonzero(ok), obs + rng.normal(0.0, noise_px, obs.shape)


def solve_gtsam(g, cam, start, views, fixed: int):
    """Levenberg-Marquardt over the window (rectification = identity here: the camera is the rectified one)."""
    graph, values = g.NonlinearFactorGraph(), g.Values()
    Xk, Lk = g.symbol_shorthand.X, g.symbol_shorthand.L
    K = g.Cal3_S2Stereo(cam.f, cam.f, 0.0, cam.cx, cam.cy, cam.baseline_m)
    nm = g.noiseModel
    noise = nm.Robust.Create(nm.mEstimator.Huber.Create(1.0), nm.Isotropic.Sigma(3, 1.0))
    ids_all, counts = np.unique(np.concatenate([i for i, _ in views]), return_counts=True)
    keep = set(ids_all[counts >= 2].tolist())
    for k, T in enumerate(start):
        values.insert(Xk(k), g.Pose3(T))
        if k < fixed:
            graph.add(g.NonlinearEqualityPose3(Xk(k), g.Pose3(T)))
    first: dict[int, np.ndarray] = {}
    for k, (ids, obs) in enumerate(views):
        for i, (u, v, d) in zip(ids.tolist(), obs):
            if i not in keep:
                continue
            graph.add(g.GenericStereoFactor3D(g.StereoPoint2(u, u - d, v), noise, Xk(k), Lk(i), K))
            if i not in first:
                z = cam.fb / d
                first[i] = start[k][:3, :3] @ np.array([(u - cam.cx) / cam.f * z, (v - cam.cy) / cam.f * z, z]) \
                    + start[k][:3, 3]
    for i, Xw in first.items():
        values.insert(Lk(i), g.Point3(*Xw))
    params = g.LevenbergMarquardtParams()
    params.setMaxIterations(5)
    res = g.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return [res.atPose3(Xk(k)).matrix() for k in range(len(start))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--keyframes", type=int, default=6)
    ap.add_argument("--points", type=int, default=400)
    ap.add_argument("--fixed", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=10)
    args = ap.parse_args()
    import gtsam

    from stereopath.device.core.geometry import make_pose, so3_exp
    from stereopath.device.core.stereo_config import WindowConfig
    from stereopath.device.estimation.disparity_offset import RectifiedCamera
    from stereopath.device.estimation.local_window import WindowJob, solve_window

    cam = RectifiedCamera(400.0, 320.0, 240.0, 0.1)
    truth, X, rng = scene(args.keyframes, args.points)
    views = [observe(cam, T, X, rng, 0.3) for T in truth]
    start = [T.copy() if k < args.fixed else
             make_pose(so3_exp(rng.normal(0, 0.01, 3)) @ T[:3, :3], T[:3, 3] + rng.normal(0, 0.01, 3))
             for k, T in enumerate(truth)]
    job = WindowJob(args.keyframes - 1, start, list(range(args.keyframes)), views, [None] * args.keyframes, 0.0,
                    np.eye(4))
    cfg = WindowConfig(keyframes=args.keyframes, fixed=args.fixed, iterations=5, gyro=False)

    def err(poses):
        return 1000.0 * max(float(np.linalg.norm(a[:3, 3] - b[:3, 3])) for a, b in zip(poses, truth))

    for name, run in (("numpy", lambda: solve_window(job, cam, np.eye(3), cfg).T_after),
                      ("gtsam", lambda: solve_gtsam(gtsam, cam, start, views, args.fixed))):
        poses = run()
        t0 = time.thread_time()
        for _ in range(args.repeat):
            run()
        ms = 1000.0 * (time.thread_time() - t0) / args.repeat
        print(f"{name}: {ms:.1f} ms CPU per window, largest pose error {err(poses):.3f} mm "
              f"(start {err(start):.3f} mm)", flush=True)


if __name__ == "__main__":
    main()
