"""The dense model's stored progress: the volume and the mapper's lists every so many keyframes.

An interrupted ``map`` stage goes on from the last stored chunk: ``chunk-<k>/`` in the stage's parts
folder holds the TSDF volume (:meth:`~stereopath.host.mapping.fusion.TsdfVolume.store`) and
``mapper.json`` (:meth:`~stereopath.host.mapping.mapper.DenseMapper.progress`) with the keyframes
fused before keyframe ``k``.  A chunk is written into a temporary folder and renamed when complete;
the volume is written from the hash map's own buffers a slice at a time, so storing it costs no
memory; only the newest chunk is kept.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from stereopath.host.mapping.fusion import TsdfVolume

log = logging.getLogger(__name__)

CHUNK_KEYFRAMES = 200  # keyframes fused between two stored chunks
_TMP = ".tmp"


class DenseMapper(Protocol):
    """What is stored of :class:`stereopath.host.mapping.mapper.DenseMapper` (its own methods do it)."""

    @property
    def volume(self) -> TsdfVolume: ...

    @property
    def poses(self) -> list[np.ndarray]: ...

    def progress(self) -> dict[str, Any]: ...

    def resume(self, volume_folder: Path, state: dict[str, Any]) -> None: ...

    def reset(self) -> None: ...


@dataclass
class MapCheckpoint:
    """Chunks of a map build in ``parts`` (see the module doc), one every ``every`` keyframes."""

    parts: Path
    every: int = CHUNK_KEYFRAMES

    def save(self, mapper: DenseMapper, next_k: int, skipped: list[str]) -> None:
        """Store ``mapper`` (the keyframes before ``next_k`` fused, ``skipped`` the unreadable ones)."""
        folder = Path(self.parts) / f"chunk-{next_k:06d}"
        tmp = folder.with_name(folder.name + _TMP)
        shutil.rmtree(tmp, ignore_errors=True)
        mapper.volume.store(tmp)
        (tmp / "mapper.json").write_text(json.dumps({"next_keyframe": next_k, "skipped": skipped,
                                                     **mapper.progress()}))
        shutil.rmtree(folder, ignore_errors=True)
        tmp.rename(folder)
        for old in Path(self.parts).glob("chunk-*"):
            if old != folder:
                shutil.rmtree(old, ignore_errors=True)
        log.debug("map: progress stored before keyframe %d", next_k)

    def load(self, mapper: DenseMapper) -> tuple[int, list[str]] | None:
        """Restore the newest chunk into ``mapper`` (a new one): ``(next keyframe, skipped)``, or None when
        there is none or it cannot be used (logged; the build starts from the first keyframe)."""
        chunks = sorted(p for p in Path(self.parts).glob("chunk-*") if not p.name.endswith(_TMP))
        if not chunks:
            return None
        folder = chunks[-1]
        try:
            state = json.loads((folder / "mapper.json").read_text())
            mapper.resume(folder, state)
            next_k, skipped = int(state["next_keyframe"]), [str(s) for s in state["skipped"]]
            if not 0 < len(mapper.poses) <= next_k:
                raise ValueError(f"{len(mapper.poses)} keyframes fused before keyframe {next_k}")
        except Exception as exc:  # noqa: BLE001 - any unusable chunk means: start again from the first keyframe
            log.warning("%s not usable (%s): the model is built from the first keyframe", folder, exc)
            mapper.reset()
            return None
        log.info("map: resuming at keyframe %d from the stored volume (%d blocks)", next_k, mapper.volume.block_count)
        return next_k, skipped
