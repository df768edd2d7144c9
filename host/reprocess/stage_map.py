"""Stage ``map``: the dense model with the refined path (:func:`stereopath.host.mapping.mapper.map_sequence`).

``run(config, inputs)``: ``config`` the mapper's settings (``map_preset(name)``, or ``"auto"``: the
preset chosen from the keyframes' stereo depth, recorded in map.json); ``inputs.extra``
holds ``trajectory`` (the refined path), ``dst`` (the stage folder, rewritten) and ``label``.
Outputs: the files :data:`MODEL_FILES` in ``dst``.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

from stereopath.host.reprocess.config import StageInputs

if TYPE_CHECKING:
    from stereopath.host.mapping.mapper import MapConfig

NAME = "map"
MODEL_FILES = ("mesh.ply", "cloud.ply", "model.png", "map.json")


def settings(config: MapConfig | str) -> dict[str, Any]:
    """What the stage's key hashes: the depth settings in their recorded (``map.json``) form, constants included."""
    if isinstance(config, str):
        return {"preset": config}
    return {**dataclasses.asdict(config), "depth": config.depth.record()}


def table_blocks(blocks: int, initial_blocks: int) -> int:
    """The blocks the volume's hash table holds room for once ``blocks`` are in use: Open3D's
    ``VoxelBlockGrid`` starts with ``initial_blocks`` and doubles its table when it fills, every slot
    allocated (and resident) whether used or not, the old table and the new one both held while it
    grows."""
    cap = max(int(initial_blocks), 1)
    while cap < blocks:
        cap *= 2
    return cap


def run(config: MapConfig | str, inputs: StageInputs) -> list[str]:
    from stereopath.host.mapping.fusion import FusionConfig
    from stereopath.host.mapping.mapper import map_sequence

    dst = Path(inputs.extra["dst"])
    if dst.exists():
        shutil.rmtree(dst)
    from stereopath.host.mapping import map_progress

    # the volume stored every CHUNK_KEYFRAMES keyframes: an interrupted stage goes on from there
    checkpoint = (map_progress.MapCheckpoint(inputs.parts, map_progress.CHUNK_KEYFRAMES)
                  if inputs.parts is not None else None)
    result = map_sequence(inputs.seq, inputs.extra["trajectory"], dst, config, progress=inputs.progress,
                          source=inputs.extra["label"], checkpoint=checkpoint)
    fusion = result.stats["config"]["fusion"]
    voxel_bytes = FusionConfig(**fusion).voxel_bytes
    block_bytes = fusion["block_resolution"] ** 3 * voxel_bytes
    inputs.memory.note("tsdf_volume", result.stats["blocks"] * block_bytes)
    inputs.memory.note("tsdf_table", table_blocks(result.stats["blocks"], fusion["initial_blocks"]) * block_bytes)
    return [f for f in MODEL_FILES if (dst / f).is_file()]


def read_stats(dst: Path) -> dict[str, Any] | None:
    """The model's ``map.json`` (None when missing or unreadable)."""
    try:
        return json.loads((Path(dst) / "map.json").read_text())
    except (OSError, json.JSONDecodeError):
        return None
