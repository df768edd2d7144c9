"""Every keyframe's stereo keypoints in a file of the stage store, a few held in memory at a time.

The tracks stage computes keypoints and descriptors at every keyframe (several MB each), matches
each keyframe with the ones up to ``window`` keyframes later, and verifies loops between a few
keyframe pairs far apart.  Held all at once they grow with the scan; here each keyframe's keypoints
are written to ``OUT/stages/tracks.parts/<stage key>/`` as they are computed and read back when a
step needs them (the last :data:`HELD` stay in memory).  A tracks stage interrupted on a long
session finds the keyframes already computed there and starts from the last one; the folder is
removed when the stage is stored.  Descriptors that are whole numbers within 0-255 (SIFT's) are
written as bytes, exactly.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from pathlib import Path

import numpy as np

from stereopath.host.backend.tracks import KeyframeFeatures
from stereopath.host.reprocess.store import UNREADABLE, save_npz

log = logging.getLogger(__name__)

HELD = 48  # keyframes kept in memory: the matching window (20) and a batch after it


def _packed(a: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    d = a["desc"]
    if d.dtype == np.float32 and d.size and d.min() >= 0 and d.max() <= 255 and np.array_equal(d, np.round(d)):
        a = {**a, "desc": d.astype(np.uint8), "desc_float32": np.array(True)}
    return a


def _unpacked(a: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    if "desc_float32" in a:
        a = {k: v for k, v in a.items() if k != "desc_float32"}
        a["desc"] = a["desc"].astype(np.float32)
    return a


class KeyframeFeatureStore:
    """Keyframes' :class:`KeyframeFeatures` in order, as a read-only list (``len``, ``[k]``) that loads on
    demand; ``folder`` None keeps them all in memory (short runs, tests)."""

    def __init__(self, folder: Path | None, held: int = HELD) -> None:
        self.folder, self.held = folder, held
        if folder is not None:
            folder.mkdir(parents=True, exist_ok=True)
        self.frames: list[int] = []
        self.sizes: list[int] = []
        self._cache: OrderedDict[int, KeyframeFeatures] = OrderedDict()
        self._all: dict[int, KeyframeFeatures] = {}

    def _path(self, frame: int) -> Path:
        assert self.folder is not None
        return self.folder / f"kf_{frame:07d}.npz"

    def stored(self, frame: int) -> KeyframeFeatures | None:
        """Frame ``frame``'s keypoints when an earlier (interrupted) run stored them, else None."""
        if self.folder is None or not self._path(frame).is_file():
            return None
        try:
            with np.load(self._path(frame), allow_pickle=False) as z:
                return KeyframeFeatures.from_arrays(_unpacked({k: z[k] for k in z.files}))
        except UNREADABLE as exc:
            log.warning("%s unreadable (%s): recomputing", self._path(frame), exc)
            return None

    def features(self, frame: int, compute) -> KeyframeFeatures:
        """Frame ``frame``'s keypoints: stored by an earlier run, else ``compute(frame)`` (then stored)."""
        kf = self.stored(frame)
        if kf is None:
            kf = compute(frame)
            if self.folder is not None:
                save_npz(self._path(frame), **_packed(kf.to_arrays()))
        return kf

    def append(self, frame: int, kf: KeyframeFeatures) -> None:
        """Keyframe ``len(self)`` is frame ``frame`` with keypoints ``kf`` (already stored by :meth:`features`,
        or kept in memory without a folder)."""
        if self.folder is None:
            self._all[len(self.frames)] = kf
        self.frames.append(int(frame))
        self.sizes.append(len(kf))
        self._keep(len(self.frames) - 1, kf)

    def _keep(self, k: int, kf: KeyframeFeatures) -> None:
        if self.folder is None:
            return
        self._cache[k] = kf
        self._cache.move_to_end(k)
        while len(self._cache) > self.held:
            self._cache.popitem(last=False)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, k: int) -> KeyframeFeatures:
        if not -len(self) <= k < len(self):
            raise IndexError(k)
        k %= len(self)
        if self.folder is None:
            return self._all[k]
        kf = self._cache.get(k)
        if kf is None:
            kf = self.stored(self.frames[k])
            if kf is None:
                raise FileNotFoundError(self._path(self.frames[k]))
            self._keep(k, kf)
        else:
            self._cache.move_to_end(k)
        return kf

    def __iter__(self):
        return (self[k] for k in range(len(self)))

    def held_bytes(self) -> int:
        """Bytes of the keypoints held in memory now."""
        held = self._all.values() if self.folder is None else self._cache.values()
        return sum(sum(v.nbytes for v in kf.to_arrays().values()) for kf in held)
