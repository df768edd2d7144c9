"""The dense model's stored progress: the volume and the mapper's lists every so many keyframes.

An interrupted ``map`` stage goes on from the last stored chunk: ``chunk-<k>/`` in the stage's parts
folder holds the TSDF volume (:meth:`~stereopath.host.mapping.fusion.TsdfVolume.store`) and
``mapper.json`` (written last: a chunk without it is incomplete and ignored) with the keyframes fused
before keyframe ``k``.  The volume is written from the hash map's own buffers, so storing it costs no
memory; only the newest chunk is kept.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from stereopath.device.errors import StereopathError
from stereopath.device.formats.fileio import write_text_atomic
from stereopath.host.mapping.fusion import TsdfVolume

log = logging.getLogger(__name__)

CHUNK_KEYFRAMES = 200  # keyframes fused between two stored chunks


class DenseMapper(Protocol):
    """What is stored of :class:`stereopath.host.mapping.mapper.DenseMapper`."""

    volume: TsdfVolume
    poses: list[np.ndarray]
    indices: list[int]
    valid_fractions: list[float]
    timings: dict[str, float]

    def reset(self) -> None: ...


@dataclass
class MapCheckpoint:
    """Chunks of a map build in ``parts`` (see the module doc), one every ``every`` keyframes."""

    parts: Path
    every: int = CHUNK_KEYFRAMES

    def due(self, fused: int) -> bool:
        return fused > 0 and fused % self.every == 0

    def save(self, mapper: DenseMapper, next_k: int, skipped: list[str]) -> None:
        """Store ``mapper`` (the keyframes before ``next_k`` fused, ``skipped`` the unreadable ones)."""
        folder = Path(self.parts) / f"chunk-{next_k:06d}"
        shutil.rmtree(folder, ignore_errors=True)
        mapper.volume.store(folder)
        write_text_atomic(folder / "mapper.json", json.dumps({
            "next_keyframe": next_k, "poses": np.asarray(mapper.poses).tolist(), "indices": mapper.indices,
            "valid_fractions": mapper.valid_fractions, "timings": mapper.timings, "skipped": skipped}))
        for old in Path(self.parts).glob("chunk-*"):
            if old != folder:
                shutil.rmtree(old, ignore_errors=True)
        log.debug("map: progress stored before keyframe %d", next_k)

    def load(self, mapper: DenseMapper) -> tuple[int, list[str]] | None:
        """Restore the newest complete chunk into ``mapper`` (a new one): ``(next keyframe, skipped)``, or
        None when there is none or it cannot be read (logged; the build starts from the first keyframe)."""
        chunks = sorted(p for p in Path(self.parts).glob("chunk-*") if (p / "mapper.json").is_file())
        if not chunks:
            return None
        folder = chunks[-1]
        try:
            state = json.loads((folder / "mapper.json").read_text())
            mapper.volume.restore(folder)
            poses = [np.asarray(T, float).reshape(4, 4) for T in state["poses"]]
            mapper.poses, mapper.indices = poses, [int(i) for i in state["indices"]]
            mapper.valid_fractions = [float(f) for f in state["valid_fractions"]]
            mapper.timings.update({k: float(v) for k, v in state["timings"].items()})
            next_k, skipped = int(state["next_keyframe"]), [str(s) for s in state["skipped"]]
        except (OSError, ValueError, KeyError, TypeError, StereopathError) as exc:
            log.warning("%s not usable (%s): the model is built from the first keyframe", folder, exc)
            mapper.reset()
            return None
        log.info("map: resuming at keyframe %d from the stored volume (%d blocks)", next_k, mapper.volume.block_count)
        return next_k, skipped
