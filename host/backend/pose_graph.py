"""The live map's pose graph, solved incrementally (GTSAM's iSAM2) as keyframes and loops arrive.

One pose per keyframe, tied to the previous one by the on-board relative motion (a drift-per-metre
uncertainty, :func:`stereopath.host.backend.gtsam_ba.odometry_factor`) and to earlier keyframes by
every verified loop (a robust relative-pose factor).  iSAM2 keeps the factorisation and re-eliminates
only the part of the Bayes tree a new factor touches; after a loop the update is repeated until the
poses move by less than ``tol_m`` / ``tol_rad``, and a pose is relinearised once its change passes
:data:`RELINEARIZE`, so the solution stays within a few tenths of a millimetre of the optimum
(``tests/backend/test_pose_graph.py``; ``benchmarks/bench_live_loops.py`` compares it with the batch).
Forgetting a keyframe (:meth:`LivePoseGraph.rebuild`) rebuilds the graph.  Pure computation: no I/O.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from stereopath.host.backend.loops import Loop

log = logging.getLogger(__name__)

RELINEARIZE = 3e-5
WILDFIRE = 3e-7


class LivePoseGraph:
    """Keyframe poses in arrival order, with loops, re-estimated incrementally."""

    def __init__(self, max_updates: int = 20, tol_m: float = 1e-5, tol_rad: float = 1e-5) -> None:
        from stereopath.host.backend.gtsam_ba import import_gtsam

        self.g = import_gtsam()
        self.X = self.g.symbol_shorthand.X
        self.max_updates, self.tol_m, self.tol_rad = max_updates, tol_m, tol_rad
        self.onboard: list[np.ndarray] = []
        self.loops: list[Loop] = []
        self._reset()

    def _reset(self) -> None:
        params = self.g.ISAM2Params()
        # a pose is relinearised once its change passes this (rad and m), and a change smaller than
        # the wildfire threshold stops spreading through the tree: both far below what the map shows
        params.setRelinearizeThreshold(RELINEARIZE)
        params.relinearizeSkip = 1
        gn = self.g.ISAM2GaussNewtonParams()
        gn.setWildfireThreshold(WILDFIRE)
        params.setOptimizationParams(gn)
        self.isam = self.g.ISAM2(params)
        self._poses = np.zeros((0, 4, 4))

    def __len__(self) -> int:
        return len(self.onboard)

    def poses(self) -> np.ndarray:
        """(K, 4, 4) the current estimate of every keyframe's pose (the on-board poses until a loop)."""
        return self._poses.copy()

    def add(self, T_world_cam: np.ndarray) -> None:
        """One more keyframe, tied to the previous one by the on-board relative motion; it starts
        where that motion puts it from the previous keyframe's current estimate (which is where
        the graph's optimum puts it too: nothing else constrains it yet)."""
        from stereopath.host.backend.gtsam_ba import gauge_prior, odometry_factor

        g, X = self.g, self.X
        T = np.asarray(T_world_cam, float)
        k = len(self.onboard)
        graph, values = g.NonlinearFactorGraph(), g.Values()
        if k == 0:
            start = T
            graph.add(gauge_prior(g, X, T))
        else:
            start = self._poses[-1] @ np.linalg.inv(self.onboard[-1]) @ T
            graph.add(odometry_factor(g, X, k - 1, self.onboard[-1], T))
        values.insert(X(k), g.Pose3(g.Rot3.ClosestTo(start[:3, :3]), start[:3, 3]))
        self.isam.update(graph, values)
        self.onboard.append(T)
        self._poses = np.concatenate([self._poses, start[None]])

    def add_loop(self, loop: Loop) -> None:
        """A verified loop between keyframes ``loop.i`` and ``loop.j`` (both already added); every
        pose is re-estimated."""
        from stereopath.host.backend.gtsam_ba import add_loop_factors

        graph = self.g.NonlinearFactorGraph()
        add_loop_factors(self.g, graph, self.X, [loop])
        self.loops.append(loop)
        self.isam.update(graph, self.g.Values())
        self._settle()

    def rebase(self, T_new_old: np.ndarray, moved: np.ndarray) -> None:
        """The world redefined (a device's world rebase): the keyframes flagged ``moved`` were given in the
        earlier world and are mapped by the rigid motion ``T_new_old``, on-board poses and current
        estimates alike; the loops (relative poses) stay as they are."""
        A = np.asarray(T_new_old, float)
        moved = np.asarray(moved, bool)
        if len(moved) != len(self.onboard):
            raise ValueError(f"rebase: {len(moved)} flags for {len(self.onboard)} keyframes")
        onboard = [A @ T if m else T for T, m in zip(self.onboard, moved)]
        if len(self._poses) >= len(moved):
            self._poses = self._poses.copy()
            self._poses[:len(moved)][moved] = A @ self._poses[:len(moved)][moved]
        self.rebuild(np.array(onboard).reshape(-1, 4, 4), self.loops)

    def rebuild(self, T_world_cam: np.ndarray, loops: list) -> None:
        """Start again from these keyframe poses and loops (after a keyframe was taken back): the
        whole graph in one update, started from the current estimate (the on-board poses when no
        loop is left, which is then the solution)."""
        from stereopath.host.backend.gtsam_ba import pose_graph_factors

        g, X = self.g, self.X
        onboard = [np.asarray(T, float) for T in T_world_cam]
        n = len(onboard)
        start = self._poses[:n] if loops and len(self._poses) >= n else np.array(onboard).reshape(-1, 4, 4)
        self.onboard, self.loops = onboard, list(loops)
        self._reset()
        if not onboard:
            return
        graph, values = pose_graph_factors(g, X, np.array(onboard), self.loops), g.Values()
        for k, T in enumerate(start):
            values.insert(X(k), g.Pose3(g.Rot3.ClosestTo(T[:3, :3]), T[:3, 3]))
        self.isam.update(graph, values)
        self._poses = np.array(start)
        if self.loops:
            self._settle()

    def _settle(self) -> None:
        """More iSAM2 updates until no pose moves by more than the tolerances (or ``max_updates``)."""
        prev = self._estimate()
        for _ in range(self.max_updates):
            self.isam.update()
            cur = self._estimate()
            moved = np.max(np.linalg.norm(cur[:, :3, 3] - prev[:, :3, 3], axis=1))
            turned = np.max(np.linalg.norm(cur[:, :3, :3] - prev[:, :3, :3], axis=(1, 2)))  # ~ sqrt(2) x angle
            prev = cur
            if moved <= self.tol_m and turned <= self.tol_rad:
                break
        else:
            log.warning("live pose graph: still moving after %d iSAM2 updates", self.max_updates)
        self._poses = prev

    def _estimate(self) -> np.ndarray:
        """(K, 4, 4) iSAM2's current estimate (the graph holds poses only, keyed in keyframe order)."""
        rows = np.asarray(self.g.utilities.extractPose3(self.isam.calculateEstimate()))  # R row-major, then t
        T = np.tile(np.eye(4), (len(rows), 1, 1))
        T[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
        T[:, :3, 3] = rows[:, 9:]
        return T
