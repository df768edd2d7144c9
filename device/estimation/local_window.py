"""The ``stereo`` estimator's local window: a bundle adjustment over its last keyframes (pure compute).

The last ``window.keyframes`` keyframes' poses and every point seen in stereo at two of them or more
are solved on the rectified ``(u, v, disparity)`` observations the keyframes made (the disparity
offset in use removed), with a Huber loss, by Gauss-Newton with the points eliminated (Schur
complement).  The tracked map's points (each the running mean of its stereo triangulations since it
was mapped) can enter as a prior of the window's points, seen from the oldest keyframe: what the
keyframes that left the window knew of them.  With a gyro, the rotation it measured between
consecutive keyframes is one more residual per pair (weighted by its noise and the bias's
uncertainty over the interval).  The gauge and what leaves the window: the oldest ``window.fixed``
keyframes are held where earlier windows left them; without the map prior, what a keyframe knew
leaves with it.

:class:`WindowKeyframes` keeps the keyframe records on the frame loop's side (their poses move with
every correction of the live state, except a window's own refinement of them); the keyframe worker
runs :func:`solve_window` on a copy (:class:`WindowJob`) and its result comes back through
:meth:`~stereopath.device.estimation.keyframe_jobs.KeyframeWorker.poll`.
See docs/architecture.md, "The on-board estimator" (the local window, and why it is off by default).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from stereopath.device.core.geometry import invert_pose, project_to_se3, so3_exp, so3_log
from stereopath.device.core.stereo_config import WindowConfig
from stereopath.device.estimation.disparity_offset import (RectifiedCamera, huber_weights,
                                                          projection_and_motion_jacobians)
from stereopath.device.estimation.inertial import VisionGyroBias
from stereopath.device.estimation.live_state import LiveState, StereoStats
from stereopath.device.estimation.tracked_map import TrackedMap

LM_DAMPING = 1e-6  # relative damping of the reduced system's diagonal
MIN_LINK_POINTS = 6  # consecutive keyframes sharing fewer points are not in one window


@dataclass
class WindowKeyframe:
    """One keyframe as the window sees it: its stereo observations and its pose (camera 1 to world)."""

    seq: int
    T_world_cam: np.ndarray
    ids: np.ndarray  # point ids
    obs: np.ndarray  # (n, 3) rectified (u, v, disparity) as measured
    C: np.ndarray  # the live state's cumulative correction the pose is expressed in
    R_gyro: np.ndarray | None = None  # the camera's rotation from the previous keyframe by the gyro
    dt_gyro: float = 0.0  # seconds the gyro rotation covers


@dataclass
class WindowJob:
    """A window solve as the frame loop hands it over (copies, in the world of its submission)."""

    seq: int  # the newest keyframe's frame
    poses: list[np.ndarray]  # camera 1 to world, oldest first
    seqs: list[int]
    views: list[tuple[np.ndarray, np.ndarray]]  # (ids, rectified rows) per keyframe
    gyro: list[tuple[np.ndarray, float] | None]  # camera rotation from the previous keyframe and its sigma (rad)
    offset_px: float  # the disparity offset in use
    C_sub: np.ndarray
    map_points: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # tracked map: ids, X (world), nobs


@dataclass
class WindowResult:
    """A solved window: each keyframe's refined pose (world of the job's submission)."""

    seq: int
    seqs: list[int]
    T_before: list[np.ndarray]
    T_after: list[np.ndarray]
    rms_px: float
    n_points: int
    cpu_ms: float
    depth_m: float = float("nan")  # the median depth of the newest keyframe's points (the translation gate's scale)


@dataclass
class WindowKeyframes:
    """The frame loop's side: the last keyframes' records, and the gyro rotation since the newest."""

    cfg: WindowConfig
    records: deque[WindowKeyframe] = field(default_factory=deque)
    _R_gyro: np.ndarray | None = None
    _dt_gyro: float = 0.0

    def gyro_step(self, step: tuple[np.ndarray, float] | None, R_body_cam: np.ndarray | None) -> None:
        """The gyro's body rotation over one frame and its length (None: no gyro, or a gap; the chain
        since the newest keyframe is then broken)."""
        if step is None or R_body_cam is None:
            self._R_gyro, self._dt_gyro = None, -1.0
            return
        if self._dt_gyro < 0.0:
            return
        R_cam = R_body_cam.T @ step[0] @ R_body_cam
        self._R_gyro = R_cam if self._R_gyro is None else self._R_gyro @ R_cam
        self._dt_gyro += step[1]

    def add(self, seq: int, T_world_cam: np.ndarray, ids: np.ndarray, obs: np.ndarray, C: np.ndarray) -> None:
        """A new keyframe (its observations as measured, its pose in the live world of correction ``C``)."""
        R_g = self._R_gyro if self._dt_gyro > 0.0 and self.records else None
        self.records.append(WindowKeyframe(seq, T_world_cam.copy(), ids.copy(), obs.copy(), C.copy(), R_g,
                                           max(self._dt_gyro, 0.0)))
        while len(self.records) > self.cfg.keyframes:
            self.records.popleft()
        self._R_gyro, self._dt_gyro = None, 0.0

    def linked(self) -> list[WindowKeyframe]:
        """The newest records linked to each other by shared points (a restarted map cuts the chain)."""
        recs = list(self.records)
        k = len(recs) - 1
        while k > 0 and len(np.intersect1d(recs[k - 1].ids, recs[k].ids)) >= MIN_LINK_POINTS:
            k -= 1
        return recs[k:]

    def job(self, C: np.ndarray, offset_px: float, bias: VisionGyroBias | None,
            tracked: TrackedMap | None = None) -> WindowJob | None:
        """The window to solve now (the live world of correction ``C``; ``bias``: the gyro bias's
        estimate, whose uncertainty weighs the gyro residuals; ``tracked``: the map, for the map prior),
        None when it is too short."""
        recs = self.linked()
        if len(recs) < self.cfg.fixed + 1:
            return None
        poses = [project_to_se3(C @ invert_pose(r.C) @ r.T_world_cam) for r in recs]
        bias_sigma = max(self.cfg.gyro_bias_floor_rad_s, 0.0 if bias is None else bias.sigma_rad_s)
        gyro: list[tuple[np.ndarray, float] | None] = [None]
        for r in recs[1:]:
            if r.R_gyro is None or not self.cfg.gyro:
                gyro.append(None)
            else:
                dt = r.dt_gyro
                gyro.append((r.R_gyro, float(np.hypot(self.cfg.gyro_noise_rad_s_rthz * np.sqrt(dt), bias_sigma * dt))))
        points = None
        if tracked is not None and self.cfg.map_prior_weight > 0.0:
            points = (tracked.ids.copy(), tracked.X.copy(), tracked.nobs.copy())
        return WindowJob(recs[-1].seq, poses, [r.seq for r in recs], [(r.ids, r.obs) for r in recs], gyro,
                         offset_px, C.copy(), points)

    def joined(self, res: WindowResult, G: np.ndarray | None, C_since: np.ndarray, state: LiveState,
               counts: StereoStats) -> None:
        """A solved window comes back (on the frame loop): its newest keyframe's correction ``G`` (None:
        refused) moves the live state; its refined keyframes are kept for the next windows (``C_since``
        maps its world to the live one)."""
        if G is not None:
            state.apply(G)
            counts.window_corrections += 1
        counts.window_cpu_us += int(round(1000 * res.cpu_ms))
        if G is None:
            return
        after = dict(zip(res.seqs, res.T_after))
        for r in self.records:
            if r.seq in after:
                r.T_world_cam = project_to_se3(C_since @ after[r.seq])
                r.C = state.C.copy()


@dataclass(frozen=True)
class _Observations:
    """Every stereo observation of the window, grouped by point: rows, keyframe, point index, group starts."""

    M: np.ndarray
    kf: np.ndarray
    pt: np.ndarray
    starts: np.ndarray
    weight: np.ndarray  # 1 for a measurement, the map prior's weight for its rows
    prior: np.ndarray  # the map prior's rows


def _gather(views: list[tuple[np.ndarray, np.ndarray]], offset_px: float,
            prior: MapPrior | None = None) -> tuple[_Observations, np.ndarray] | None:
    """The observations of points seen at two keyframes or more (offset removed), and those points' ids;
    ``prior``: rows of the tracked map's points at the oldest keyframe (its pose is held), weighted."""
    kf, ids, M, wt, pr = [], [], [], [], []
    for j, (i, obs) in enumerate(views):
        obs = np.asarray(obs, float).reshape(-1, 3)
        ok = np.isfinite(obs).all(1) & (obs[:, 2] - offset_px > 0.5)
        kf.append(np.full(int(ok.sum()), j))
        ids.append(np.asarray(i, np.int64)[ok])
        M.append(obs[ok] - np.array([0.0, 0.0, offset_px]))
        wt.append(np.ones(int(ok.sum())))
        pr.append(np.zeros(int(ok.sum()), bool))
    kf_a, id_a = np.concatenate(kf), np.concatenate(ids)
    uniq, counts = np.unique(id_a, return_counts=True)
    keep = uniq[counts >= 2]
    if len(keep) == 0:
        return None
    if prior is not None:
        on = np.isin(prior.ids, keep)
        kf.append(np.zeros(int(on.sum()), np.int64))
        ids.append(prior.ids[on])
        M.append(prior.rows[on])
        wt.append(prior.weight[on])
        pr.append(np.ones(int(on.sum()), bool))
        kf_a, id_a = np.concatenate(kf), np.concatenate(ids)
    M_a, wt_a, pr_a = np.concatenate(M), np.concatenate(wt), np.concatenate(pr)
    sel = np.isin(id_a, keep)
    pt = np.searchsorted(keep, id_a[sel])
    # by point, then keyframe, measurements before a prior row of the same keyframe
    order = np.lexsort((pr_a[sel], kf_a[sel], pt))
    kf_s, pt_s = kf_a[sel][order], pt[order]
    starts = np.flatnonzero(np.r_[True, pt_s[1:] != pt_s[:-1]])
    return _Observations(M_a[sel][order], kf_s, pt_s, starts, wt_a[sel][order], pr_a[sel][order]), keep


@dataclass(frozen=True)
class MapPrior:
    """The tracked map's points as a prior of the window's: each one's (u, v, disparity) at the oldest
    keyframe and its weight."""

    ids: np.ndarray
    rows: np.ndarray
    weight: np.ndarray


def map_prior(job: WindowJob, cam: RectifiedCamera, R0: np.ndarray, scale: float) -> MapPrior | None:
    """The map's points of ``job`` (each the mean of ``nobs`` stereo triangulations) seen from its
    oldest keyframe, each weighing ``scale * sqrt(nobs)`` (its mean's standard error in observations)."""
    if job.map_points is None or scale <= 0.0:
        return None
    ids, X, nobs = job.map_points
    R, t = _to_rectified(job.poses[0], R0)
    Xr = X @ R.T + t
    ok = Xr[:, 2] > 1e-3
    z = Xr[ok, 2]
    rows = np.column_stack([cam.f * Xr[ok, 0] / z + cam.cx, cam.f * Xr[ok, 1] / z + cam.cy, cam.fb / z])
    w = scale * np.sqrt(np.maximum(nobs[ok], 1.0))
    return MapPrior(np.asarray(ids, np.int64)[ok], rows, w)


def _to_rectified(T_world_cam: np.ndarray, R0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World -> rectified camera 1 (``x = R X + t``) of a camera-1 pose."""
    T_cw = invert_pose(T_world_cam)
    return R0 @ T_cw[:3, :3], R0 @ T_cw[:3, 3]


def _from_rectified(R: np.ndarray, t: np.ndarray, R0: np.ndarray) -> np.ndarray:
    T_cw = np.eye(4)
    T_cw[:3, :3], T_cw[:3, 3] = R0.T @ R, R0.T @ t
    return invert_pose(T_cw)


def solve_window(job: WindowJob, cam: RectifiedCamera, R0: np.ndarray, cfg: WindowConfig) -> WindowResult | None:
    """The window's bundle adjustment (see the module's docstring); None when it has too few points or the
    solve fails.  ``cam`` and ``R0``: the rig's rectified left camera and its rectifying rotation."""
    t_cpu = time.thread_time()
    got = _gather(job.views, job.offset_px, map_prior(job, cam, R0, cfg.map_prior_weight))
    if got is None or len(got[1]) < cfg.min_points:
        return None
    seen, _ = got
    K = len(job.poses)
    Rt = [_to_rectified(T, R0) for T in job.poses]
    R = [a for a, _ in Rt]
    t = [b for _, b in Rt]
    X = _initial_points(seen, R, t, cam)
    nf = min(cfg.fixed, K - 1)
    gyro = [None if g is None else (R0 @ g[0] @ R0.T, g[1]) for g in job.gyro]
    rms = float("nan")
    cost0 = best = _window_cost(R, t, X, seen, cam, gyro, cfg)
    kept = (list(R), list(t), X, rms)
    for _ in range(cfg.iterations):
        step = _gauss_newton_step(R, t, X, seen, cam, gyro, nf, cfg)
        if step is None:
            return None
        dg, dX, rms = step
        if not (np.isfinite(dg).all() and np.isfinite(dX).all()):
            return None
        for k in range(nf, K):
            o = 6 * (k - nf)
            R[k] = so3_exp(dg[o + 3:o + 6]) @ R[k]
            t[k] = t[k] + dg[o:o + 3]
        X = X + dX
        cost = _window_cost(R, t, X, seen, cam, gyro, cfg)
        if not cost < best:  # a step that does not lower the robust cost: the last good state
            break
        best, kept = cost, (list(R), list(t), X, rms)
        if np.abs(dg).max(initial=0.0) < 1e-7:
            break
    if not best < cost0:  # the solve did not lower the cost: nothing to correct with
        return None
    R, t, X, rms = kept
    after = [job.poses[k].copy() if k < nf else _from_rectified(R[k], t[k], R0) for k in range(K)]
    newest = seen.kf == K - 1
    depth = float(np.median(cam.fb / seen.M[newest, 2])) if newest.any() else float("nan")
    cpu_ms = 1000.0 * (time.thread_time() - t_cpu)
    return WindowResult(job.seq, list(job.seqs), [T.copy() for T in job.poses], after, rms, len(X), cpu_ms, depth)


def _initial_points(seen: _Observations, R: list[np.ndarray], t: list[np.ndarray], cam: RectifiedCamera) -> np.ndarray:
    """Each point triangulated at its newest observation (world)."""
    last = np.r_[seen.starts[1:], len(seen.M)] - 1
    u, v, d = seen.M[last].T
    z = cam.fb / d
    xr = np.column_stack([(u - cam.cx) / cam.f * z, (v - cam.cy) / cam.f * z, z])
    Rs, ts = np.stack(R)[seen.kf[last]], np.stack(t)[seen.kf[last]]
    return np.einsum("nji,nj->ni", Rs, xr - ts)


def _window_cost(R: list[np.ndarray], t: list[np.ndarray], X: np.ndarray, seen: _Observations, cam: RectifiedCamera,
                 gyro: list[tuple[np.ndarray, float] | None], cfg: WindowConfig) -> float:
    """The robust cost the Gauss-Newton steps lower: each residual component's Huber loss (capped where the
    step's weights ignore it) and the gyro's whitened rotation residuals."""
    Ra, ta = np.stack(R)[seen.kf], np.stack(t)[seen.kf]
    Xc = np.matmul(Ra, X[seen.pt][:, :, None])[:, :, 0] + ta
    z = np.maximum(Xc[:, 2], 1e-9)
    ws = seen.weight[:, None] * np.array([1.0, 1.0, cfg.disparity_weight])
    r = (np.column_stack([cam.f * Xc[:, 0] / z + cam.cx, cam.f * Xc[:, 1] / z + cam.cy, cam.fb / z]) - seen.M) * ws
    k = cfg.huber_px
    e = np.minimum(np.abs(r), 20 * k)
    cost = float(np.sum(np.where(e < k, e * e, 2 * k * e - k * k)))
    for j in range(1, len(R)):
        if gyro[j] is not None:
            D, sigma = gyro[j]
            cost += float(np.sum(so3_log(D.T @ R[j - 1] @ R[j].T) ** 2)) / sigma**2
    return cost


def _gauss_newton_step(R: list[np.ndarray], t: list[np.ndarray], X: np.ndarray, seen: _Observations,
                       cam: RectifiedCamera, gyro: list[tuple[np.ndarray, float] | None], nf: int,
                       cfg: WindowConfig) -> tuple[np.ndarray, np.ndarray, float] | None:
    """One step ``(d poses, d points, rms px)``: the free poses' (dt, dtheta) and each point's move (the
    first ``nf`` poses held).  The disparity residual weighs ``cfg.disparity_weight`` (u and v: 1)."""
    K = len(R)
    ng = 6 * (K - nf)
    Ra, ta = np.stack(R)[seen.kf], np.stack(t)[seen.kf]
    RX = np.matmul(Ra, X[seen.pt][:, :, None])[:, :, 0]
    Xc = RX + ta
    z = np.maximum(Xc[:, 2], 1e-9)
    f, cx, cy, fb = cam.f, cam.cx, cam.cy, cam.fb
    scale = np.array([1.0, 1.0, cfg.disparity_weight])
    ws = seen.weight[:, None] * scale
    r = (np.column_stack([f * Xc[:, 0] / z + cx, f * Xc[:, 1] / z + cy, fb / z]) - seen.M) * ws
    w = huber_weights(r, z, cfg.huber_px)
    dproj, dX = projection_and_motion_jacobians(Xc, RX, z, f, fb)
    dproj = dproj * ws[:, :, None]
    Jp = np.matmul(dproj, Ra)  # (o, 3, 3) by the point
    Jpose = np.matmul(dproj, dX)  # (o, 3, 6) by the observing pose
    Jpose_w, Jp_w = Jpose * w[:, :, None], Jp * w[:, :, None]
    # each observation touches one pose and one point: the normal equations by blocks, as stacks of
    # small products (no large BLAS call: a multi-threaded BLAS on a busy machine costs a hundred times more)
    H = np.zeros((ng, ng))
    b = np.zeros(ng)
    for k in range(nf, K):
        at = seen.kf == k
        o = 6 * (k - nf)
        H[o:o + 6, o:o + 6] = np.matmul(Jpose_w[at].transpose(0, 2, 1), Jpose[at]).sum(0)
        b[o:o + 6] = np.matmul(Jpose_w[at].transpose(0, 2, 1), r[at][:, :, None]).sum(0)[:, 0]
    _add_gyro_terms(H, b, R, gyro, nf)
    starts = seen.starts
    Jp_wT = Jp_w.transpose(0, 2, 1)
    Hpp = np.add.reduceat(np.matmul(Jp_wT, Jp), starts, axis=0) + 1e-9 * np.eye(3)
    bp = np.add.reduceat(np.matmul(Jp_wT, r[:, :, None])[:, :, 0], starts, axis=0)
    try:
        Hpp_inv = np.linalg.inv(Hpp)
    except np.linalg.LinAlgError:
        return None
    if ng == 0:  # every pose held: the points alone
        return np.zeros(0), -np.matmul(Hpp_inv, bp[:, :, None])[:, :, 0], _rms(r, w, seen.prior)
    free = np.flatnonzero(seen.kf >= nf)
    Hgp = np.zeros((len(starts), ng, 3))  # pose-point blocks (a point is seen once per keyframe)
    blocks = np.matmul(Jpose_w[free].transpose(0, 2, 1), Jp[free])
    cols = 6 * (seen.kf[free] - nf)
    for c in range(6):
        np.add.at(Hgp, (seen.pt[free], cols + c), blocks[:, c, :])
    W = np.matmul(Hgp, Hpp_inv)
    S = H - np.einsum("pik,pjk->ij", W, Hgp)
    S = S + LM_DAMPING * np.diag(np.diag(S)) + 1e-12 * np.eye(ng)
    try:
        dg = -np.linalg.solve(S, b - np.matmul(W, bp[:, :, None]).sum(0)[:, 0])
    except np.linalg.LinAlgError:
        return None
    dp = -np.matmul(Hpp_inv, (bp + np.matmul(Hgp.transpose(0, 2, 1), dg))[:, :, None])[:, :, 0]
    return dg, dp, _rms(r, w, seen.prior)


def _rms(r: np.ndarray, w: np.ndarray, prior: np.ndarray) -> float:
    """The RMS (px) of the measurements' residuals no component of which is ignored."""
    good = (w.min(1) > 0) & ~prior
    return float(np.sqrt(np.mean(r[good] ** 2))) if good.any() else float("nan")


def _add_gyro_terms(H: np.ndarray, b: np.ndarray, R: list[np.ndarray], gyro: list[tuple[np.ndarray, float] | None],
                    nf: int) -> None:
    """The gyro's rotation between consecutive keyframes: ``e = log(D^T R_i R_j^T)`` with ``D`` the
    measured ``R_i R_j^T`` (world -> rectified rotations), ``de/da_i = (R_i R_j^T)^T`` and ``de/da_j = -I``
    for left perturbations ``exp(a) R``, over its sigma."""
    for j in range(1, len(R)):
        g = gyro[j]
        if g is None:
            continue
        D, sigma = g
        i = j - 1
        M = R[i] @ R[j].T
        e = so3_log(D.T @ M)
        Ji, Jj = M.T, -np.eye(3)
        s2 = 1.0 / sigma**2
        blocks = [(i, Ji), (j, Jj)]
        for k, Jk in blocks:
            if k < nf:
                continue
            ok = 6 * (k - nf) + 3
            b[ok:ok + 3] += s2 * Jk.T @ e
            for m, Jm in blocks:
                if m < nf:
                    continue
                om = 6 * (m - nf) + 3
                H[ok:ok + 3, om:om + 3] += s2 * Jk.T @ Jm
