"""Why a local window can make a simulated scan worse: the window's solves measured against the truth.

    .venv/bin/python benchmarks/window_study.py [--spec sim:0] [--frames 400]
        [--variant NAME=JSON ...]

Runs our ``stereo`` estimator (keyframe work in line, so runs repeat) with the window off and in the
given variants (``[estimator.stereo.window]`` keys, and ``"dry": true``: solved, never applied;
``"anchor": "tracked"``: the window's own corrections do not move its keyframes, so each window holds
its oldest keyframe where the frame loop put it), and for every window solved prints, against the
simulator's true poses:

* the newest keyframe's pose relative to the held oldest one, as tracked (``tracked``), as the window
  left it (``window``), and where the window converges when started at the true poses (``from truth``:
  the error of the window's optimum itself, whatever its start);
* each point triangulated (true poses) at its first observation in the window and its later
  observations' residuals by their age in keyframes (``drift_px_by_age``: u, v, disparity RMS);
  they grow with the baseline through the first triangulation's depth error as well as with tracks
  that slide over the surface, so they bound the slide rather than measure it;
* the window's reprojection RMS at its optimum and with every pose held at the truth (points free):
  an optimum that fits the observations better than the truth does says the observations carry an
  error the window turns into pose error.

Figures in millimetres and degrees (medians over the windows), then each run's ATE.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
from dataclasses import replace

import numpy as np

DEFAULT_VARIANTS = {  # the figures of the docs (fixed: 1 unless named)
    "dry_gyro": {"enabled": True, "fixed": 1, "dry": True},
    "dry_vision": {"enabled": True, "fixed": 1, "gyro": False, "dry": True},
    "gyro": {"enabled": True, "fixed": 1},
    "vision": {"enabled": True, "fixed": 1, "gyro": False},
    "vision_k3": {"enabled": True, "fixed": 1, "gyro": False, "keyframes": 3},
    "vision_fixed3": {"enabled": True, "gyro": False, "fixed": 3},
    "vision_huber3": {"enabled": True, "fixed": 1, "gyro": False, "huber_px": 3.0},
    "vision_disp0.2": {"enabled": True, "fixed": 1, "gyro": False, "disparity_weight": 0.2},
    "prior3_gyro": {"enabled": True, "fixed": 1, "map_prior_weight": 3.0},
    "anchor_tracked": {"enabled": True, "fixed": 1, "gyro": False, "anchor": "tracked"},
}


def _rel(T0: np.ndarray, T: np.ndarray) -> np.ndarray:
    return np.linalg.inv(T0) @ T


def _err(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    from stereopath.device.core.geometry import rotation_angle_deg

    D = np.linalg.inv(A) @ B
    return 1000.0 * float(np.linalg.norm(D[:3, 3])), rotation_angle_deg(D[:3, :3])


def rms_at(job, cam, R0, cfg) -> float:
    """The window's reprojection RMS of u, v and disparity with every pose held where ``job`` puts it
    (points solved)."""
    from stereopath.device.estimation import local_window as lw

    got = lw._gather(job.views, job.offset_px)
    if got is None:
        return float("nan")
    seen, _ = got
    Rt = [lw._to_rectified(T, R0) for T in job.poses]
    R, t = [a for a, _ in Rt], [b for _, b in Rt]
    X = lw._initial_points(seen, R, t, cam)
    rms = float("nan")
    K = len(R)
    for _ in range(cfg.iterations + 1):
        step = lw._gauss_newton_step(R, t, X, seen, cam, [None] * K, K, cfg)
        if step is None:
            return float("nan")
        _, dX, rms = step
        X = X + dX
    # each component's RMS (px) over the observations the loss keeps
    Xc = np.matmul(np.stack(R)[seen.kf], X[seen.pt][:, :, None])[:, :, 0] + np.stack(t)[seen.kf]
    z = Xc[:, 2]
    r = np.column_stack([cam.f * Xc[:, 0] / z + cam.cx, cam.f * Xc[:, 1] / z + cam.cy, cam.fb / z]) - seen.M
    keep = np.abs(r).max(1) < 20 * cfg.huber_px
    return tuple(float(v) for v in np.sqrt(np.mean(r[keep] ** 2, axis=0)))


def drift_by_age(job, true_poses, cam, R0) -> dict[int, tuple[float, float, float]]:
    """With the true poses: each point triangulated at its first observation in the window, its later
    observations' residuals (RMS of u, v, disparity, px) by their age in keyframes."""
    from stereopath.device.estimation import local_window as lw

    got = lw._gather(job.views, job.offset_px)
    if got is None:
        return {}
    seen, _ = got
    Rt = [lw._to_rectified(T, R0) for T in true_poses]
    first = seen.starts
    u, v, d = seen.M[first].T
    z = cam.fb / d
    xr = np.column_stack([(u - cam.cx) / cam.f * z, (v - cam.cy) / cam.f * z, z])
    k0 = seen.kf[first]
    Rs, ts = np.stack([a for a, _ in Rt]), np.stack([b for _, b in Rt])
    X = np.einsum("nji,nj->ni", Rs[k0], xr - ts[k0])
    Xc = np.einsum("nij,nj->ni", Rs[seen.kf], X[seen.pt]) + ts[seen.kf]
    zc = Xc[:, 2]
    r = np.column_stack([cam.f * Xc[:, 0] / zc + cam.cx, cam.f * Xc[:, 1] / zc + cam.cy, cam.fb / zc]) - seen.M
    age = seen.kf - k0[seen.pt]
    out = {}
    for a in range(1, len(true_poses)):
        at = (age == a) & (np.abs(r).max(1) < 5.0)
        if at.sum() >= 20:
            out[a] = tuple(float(x) for x in np.sqrt(np.mean(r[at] ** 2, axis=0)))
    return out


def study(spec: str, frames: int, window: dict | None) -> dict:
    from stereopath.device.core.geometry import invert_pose
    from stereopath.device.estimation import local_window as lw
    from stereopath.device.estimation.base import run_estimator
    from stereopath.device.estimation.registry import make_estimator
    from stereopath.device.formats.source import open_source
    from stereopath.host.evaluation.evaluate import evaluate

    seq = open_source(spec, frames=frames) if spec.startswith("sim") else open_source(spec)
    options: dict = {"keyframes": {"background": False}}
    window = dict(window or {})
    dry = bool(window.pop("dry", False))
    anchor_tracked = window.pop("anchor", "window") == "tracked"
    if window:
        options["window"] = window
    est = make_estimator("stereo", seq.rig, options=options)
    solved: list = []
    original = lw.solve_window

    def recording(job, cam, R0, cfg):
        res = original(job, cam, R0, cfg)
        if res is not None:
            solved.append((job, res, cam, R0, cfg))
        return res

    lw.solve_window = recording
    from stereopath.device.estimation.keyframe_jobs import KeyframeWorker

    correction = KeyframeWorker._window_correction
    joined = lw.WindowKeyframes.joined
    if anchor_tracked:  # the records keep the frame loop's poses: the window's own corrections do not move them

        def joined_tracked(self, res, G, C_since, state, counts):
            if G is not None:
                C_old = state.C.copy()
                state.apply(G)
                counts.window_corrections += 1
                for r in self.records:  # C_new inv(r.C') = C_old inv(r.C): the record stays where it was
                    r.C = r.C @ invert_pose(C_old) @ state.C

        lw.WindowKeyframes.joined = joined_tracked
    if dry:  # solved and measured, never applied: the tracked poses stay the frame loop's own
        KeyframeWorker._window_correction = lambda self, res, C_since: replace(correction(self, res, C_since), G=None)
    t_of: dict[int, int] = {}

    def frames_seen():
        for f in seq.frames():
            t_of[f.seq] = f.t_ns
            yield f

    try:
        run = run_estimator(est, frames_seen(), seq.imu)
    finally:
        lw.solve_window = original
        KeyframeWorker._window_correction = correction
        lw.WindowKeyframes.joined = joined
        est.close()
    m = evaluate(seq.groundtruth, run.trajectory)
    gt = seq.groundtruth
    rows = []
    for job, res, cam, R0, cfg in solved:
        idx = [int(np.argmin(np.abs(gt.t_ns - t_of[s]))) for s in job.seqs]
        Tt = [gt.T_world_cam[i] for i in idx]
        true_rel = _rel(Tt[0], Tt[-1])
        tracked = _err(true_rel, _rel(job.poses[0], job.poses[-1]))
        window_err = _err(true_rel, _rel(res.T_after[0], res.T_after[-1]))
        # the true poses in the estimator's world, through the held oldest keyframe
        A = job.poses[0] @ invert_pose(Tt[0])
        truth_job = replace(job, poses=[A @ T for T in Tt])
        from_truth = original(truth_job, cam, R0, cfg)
        ft = _err(true_rel, _rel(from_truth.T_after[0], from_truth.T_after[-1])) if from_truth else (np.nan, np.nan)
        rows.append((tracked, window_err, ft, res.rms_px, rms_at(truth_job, cam, R0, cfg), res.cpu_ms,
                     drift_by_age(job, truth_job.poses, cam, R0)))
    out = dict(ate_mm=1000.0 * m["ate_rmse_m"], end_pct=m["end_error_pct"], windows=len(rows),
               corrections=est.counts.window_corrections)
    if rows:
        med = lambda k, j=None: float(np.nanmedian([r[k] if j is None else r[k][j] for r in rows]))  # noqa: E731
        out.update(tracked_mm=med(0, 0), window_mm=med(1, 0), from_truth_mm=med(2, 0), tracked_deg=med(0, 1),
                   window_deg=med(1, 1), from_truth_deg=med(2, 1), rms_opt_px=med(3),
                   rms_truth_u_px=med(4, 0), rms_truth_v_px=med(4, 1), rms_truth_d_px=med(4, 2),
                   cpu_ms=statistics.median(r[5] for r in rows))
        ages = sorted({a for r in rows for a in r[6]})
        out["drift_px_by_age"] = {a: [round(float(np.median([r[6][a][c] for r in rows if a in r[6]])), 3)
                                      for c in range(3)] for a in ages}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spec", default="sim:0")
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--variant", action="append", default=[], help="NAME=JSON of [estimator.stereo.window]")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    variants = dict(DEFAULT_VARIANTS)
    if args.variant:
        variants = {kv.split("=", 1)[0]: json.loads(kv.split("=", 1)[1]) for kv in args.variant}
    base = study(args.spec, args.frames, None)
    print(f"off: ATE {base['ate_mm']:.3f} mm, end {base['end_pct']:.4f} %", flush=True)
    for name, w in variants.items():
        r = study(args.spec, args.frames, w)
        print(f"{name}: " + json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()}),
              flush=True)


if __name__ == "__main__":
    main()
