"""The stereo calibration refined by reprocessing, for the device: ``OUT/rig_refined.yaml``.

The bundle adjustment (:mod:`stereopath.host.backend.gtsam_ba`) can estimate one constant disparity
error of the pair as a shift of the right camera's principal point (``cx1 + offset``).  When it applied
such an offset, the session's rig with ``cam1.cx`` moved by it is written; given to the device for the
next sessions of the same rig (``source.rig_file``), the on-board estimator triangulates with it.  A
positive offset means the measured disparities were too small (points too far, the path too long).  A
rig of pinhole views of fisheye lenses (``Rig.views_of``) keeps its camchain on the device: the refined
rig is then for ``--rig`` of ``host live`` / ``host map``, and the report says so.
See docs/reprocess.md, "Refined rig".
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

from stereopath.device.core.rig import Rig, make_camera, make_rig

log = logging.getLogger(__name__)

RIG_REFINED_FILE = "rig_refined.yaml"


def applied_offset(ba_stats: dict[str, Any]) -> float | None:
    """The disparity offset (px) the bundle adjustment applied, or None (not estimated, below the
    threshold, or no adjustment): ``bundle_adjust`` reports exactly 0 when it did not apply one."""
    off = ba_stats.get("disparity_offset_px")
    if off is None or not math.isfinite(float(off)) or float(off) == 0.0:
        return None
    return float(off)


def refined_rig(rig: Rig, offset_px: float) -> Rig:
    """``rig`` with the right camera's principal point ``cx`` moved by ``offset_px`` (everything else kept)."""
    K1 = rig.cam1.K.copy()
    K1[0, 2] += float(offset_px)
    cam1 = make_camera("cam1", K1, rig.cam1.dist, rig.cam1.size)
    return make_rig(rig.cam0, cam1, rig.R, rig.T, name=rig.name, T_body_cam0=rig.T_body_cam0, views_of=rig.views_of)


def use_of(rig: Rig) -> str:
    """Where the refined rig goes: the device's rig file, or only the host's (a fisheye box's views)."""
    if rig.views_of:
        return (f"--rig of host live / host map; not the device's source.rig_file: its cameras are pinhole views "
                f"of the fisheye calibration {rig.views_of}, which the device keeps")
    return "device configuration source.rig_file (or --rig of host live / host map) for later sessions of the same rig"


def report_entry(rig: Rig, ba_stats: dict[str, Any]) -> dict[str, Any] | None:
    """The ``rig_refined`` entry of report.json: None when no offset was applied (no file is written)."""
    off = applied_offset(ba_stats)
    if off is None:
        return None
    return {"file": RIG_REFINED_FILE, "disparity_offset_px": off,
            "cam1_cx_px": {"before": rig.cam1.cx, "after": rig.cam1.cx + off},
            "use": use_of(rig)}


def comment(rig: Rig, offset_px: float, session: str) -> str:
    """The header of ``rig_refined.yaml``: where it comes from, the shift and what it means."""
    sense = "too small (points too far, path too long)" if offset_px > 0 else "too large (points too near, path too short)"
    return (f"stereopath rig refined by `stereopath host reprocess` of session {session}\n"
            f"right camera principal point cx moved by {offset_px:+.4f} px ({rig.cam1.cx:.4f} -> "
            f"{rig.cam1.cx + offset_px:.4f}):\n"
            f"the bundle adjustment found the pair's measured disparities {abs(offset_px):.4f} px {sense};\n"
            f"with this rig the device's estimator triangulates them corrected.\n"
            f"use: {use_of(rig)}")


def write_refined_rig(out: Path, rig: Rig, entry: dict[str, Any] | None, session: str) -> list[str]:
    """Write ``out/rig_refined.yaml`` for a report entry (or remove an earlier run's); the file names written."""
    from stereopath.device.formats.rig_files import save_rig_yaml

    path = Path(out) / RIG_REFINED_FILE
    if entry is None:
        if path.exists():
            path.unlink()  # from an earlier run that applied an offset
        log.debug("no disparity offset applied: no %s", RIG_REFINED_FILE)
        return []
    off = float(entry["disparity_offset_px"])
    save_rig_yaml(refined_rig(rig, off), path, comment=comment(rig, off, session))
    log.info("refined stereo calibration (right cx %+.3f px, the disparity offset the bundle adjustment applied) "
             "written to %s: use: %s", off, path, use_of(rig))
    return [RIG_REFINED_FILE]
