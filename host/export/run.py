"""``stereopath host export``: open the result, check the output folder, write the format into a
temporary folder and rename it into place (:mod:`stereopath.host.export.outdir`)."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

from stereopath.device.errors import ConfigError

log = logging.getLogger(__name__)

FORMATS = ("colmap", "nerfstudio", "mcap")
SUMMARY = "export.json"


def export_result(result: str | Path, out: str | Path, fmt: str, force: bool = False, progress: bool | None = None,
                  session: str | Path | None = None, text: bool = False, ros2: bool = False) -> dict[str, Any]:
    """Export ``result`` (see :func:`stereopath.host.export.result.open_result`) as ``fmt`` into ``out``.

    ``out`` must be empty or missing (``force`` replaces it); nothing is left behind on failure.
    ``text``: a COLMAP model as text; ``ros2``: an MCAP export as a ROS 2 bag in ROS 2 message types.
    Returns the summary also written to ``OUT/export.json``."""
    from stereopath.host.export.outdir import check_export_out, staged_folder
    from stereopath.host.export.result import open_result

    if fmt not in FORMATS:
        raise ConfigError(f"--format {fmt!r}: known formats are {', '.join(FORMATS)}")
    if ros2 and fmt != "mcap":
        raise ConfigError(f"--ros2 goes with --format mcap, not {fmt}")
    if text and fmt != "colmap":
        raise ConfigError(f"--text goes with --format colmap, not {fmt}")
    inputs = [result] + ([session] if session is not None else [])
    check_export_out(out, force, inputs=inputs)
    t0 = time.perf_counter()
    src = open_result(result, session=session)
    log.info("exporting %s (%s: %d poses, %d keyframes, %d points) as %s", result, src.kind, len(src.t_ns),
             len(src.keyframes), len(src.point_ids), fmt)
    with staged_folder(out) as tmp:
        if fmt == "colmap":
            from stereopath.host.export.colmap import export_colmap

            counts = export_colmap(src, tmp, progress, text=text)
        elif fmt == "nerfstudio":
            from stereopath.host.export.nerfstudio import export_nerfstudio

            counts = export_nerfstudio(src, tmp, progress)
        elif ros2:
            from stereopath.host.export.ros2_bag import export_ros2

            counts = export_ros2(src, tmp, progress)
        else:
            from stereopath.host.export.mcap_export import export_mcap

            counts = export_mcap(src, tmp, progress)
        summary = {"format": fmt + ("+ros2" if ros2 else ""), "source": str(result), "source_kind": src.kind, "world_frame": src.world_frame,
                   **counts, "ba_rms_px": src.ba_stats.get("rms_after_px"),
                   "seconds": round(time.perf_counter() - t0, 3)}
        (tmp / SUMMARY).write_text(json.dumps(summary, indent=2) + "\n")
    return summary
