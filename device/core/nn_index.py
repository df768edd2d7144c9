"""Nearest-neighbour search over descriptors: brute force (exact) or a FLANN KD-tree (approximate).

Pure compute; used by :mod:`stereopath.device.core.matching`.
"""

from __future__ import annotations

from typing import Protocol

import cv2
import numpy as np


class NNParams(Protocol):
    """What :class:`NNIndex` reads from a configuration (``matching.MatchConfig``)."""

    method: str
    bf_max_pairs: int
    k: int
    flann_trees: int
    flann_checks: int


class NNIndex:
    """Nearest-neighbour search over fixed reference descriptors (brute force or FLANN KD-tree).

    ``auto`` picks brute force (exact) while ``expected_queries * len(ref) <=
    cfg.bf_max_pairs`` and a FLANN KD-tree (approximate, built once) otherwise.
    """

    def __init__(self, ref: np.ndarray, cfg: NNParams, expected_queries: int = 0) -> None:
        self.ref = np.ascontiguousarray(ref, np.float32)
        self.cfg = cfg
        m = len(self.ref)
        method = cfg.method
        if method == "auto":
            method = "bf" if expected_queries * m <= cfg.bf_max_pairs else "flann"
        self.method = method if m >= 2 * cfg.k else "bf"
        if self.method == "flann":
            cv2.setRNGSeed(0)  # the randomised KD-trees are built the same way every time
        self._flann = cv2.flann_Index(self.ref, dict(algorithm=1, trees=cfg.flann_trees)) if self.method == "flann" else None

    def query(self, query: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(index (n, k) int64, distance (n, k) float32)``, sorted by distance; missing -> (0, inf)."""
        q = np.ascontiguousarray(query, np.float32)
        n, m = len(q), len(self.ref)
        k = int(min(k, m))
        if n == 0 or k == 0:
            return np.zeros((n, k), np.int64), np.zeros((n, k), np.float32)
        if self._flann is not None:
            idx, d2 = self._flann.knnSearch(q, k, params=dict(checks=self.cfg.flann_checks))
            idx = np.asarray(idx, np.int64).reshape(n, k)
            dist = np.sqrt(np.maximum(np.asarray(d2, np.float32).reshape(n, k), 0.0))
            bad = (idx < 0) | (idx >= m)
        else:
            dist, idx = cv2.batchDistance(q, self.ref, cv2.CV_32F, normType=cv2.NORM_L2, K=k)
            idx = np.asarray(idx, np.int64).reshape(n, k)
            dist = np.asarray(dist, np.float32).reshape(n, k)
            bad = idx < 0  # batchDistance marks missing neighbours with -1
        if bad.any():
            idx = np.where(bad, 0, idx)
            dist = np.where(bad, np.inf, dist).astype(np.float32)
        return idx, dist
