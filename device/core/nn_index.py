"""Nearest-neighbour search over descriptors: brute force (exact) or a FLANN KD-tree (approximate).

Pure compute; used by :mod:`stereopath.device.core.matching`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from stereopath.device.core.config import check_ranges, ranged


@dataclass(frozen=True)
class NNConfig:
    """How nearest neighbours are searched (``[index]`` of ``matching.MatchConfig``)."""

    method: Literal["auto", "bf", "flann"] = "auto"
    bf_max_pairs: int = ranged(4_000_000, 0, 10**12)  # auto: brute force while n_queries * n_ref <= this
    flann_trees: int = ranged(2, 1, 32)
    flann_checks: int = ranged(16, 1, 100_000)  # leaves visited per query: nearly all the matches of 32 at half the time

    def __post_init__(self) -> None:
        check_ranges(self, "index.")


class NNIndex:
    """Nearest-neighbour search over fixed reference descriptors (brute force or FLANN KD-tree).

    ``auto`` picks brute force (exact) while ``expected_queries * len(ref) <=
    cfg.bf_max_pairs`` and a FLANN KD-tree (approximate, built once) otherwise; brute force
    also when ``ref`` has fewer than ``2 * k`` rows (``k``: the neighbours the caller searches).
    """

    def __init__(self, ref: np.ndarray, cfg: NNConfig, k: int, expected_queries: int = 0) -> None:
        self.ref = np.ascontiguousarray(ref, np.float32)
        self.cfg = cfg
        m = len(self.ref)
        method = cfg.method
        if method == "auto":
            method = "bf" if expected_queries * m <= cfg.bf_max_pairs else "flann"
        self.method = method if m >= 2 * k else "bf"
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
