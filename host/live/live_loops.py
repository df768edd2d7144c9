"""Loop closure while scanning (``host live --map``): keyframes re-posed when the path comes back.

Each keyframe gets stereo SIFT keypoints and its on-board pose, and is checked against earlier keyframes
near it on the corrected path and far enough back, with the offline verification
(:func:`stereopath.host.backend.loops.verify_pair`).  The keyframe poses live in a pose graph solved
incrementally (:class:`stereopath.host.backend.pose_graph.LivePoseGraph`): the on-board relative
motion with a drift-per-metre uncertainty, plus every loop; an accepted loop spreads its correction
along the path, and later keyframes follow the last corrected one by their on-board motion.  The caller
re-poses its fused keyframes (:meth:`stereopath.host.mapping.mapper.DenseMapper.repose`).
See docs/architecture.md, "A keyframe on the host".
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np

from stereopath.device.core.rig import Rig
from stereopath.host.backend.pose_graph import LivePoseGraph

if TYPE_CHECKING:
    from stereopath.host.backend.loops import LoopConfig
    from stereopath.host.backend.tracks import TrackConfig

log = logging.getLogger(__name__)


class LiveLoopCloser:
    """Loop detection and pose-graph correction over one session's keyframes, in arrival order."""

    def __init__(self, rig: Rig, loops: LoopConfig | None = None, features: TrackConfig | None = None) -> None:
        from stereopath.host.backend.loops import LoopConfig
        from stereopath.host.backend.tracks import TrackConfig

        self.rig = rig
        self.cfg = loops or LoopConfig()
        self.track_cfg = features or TrackConfig(feature_preset="fast_asym", original_view_only=True, max_features=2000)
        self.feats: list[Any] = []
        self.graph = LivePoseGraph()

    @property
    def onboard(self) -> list[np.ndarray]:
        """The keyframe poses as they arrived."""
        return self.graph.onboard

    @property
    def loops(self) -> list[Any]:
        """The loops accepted so far."""
        return self.graph.loops

    def __len__(self) -> int:
        return len(self.graph)

    def poses(self) -> np.ndarray:
        """The current best pose of every keyframe (on-board poses until the first loop)."""
        return self.graph.poses()

    def add(self, left: np.ndarray, right: np.ndarray, T_world_cam: np.ndarray) -> bool:
        """Take one keyframe; True when it closed a loop (every pose of :meth:`poses` may have moved)."""
        from stereopath.host.backend.tracks import stereo_features

        feats = stereo_features(self.rig, left, right, self.track_cfg)
        self.feats.append(feats)
        try:
            self.graph.add(T_world_cam)
            loop = self._check(len(self.graph) - 1) if self.cfg.enabled else None
            if loop is not None:
                self.graph.add_loop(loop)
        except Exception:
            self._forget_last()  # a keyframe that could not be taken leaves no trace
            raise
        if loop is None:
            return False
        log.info("live loop closed: keyframes %d-%d (%d inliers, correction %.1f mm); %d keyframes re-posed",
                 loop.i, loop.j, loop.inliers, 1000 * loop.correction_m, len(self.graph))
        return True

    def rebase(self, T_new_old: np.ndarray, moved: np.ndarray) -> None:
        """The session's world redefined: the keyframes flagged ``moved`` (sent before the rebase) map by
        ``T_new_old`` (:meth:`LivePoseGraph.rebase`)."""
        self.graph.rebase(T_new_old, moved)

    def discard_last(self) -> None:
        """Forget the last keyframe (it could not be fused) and any loop it closed."""
        if len(self.graph):
            self._forget_last()

    def _forget_last(self) -> None:
        j = len(self.feats) - 1
        self.feats.pop()
        keep = [lp for lp in self.graph.loops if lp.j < j]
        self.graph.rebuild(self.graph.onboard[:j], keep)

    def _check(self, j: int):
        """A verified loop between keyframe ``j`` and an earlier keyframe (the nearest that verifies), or None."""
        from stereopath.host.backend.loops import candidate_pairs, path_lengths, verified_in_order

        T = self.poses()
        pairs = [i for i, jj in candidate_pairs(T, self.cfg) if jj == j]
        C = T[:, :3, 3]
        pairs.sort(key=lambda i: float(np.linalg.norm(C[i] - C[j])))  # the nearest first, as offline
        tried = [(i, j) for i in pairs[:self.cfg.nearest_checked]]
        loops = verified_in_order(self.rig, self.feats, T, path_lengths(T), tried, self.cfg, 1)
        return loops[0] if loops else None
