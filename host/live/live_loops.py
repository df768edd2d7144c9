"""Loop closure while scanning (``host live --map``): keyframes re-posed when the path comes back.

Each keyframe that reaches the live map gets stereo keypoints (plain SIFT, original view only:
a few tenths of a second) and its on-board pose.  The new keyframe is checked against the earlier
ones close to it in space (on the current, corrected path) and far enough back in the sequence,
with the offline back end's verification (:func:`stereopath.host.reprocess.loops.verify_pair`:
PnP RANSAC on stereo points, consistent scale, agreement with the path within its possible
drift; a repeated texture elsewhere is rejected).  An accepted loop re-estimates every keyframe
pose on GTSAM (:func:`stereopath.host.reprocess.gtsam_ba.pose_graph`: the on-board relative
motion between consecutive keyframes, with a drift-per-metre uncertainty, plus every loop so
far), so the loop's correction is spread along the path.  Later keyframes are moved by the last
keyframe's correction.  The caller re-poses its fused keyframes
(:meth:`stereopath.host.mapping.mapper.DenseMapper.repose`).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from stereopath.device.core.rig import Rig

log = logging.getLogger(__name__)


class LiveLoopCloser:
    """Loop detection and pose-graph correction over one session's keyframes, in arrival order."""

    def __init__(self, rig: Rig, loops: Any = None, features: Any = None) -> None:
        from stereopath.host.reprocess.loops import LoopConfig
        from stereopath.host.reprocess.tracks import TrackConfig

        self.rig = rig
        self.cfg = loops or LoopConfig()
        self.track_cfg = features or TrackConfig(feature_preset="fast_asym", original_view_only=True, max_features=2000)
        self.onboard: list[np.ndarray] = []  # the poses as they arrived
        self.feats: list[Any] = []
        self.loops: list[Any] = []
        self._corrected: np.ndarray | None = None  # pose-graph poses of the keyframes up to the last loop

    def __len__(self) -> int:
        return len(self.onboard)

    def poses(self) -> np.ndarray:
        """The current best pose of every keyframe (on-board poses until the first loop)."""
        T = np.array(self.onboard)
        c = self._corrected
        if c is None:
            return T
        n = len(c)
        out = T.copy()
        out[:n] = c
        if len(T) > n:  # keyframes after the last loop: moved with the last corrected one
            out[n:] = np.einsum("ij,njk->nik", c[-1] @ np.linalg.inv(T[n - 1]), T[n:])
        return out

    def add(self, left: np.ndarray, right: np.ndarray, T_world_cam: np.ndarray) -> bool:
        """Take one keyframe; True when it closed a loop (every pose of :meth:`poses` may have moved)."""
        from stereopath.host.reprocess.gtsam_ba import pose_graph
        from stereopath.host.reprocess.tracks import stereo_features

        feats = stereo_features(self.rig, left, right, self.track_cfg)
        self.onboard.append(np.asarray(T_world_cam, float))
        self.feats.append(feats)
        try:
            loop = self._check(len(self.onboard) - 1) if self.cfg.enabled else None
            corrected = None if loop is None else pose_graph(np.array(self.onboard), self.loops + [loop])
        except Exception:
            self.onboard.pop()  # a keyframe that could not be taken leaves no trace
            self.feats.pop()
            raise
        if loop is None:
            return False
        self.loops.append(loop)
        self._corrected = corrected
        log.info("live loop closed: keyframes %d-%d (%d inliers, correction %.1f mm); %d keyframes re-posed",
                 loop.i, loop.j, loop.inliers, 1000 * loop.correction_m, len(self.onboard))
        return True

    def discard_last(self) -> None:
        """Forget the last keyframe (it could not be fused) and any loop it closed."""
        from stereopath.host.reprocess.gtsam_ba import pose_graph

        j = len(self.onboard) - 1
        if j < 0:
            return
        self.onboard.pop()
        self.feats.pop()
        if self.loops and self.loops[-1].j == j:
            self.loops.pop()
            self._corrected = pose_graph(np.array(self.onboard), self.loops) if self.loops else None
        elif self._corrected is not None and len(self._corrected) > len(self.onboard):
            self._corrected = self._corrected[: len(self.onboard)]

    def _check(self, j: int):
        """The best verified loop between keyframe ``j`` and an earlier keyframe, or None."""
        from stereopath.host.reprocess.loops import descriptor_matches, candidate_pairs, verify_pair

        T = self.poses()
        pairs = [i for i, jj in candidate_pairs(T, self.cfg) if jj == j]
        if not pairs:
            return None
        C = T[:, :3, 3]
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(C, axis=0), axis=1))])
        scored = sorted(((descriptor_matches(self.feats[i], self.feats[j]), i) for i in pairs), key=lambda mi: -len(mi[0]))
        for m, i in scored[:self.cfg.candidates_per_keyframe]:
            loop, why = verify_pair(self.rig, self.feats[i], self.feats[j], T[i], T[j], along[j] - along[i], self.cfg,
                                    i, j, m)
            log.debug("live loop candidate %d-%d: %s", i, j, why)
            if loop is not None:
                return loop
        return None
