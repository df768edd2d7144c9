"""Bundle adjustment on GTSAM: keyframe poses and points on the reprojection error in both cameras.

One ``GenericProjectionFactorCal3_S2`` per observation row ``(pose, point id, cam, u, v[, weight])``
(the right camera through ``body_P_sensor`` = the rig's ``T_cam0_cam1``: any calibrated rig), each
with a robust noise model (sigma = 1 px / weight); the first ``n_fixed`` poses held by a tight prior;
Levenberg-Marquardt over the batch (sequential Cholesky, points eliminated first in a fixed order).
Options: rotation priors (``BetweenFactorPose3`` with a free translation), and the disparity offset as
one shared right-camera ``Cal3_S2`` unknown (only ``u0`` free; right observations as
``GeneralSFMFactor2Cal3_S2``), applied only above ``disparity_offset_min_px`` and
:data:`OFFSET_SIGNIFICANCE` standard errors.  GTSAM is imported when a function runs.  Pure
computation.  See docs/architecture.md, "Reprocessing".
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from stereopath.device.core.rig import Rig
from stereopath.device.errors import ConfigError
from stereopath.host.backend.gtsam_lib import import_gtsam  # noqa: F401  (re-exported)
from stereopath.host.backend.ba_common import (
    LOSSES,
    MIN_POSES_PER_POINT,
    RELATIVE_TOL,
    BAConfig,
    BAProblem,
    BAResult,
    RotationPrior,
    check_problem,
    reprojection_residuals,
    rms_px,
    select_observations,
)

if TYPE_CHECKING:
    import gtsam

    from stereopath.host.backend.imu_factors import ImuTerms
    from stereopath.host.backend.loops import Loop

log = logging.getLogger(__name__)

GAUGE_SIGMA = 1e-6  # rad and m: the held poses
RIG_SIGMA = 1e-5  # rad and m: right-camera pose = left pose x rig extrinsics (disparity offset only)
FREE_SIGMA = 1e3  # an unconstrained direction of a prior
TILT_SIGMA = 0.1  # rad: the held pose's tilt when the IMU's gravity can fix it
OFFSET_SIGNIFICANCE = 3.0  # standard errors an estimated disparity offset must exceed to be applied


def _keys(symbol: str, index: np.ndarray) -> list[int]:
    """GTSAM symbol keys (``symbol_shorthand``) of many indices at once: char << 56 | index."""
    return ((ord(symbol) << 56) + np.asarray(index).astype(np.int64)).tolist()


def _pose(g: ModuleType, T: np.ndarray) -> gtsam.Pose3:
    return g.Pose3(g.Rot3.ClosestTo(np.asarray(T[:3, :3], float)), np.asarray(T[:3, 3], float))


def add_loop_factors(g: ModuleType, graph: gtsam.NonlinearFactorGraph, X: Callable[[int], int], loops: list[Loop],
                     k_sigma: float = 3.0) -> None:
    """Relative-pose constraints of verified loops (Huber at ``k_sigma`` standard deviations)."""
    nm = g.noiseModel
    for lp in loops:
        sig = np.array([lp.sigma_rot_rad] * 3 + [lp.sigma_trans_m] * 3)
        noise = nm.Robust.Create(nm.mEstimator.Huber.Create(k_sigma), nm.Diagonal.Sigmas(sig))
        graph.add(g.BetweenFactorPose3(X(lp.i), X(lp.j), _pose(g, lp.T_ci_cj), noise))


class _Graph:
    """Builds the factor graph and initial values of one problem."""

    def __init__(self, rig: Rig, loss: str, k_px: float, offset_px: float, estimate_offset: bool,
                 pixel_sigma: float = 1.0) -> None:
        g = self.g = import_gtsam()
        if loss not in LOSSES:
            raise ConfigError(f"loss = {loss!r}; known: {', '.join(LOSSES)}")
        self.loss, self.k, self.pixel_sigma = loss, float(k_px), float(pixel_sigma)
        self.graph = g.NonlinearFactorGraph()
        self.values = g.Values()
        self.X, self.L = g.symbol_shorthand.X, g.symbol_shorthand.L
        self.R_, self.C = g.symbol_shorthand.R, g.symbol_shorthand.C
        K0, K1 = rig.cam0.K, rig.cam1.K
        self.cal0 = g.Cal3_S2(K0[0, 0], K0[1, 1], K0[0, 1], K0[0, 2], K0[1, 2])
        self.cal1 = g.Cal3_S2(K1[0, 0], K1[1, 1], K1[0, 1], K1[0, 2] + offset_px, K1[1, 2])
        self.cx1 = float(K1[0, 2])
        self.T01 = self.pose(np.asarray(rig.T_cam0_cam1, float))
        self.est_offset = estimate_offset
        self._noise: dict[float, gtsam.noiseModel.Base] = {}
        if estimate_offset:
            self.values.insert(self.C(0), self.cal1)
            sig = np.array([RIG_SIGMA, RIG_SIGMA, RIG_SIGMA, FREE_SIGMA, RIG_SIGMA])  # fx fy s u0 v0
            self.graph.add(g.PriorFactorCal3_S2(self.C(0), self.cal1, g.noiseModel.Diagonal.Sigmas(sig)))

    def pose(self, T: np.ndarray) -> gtsam.Pose3:
        return _pose(self.g, T)

    def noise(self, weight: float) -> gtsam.noiseModel.Base:
        """Robust isotropic 2D noise with sigma ``pixel_sigma / weight`` px (cached by weight); the
        robust loss turns at ``k / weight`` px whatever the sigma."""
        m = self._noise.get(weight)
        if m is None:
            nm = self.g.noiseModel
            m = nm.Isotropic.Sigma(2, self.pixel_sigma / max(weight, 1e-9))
            if self.loss != "linear":
                est = nm.mEstimator.Huber if self.loss == "huber" else nm.mEstimator.Cauchy
                m = nm.Robust.Create(est.Create(self.k / self.pixel_sigma), m)
            self._noise[weight] = m
        return m

    def gauge_noise(self, T: np.ndarray, gravity_world: np.ndarray | None) -> gtsam.noiseModel.Base:
        """The held pose's prior: tight, or (with the IMU) free to tilt, i.e. to rotate about the
        horizontal axes, which only gravity can fix (the visual problem is the same in any rotation)."""
        nm = self.g.noiseModel
        if gravity_world is None:
            return nm.Isotropic.Sigma(6, GAUGE_SIGMA)
        u = np.asarray(gravity_world, float) / np.linalg.norm(gravity_world)
        cov_world = GAUGE_SIGMA ** 2 * np.outer(u, u) + TILT_SIGMA ** 2 * (np.eye(3) - np.outer(u, u))
        R = np.asarray(T[:3, :3], float)
        cov = np.zeros((6, 6))
        cov[:3, :3] = R.T @ cov_world @ R  # Pose3's rotation tangent is in the pose's own frame
        cov[3:, 3:] = GAUGE_SIGMA ** 2 * np.eye(3)
        return nm.Gaussian.Covariance(cov)

    def add_poses(self, T_world_cam: np.ndarray, held: np.ndarray, gravity_world: np.ndarray | None = None) -> None:
        g = self.g
        rig_noise = g.noiseModel.Isotropic.Sigma(6, RIG_SIGMA)
        for k, T in enumerate(T_world_cam):
            P = self.pose(T)
            self.values.insert(self.X(k), P)
            if held[k]:
                self.graph.add(g.PriorFactorPose3(self.X(k), P, self.gauge_noise(T, gravity_world)))
            if self.est_offset:
                self.values.insert(self.R_(k), P.compose(self.T01))
                self.graph.add(g.BetweenFactorPose3(self.X(k), self.R_(k), self.T01, rig_noise))

    def add_points(self, ids: np.ndarray, xyz: np.ndarray) -> None:
        for i, x in zip(ids, xyz):
            self.values.insert(self.L(int(i)), np.asarray(x, float))

    def add_observations(self, obs: np.ndarray) -> None:
        g, add = self.g, self.graph.add
        w = obs[:, 5] if obs.shape[1] > 5 else np.ones(len(obs))
        # keys, pixels and noise models prepared in bulk: the loop only constructs factors
        xk = _keys("x", obs[:, 0])
        rk = _keys("r", obs[:, 0])
        lk = _keys("l", obs[:, 1])
        uv = np.ascontiguousarray(obs[:, 3:5], float)
        noise = [self.noise(float(x)) for x in w.tolist()]
        Proj, SFM = g.GenericProjectionFactorCal3_S2, g.GeneralSFMFactor2Cal3_S2
        cal0, cal1, T01, C0 = self.cal0, self.cal1, self.T01, self.C(0)
        for i, cam in enumerate(obs[:, 2].tolist()):
            if cam == 0:
                add(Proj(uv[i], noise[i], xk[i], lk[i], cal0))
            elif self.est_offset:
                add(SFM(uv[i], noise[i], rk[i], lk[i], C0))
            else:
                add(Proj(uv[i], noise[i], xk[i], lk[i], cal1, False, False, T01))

    def add_rotation_priors(self, priors: list[RotationPrior]) -> None:
        g = self.g
        for pr in priors:
            sig = np.array([pr.sigma_rad] * 3 + [FREE_SIGMA] * 3)
            rel = g.Pose3(g.Rot3.ClosestTo(np.asarray(pr.R_ci_cj, float)), np.zeros(3))
            # the translation of the measured relative pose is unknown: its sigma leaves it free
            self.graph.add(g.BetweenFactorPose3(self.X(pr.i), self.X(pr.j), rel, g.noiseModel.Diagonal.Sigmas(sig)))


    def add_loops(self, loops: list) -> None:
        add_loop_factors(self.g, self.graph, self.X, loops)

    def add_imu(self, terms: ImuTerms) -> None:
        """Velocity and bias unknowns, CombinedImuFactors between keyframes, a prior on each chain's first bias."""
        g = self.g
        self.V, self.B = g.symbol_shorthand.V, g.symbol_shorthand.B
        linked = sorted({k for i, j, _ in terms.pims for k in (i, j)})
        starts = {i for i, _, _ in terms.pims} - {j for _, j, _ in terms.pims}
        n = terms.noise
        bias_prior = g.noiseModel.Diagonal.Sigmas(np.array([n.accel_bias_prior] * 3 + [n.gyro_bias_prior] * 3))
        for k in linked:
            self.values.insert(self.V(k), np.asarray(terms.velocities[k], float))
            self.values.insert(self.B(k), terms.bias0)
            if k in starts:
                self.graph.add(g.PriorFactorConstantBias(self.B(k), terms.bias0, bias_prior))
        for i, j, pim in terms.pims:
            self.graph.add(g.CombinedImuFactor(self.X(i), self.V(i), self.X(j), self.V(j), self.B(i), self.B(j), pim))
        self.imu_keys = linked


def _points_first(gr: _Graph) -> gtsam.Ordering:
    """The elimination ordering of bundle adjustment: every point, then the rest (poses, velocities,
    biases, calibration).  Eliminating the points first is the Schur complement: what is left is
    the small, dense reduced camera system."""
    keys = np.array(gr.values.keys(), dtype=np.uint64)
    kind = keys >> np.uint64(56)  # the symbol's character
    # points, then poses and the rest, the shared calibration last (first, it would join every clique)
    rank = np.where(kind == ord("l"), 0, np.where(kind == ord("c"), 2, 1))
    return gr.g.Ordering(keys[np.argsort(rank, kind="stable")].tolist())


# a solve that is followed by an outlier round only has to bring the residuals to where the 3 px
# selection is settled (the last solve stops at BAConfig.relative_tol)
RELATIVE_TOL_BEFORE_OUTLIERS = 1e-2


def _optimize(gr: _Graph, max_iterations: int, on_iteration=None, relative_tol: float = RELATIVE_TOL
              ) -> tuple[gtsam.Values, int, list[float]]:
    """Levenberg-Marquardt from ``gr.values``; (values, iterations, error after each iteration).

    Points eliminated first (:func:`_points_first`), sequential Cholesky: cheaper than multifrontal
    or a METIS / COLAMD ordering on these problems, and a fixed order keeps results repeatable."""
    g = gr.g
    params = g.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_tol)
    params.setAbsoluteErrorTol(1e-9)
    params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
    params.setOrdering(_points_first(gr))
    opt = g.LevenbergMarquardtOptimizer(gr.graph, gr.values, params)
    history = [opt.error()]
    it = 0
    for it in range(1, max_iterations + 1):
        prev = opt.error()
        opt.iterate()
        history.append(opt.error())
        if on_iteration is not None:
            on_iteration(1)
        if g.checkConvergence(params.getRelativeErrorTol(), params.getAbsoluteErrorTol(), params.getErrorTol(),
                              prev, opt.error()):
            break
    return opt.values(), it, history


def _read(gr: _Graph, values: gtsam.Values, n_poses: int, ids: np.ndarray) -> tuple[np.ndarray, dict[int, np.ndarray], float]:
    T = np.array([values.atPose3(gr.X(k)).matrix() for k in range(n_poses)])
    pts = {int(i): np.asarray(values.atPoint3(gr.L(int(i))), float).copy() for i in ids}
    offset = values.atCal3_S2(gr.C(0)).px() - gr.cx1 if gr.est_offset else float(gr.cal1.px() - gr.cx1)
    return T, pts, float(offset)


@dataclass
class _Solve:
    """One batch solve's problem: poses (the first ``held`` ones tied by the gauge prior), points,
    observation rows, rotation priors, loops and IMU terms, and the disparity offset (estimated or held)."""

    T: np.ndarray
    points: dict[int, np.ndarray]
    obs: np.ndarray
    held: np.ndarray
    priors: list[RotationPrior]
    loops: list[Loop]
    imu: ImuTerms | None
    offset_px: float
    estimate_offset: bool
    held_may_tilt: bool = True


@dataclass
class _Solved:
    """What one batch solve found (the IMU's gravity and biases only with IMU terms; the offset's
    standard error only when asked for and computable)."""

    T: np.ndarray
    points: dict[int, np.ndarray]
    offset_px: float
    iterations: int
    history: list[float]
    offset_sigma_px: float | None = None
    gravity_world: np.ndarray | None = None
    imu_biases: np.ndarray | None = None


@dataclass(frozen=True)
class _Numerics:
    """How a solve weighs and stops: the robust loss, the pixel noise, the iteration limit and tolerance,
    and the offset change above which the offset's standard error is computed (None: never)."""

    loss: str
    robust_px: float
    max_iterations: int
    pixel_sigma: float = 1.0
    tol: float = RELATIVE_TOL
    offset_check_px: float | None = None


def _solve(rig: Rig, pb: _Solve, num: _Numerics, on_iteration: Callable[[int], object] | None = None) -> _Solved:
    """One batch solve (Levenberg-Marquardt from the problem's values)."""
    gr = _Graph(rig, num.loss, num.robust_px, pb.offset_px, pb.estimate_offset, num.pixel_sigma)
    ids = np.unique(pb.obs[:, 1].astype(np.int64))
    imu = pb.imu
    gr.add_poses(pb.T, pb.held, None if imu is None or not pb.held_may_tilt else imu.gravity_world)
    gr.add_points(ids, np.array([pb.points[int(i)] for i in ids]))
    gr.add_observations(pb.obs)
    gr.add_rotation_priors(pb.priors)
    gr.add_loops(pb.loops)
    if imu is not None:
        gr.add_imu(imu)
    values, iters, history = _optimize(gr, num.max_iterations, on_iteration, num.tol)
    T_new, pts_new, offset = _read(gr, values, len(pb.T), ids)
    out = _Solved(T_new, pts_new, offset, iters, history)
    check = num.offset_check_px
    if gr.est_offset and check is not None and abs(offset - pb.offset_px) >= check:
        # the offset's standard error (only where it could be applied: the marginal costs about one solve)
        try:
            cov = gr.g.Marginals(gr.graph, values).marginalCovariance(gr.C(0))
            out.offset_sigma_px = float(np.sqrt(cov[3, 3]))
        except RuntimeError as e:  # an indeterminate system (a point at the limit of its parallax):
            # Levenberg-Marquardt's damping solved it, the plain marginal cannot; the threshold decides
            log.info("disparity offset: no standard error (%s)", str(e).strip().splitlines()[0])
    if imu is not None:
        # the held pose tilted to agree with gravity: move the whole solution back onto it (a rigid
        # motion, which changes neither the path's shape nor any residual) so the world stays put
        A = pb.T[0] @ np.linalg.inv(T_new[0])
        out.T = np.einsum("ij,njk->nik", A, T_new)
        out.points = {i: A[:3, :3] @ x + A[:3, 3] for i, x in pts_new.items()}
        out.gravity_world = A[:3, :3] @ np.asarray(imu.gravity_world, float)  # where the solve put it
        biases = np.full((len(pb.T), 6), np.nan)
        for k in gr.imu_keys:
            biases[k] = values.atConstantBias(gr.B(k)).vector()
        out.imu_biases = biases
    return out


def bundle_adjust(rig: Rig, problem: BAProblem, config: BAConfig = BAConfig(),
                  priors: Sequence[RotationPrior] = (), on_iteration: Callable[[int], object] | None = None) -> BAResult:
    """Refine the problem's poses ``T_world_cam`` (K, 4, 4) and ``points`` {id: XYZ world} on its
    ``observations`` (N, 5|6), with its loops and IMU terms (see :class:`BAProblem`) and the rotation
    ``priors``.

    ``config.robust_px`` is the scale of the robust ``config.loss`` (pixels).  With
    ``config.outlier_rounds > 0`` the problem is solved, observations with a residual above
    ``config.outlier_px`` are dropped, and solved again (that many times).  ``on_iteration(1)`` is
    called after every LM iteration.  Loops (:class:`stereopath.host.backend.loops.Loop`, pose
    indices ``i``, ``j``) are added as relative-pose factors; with IMU terms
    (:class:`stereopath.host.backend.imu_factors.ImuTerms`) the biases come back in ``imu_biases``.
    """
    T, obs = check_problem(problem.T_world_cam, problem.observations, problem.points, MIN_POSES_PER_POINT)
    held = np.arange(len(T)) < max(problem.n_fixed, 0)
    loops, imu = list(problem.loops), problem.imu
    rms0 = rms_px(*reprojection_residuals(rig, T, problem.points, obs, problem.disparity_offset_px))
    offset = float(problem.disparity_offset_px)
    est = bool(config.disparity_offset) and bool(np.any(obs[:, 2] == 1))
    rounds = config.outlier_rounds
    num = _Numerics(config.loss, config.robust_px, config.max_iterations,
                    tol=RELATIVE_TOL_BEFORE_OUTLIERS if rounds else config.relative_tol,
                    offset_check_px=config.disparity_offset_min_px)
    pb = _Solve(T, problem.points, obs, held, list(priors), loops, imu, offset, est, problem.held_may_tilt)
    sol = _solve(rig, pb, num, on_iteration)
    num = dataclasses.replace(num, offset_check_px=None)  # the offset's standard error: after the first solve only
    iters, history = sol.iterations, sol.history
    resolve = num.tol != config.relative_tol  # the last solve stopped early: solve again unless a round does
    sigma = sol.offset_sigma_px or 0.0
    if est and abs(sol.offset_px - offset) < max(config.disparity_offset_min_px, OFFSET_SIGNIFICANCE * sigma):
        log.info("disparity offset %+.4f px (standard error %.4f px) below %.3f px or %g standard errors: not applied",
                 sol.offset_px - offset, sigma, config.disparity_offset_min_px, OFFSET_SIGNIFICANCE)
        est, resolve = False, True
    else:
        offset = sol.offset_px
    if imu is not None or loops or pb.priors:
        # the observations' noise as measured, so that they weigh against the IMU, loops and priors
        # as they should (it changes nothing in a problem of observations alone)
        n_unknowns = 3 * len(np.unique(obs[:, 1])) + 6 * int(np.sum(~held))
        num = dataclasses.replace(num, pixel_sigma=pixel_noise_px(
            *reprojection_residuals(rig, sol.T, sol.points, obs, offset), config.outlier_px, n_unknowns))
        log.info("bundle adjustment: pixel noise %.3f px (robust spread of the residuals)", num.pixel_sigma)
        resolve = resolve or rounds == 0
    for k in range(rounds):
        r, front = reprojection_residuals(rig, sol.T, sol.points, obs, offset)
        bad = ~front | (np.linalg.norm(r, axis=1) > config.outlier_px)
        keep = select_observations(obs[~bad], sol.points, MIN_POSES_PER_POINT)
        if not bad.any() or len(np.unique(keep[:, 1])) < 10:
            break
        obs = keep
        num = dataclasses.replace(num, tol=RELATIVE_TOL_BEFORE_OUTLIERS if k + 1 < rounds else config.relative_tol)
        sol = _next_solve(rig, pb, sol, obs, offset, est, num, on_iteration)
        offset = sol.offset_px if est else offset
        iters, history, resolve = iters + sol.iterations, history + sol.history, num.tol != config.relative_tol
    if resolve:  # no outlier round followed the first solve (or the offset was dropped after it)
        num = dataclasses.replace(num, tol=config.relative_tol)
        sol = _next_solve(rig, pb, sol, obs, offset, est, num, on_iteration)
        offset = sol.offset_px if est else offset
        iters, history = iters + sol.iterations, history + sol.history
    res = _result(rig, _Solved(sol.T, sol.points, offset, iters, history), obs, rms0, config.outlier_px)
    res.imu_biases = sol.imu_biases
    res.gravity_world = sol.gravity_world
    res.pixel_sigma_px = num.pixel_sigma if (imu is not None or loops or pb.priors) else None
    return res


def _next_solve(rig: Rig, pb: _Solve, last: _Solved, obs: np.ndarray, offset: float, est: bool, num: _Numerics,
                on_iteration: Callable[[int], object] | None) -> _Solved:
    """A further solve from the last one's poses and points, on ``obs`` with the offset as now settled."""
    nxt = dataclasses.replace(pb, T=last.T, points=last.points, obs=obs, offset_px=offset, estimate_offset=est)
    return _solve(rig, nxt, num, on_iteration)


# the smallest pixel noise assumed: sub-pixel matching is not more repeatable than this
MIN_PIXEL_SIGMA = 0.02


def pixel_noise_px(r: np.ndarray, front: np.ndarray, outlier_px: float, n_unknowns: int = 0) -> float:
    """The observations' pixel noise: 1.4826 median absolute deviation of the weighted residual
    components of the observations in front of their camera and within ``outlier_px``, scaled by
    ``sqrt(N / (N - n_unknowns))`` for the ``N`` components (the fit absorbs part of the noise);
    1 px when they are too few to tell (fewer than 10 beyond the unknowns), at least
    :data:`MIN_PIXEL_SIGMA`."""
    r = r[front & (np.linalg.norm(r, axis=1) <= outlier_px)].ravel()
    if len(r) - n_unknowns < 10:
        return 1.0
    mad = 1.4826 * np.median(np.abs(r - np.median(r)))
    return max(float(mad * np.sqrt(len(r) / (len(r) - n_unknowns))), MIN_PIXEL_SIGMA)


def _result(rig: Rig, sol: _Solved, obs: np.ndarray, rms0: float, outlier_px: float) -> BAResult:
    T, offset, history = sol.T, sol.offset_px, sol.history
    pts = {int(i): sol.points[int(i)] for i in np.unique(obs[:, 1].astype(np.int64))}
    r, front = reprojection_residuals(rig, T, pts, obs, offset)
    rn = np.linalg.norm(r[front], axis=1)
    rms1 = rms_px(r, front)
    log.info("bundle adjustment (GTSAM): %d poses, %d points, %d observations, rms %.3f -> %.3f px, %d iterations, "
             "disparity offset %+.3f px", len(T), len(pts), len(obs), rms0, rms1, sol.iterations, offset)
    return BAResult(T, pts, rms0, rms1, len(obs), len(pts), sol.iterations, history[0], history[-1],
                    float(np.mean(rn <= outlier_px)) if len(rn) else float("nan"), history, offset)


def odometry_factor(g: ModuleType, X: Callable[[int], int], k: int, T_k: np.ndarray, T_next: np.ndarray, sigma_per_m: float = 0.01,
                    rot_sigma_per_m: float = 0.005, min_sigma: float = 1e-4) -> gtsam.BetweenFactorPose3:
    """The relative pose between poses ``k`` and ``k + 1`` as measured (``T_k``, ``T_next``), with a
    standard deviation that grows with the distance between them (drift per metre, at least
    ``min_sigma``: m and rad)."""
    d = float(np.linalg.norm(T_next[:3, 3] - T_k[:3, 3]))
    return relative_factor(g, X, k, T_k, T_next, max(rot_sigma_per_m * d, min_sigma), max(sigma_per_m * d, min_sigma))


def relative_factor(g: ModuleType, X: Callable[[int], int], k: int, T_k: np.ndarray, T_next: np.ndarray,
                    sigma_rot: float, sigma_t: float) -> gtsam.BetweenFactorPose3:
    """The relative pose between poses ``k`` and ``k + 1`` as measured (``T_k``, ``T_next``), with the
    standard deviations ``sigma_rot`` (rad) and ``sigma_t`` (m)."""
    rel = np.linalg.inv(T_k) @ T_next
    sig = np.array([sigma_rot] * 3 + [sigma_t] * 3, float)
    return g.BetweenFactorPose3(X(k), X(k + 1), _pose(g, rel), g.noiseModel.Diagonal.Sigmas(sig))


def gauge_prior(g: ModuleType, X: Callable[[int], int], T: np.ndarray) -> gtsam.PriorFactorPose3:
    """The first pose held where it is (the pose graph's gauge)."""
    return g.PriorFactorPose3(X(0), _pose(g, T), g.noiseModel.Isotropic.Sigma(6, GAUGE_SIGMA))


def pose_graph_factors(g: ModuleType, X: Callable[[int], int], T: np.ndarray, loops: list[Loop], sigma_per_m: float = 0.01,
                       rot_sigma_per_m: float = 0.005, min_sigma: float = 1e-4,
                       edge_sigmas: np.ndarray | None = None) -> gtsam.NonlinearFactorGraph:
    """The pose graph of poses ``T``: the first held (:func:`gauge_prior`), consecutive ones tied by
    their relative motion (:func:`odometry_factor`; with ``edge_sigmas``, (K - 1, 2) rotation and
    translation deviations, a row given NaN keeps that model), and the verified ``loops``."""
    graph = g.NonlinearFactorGraph()
    graph.add(gauge_prior(g, X, T[0]))
    for k in range(len(T) - 1):
        if edge_sigmas is not None and np.all(np.isfinite(edge_sigmas[k])):
            graph.add(relative_factor(g, X, k, T[k], T[k + 1], float(edge_sigmas[k, 0]), float(edge_sigmas[k, 1])))
        else:
            graph.add(odometry_factor(g, X, k, T[k], T[k + 1], sigma_per_m, rot_sigma_per_m, min_sigma))
    add_loop_factors(g, graph, X, loops)
    return graph


def pose_graph(T_world_cam: np.ndarray, loops: list, odometry_sigma_per_m: float = 0.01,
               odometry_rot_sigma_per_m: float = 0.005, min_sigma: float = 1e-4, max_iterations: int = 50,
               tol: float | None = None, edge_sigmas: np.ndarray | None = None) -> np.ndarray:
    """Poses (K, 4, 4) re-estimated from their own relative motion and verified ``loops``.

    Consecutive poses are tied by their current relative pose with a standard deviation growing
    with the distance between them (:func:`odometry_factor`: a loop then spreads its correction over
    the path in proportion to the distance travelled), or as given per pair (``edge_sigmas``,
    :func:`pose_graph_factors`: in proportion to their variances); each loop adds its measured relative
    pose (:func:`add_loop_factors`); the first pose is held.  Solved in one batch (Levenberg-Marquardt,
    at most ``max_iterations``; ``tol``: its relative and absolute error tolerances, GTSAM's defaults
    when None);
    :class:`stereopath.host.backend.pose_graph.LivePoseGraph` is the same graph solved incrementally
    as poses and loops arrive."""
    T = np.asarray(T_world_cam, float)
    g = import_gtsam()
    values, X = g.Values(), g.symbol_shorthand.X
    for k, Tk in enumerate(T):
        values.insert(X(k), _pose(g, Tk))
    graph = pose_graph_factors(g, X, T, loops, odometry_sigma_per_m, odometry_rot_sigma_per_m, min_sigma, edge_sigmas)
    params = g.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    if tol is not None:
        params.setRelativeErrorTol(tol)
        params.setAbsoluteErrorTol(tol)
    out = g.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return np.array([out.atPose3(X(k)).matrix() for k in range(len(T))])
