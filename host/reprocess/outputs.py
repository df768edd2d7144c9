"""The outputs of ``host reprocess`` (always rewritten, each atomically): ``trajectory.tum``,
``report.json`` (the schema of :mod:`stereopath.host.evaluation.report` plus ``extra``: the
before/after figures of the on-board path, the re-estimate and the adjusted path, with errors
when there is ground truth), ``path.png``, ``errors.png``, the model files, ``report.html`` and,
when the bundle adjustment applied a disparity offset, ``rig_refined.yaml``
(:mod:`stereopath.host.reprocess.rig_refine`).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stereopath.device.errors import StereopathError
from stereopath.device.estimation.base import TrackStatus
from stereopath.device.formats.tum import Trajectory
from stereopath.host.reprocess.config import ReprocessPreset
from stereopath.host.reprocess.rig_refine import report_entry, write_refined_rig
from stereopath.host.reprocess.stage_map import MODEL_FILES
from stereopath.host.reprocess.store import copy_atomic, meta, plain

log = logging.getLogger(__name__)

STAGES = ("estimate", "tracks", "ba", "map")


@dataclass
class RunSummary:
    """What the outputs are made of (the stages' arrays and how each stage went)."""

    out: Path
    seq: Any
    est: dict[str, np.ndarray]
    ba: dict[str, np.ndarray]
    trk_stats: dict[str, Any]
    reest: Trajectory
    final: Trajectory
    onboard: Trajectory | None
    label: str
    preset_name: str
    preset: ReprocessPreset
    status: dict[str, str]
    stage_seconds: dict[str, float]
    map_stats: dict[str, Any] | None
    do_map: bool


def metrics(gt: Trajectory | None, traj: Trajectory | None) -> dict[str, Any] | None:
    """Frame count and (with ground truth) the report's error metrics of ``traj``."""
    from stereopath.host.evaluation.evaluate import evaluate
    from stereopath.host.evaluation.report import METRIC_KEYS

    if traj is None or len(traj) == 0:
        return None
    out: dict[str, Any] = {"frames": int(len(traj))}
    if gt is not None and len(gt) >= 3:
        from evo.core.geometry import GeometryException

        try:
            m = evaluate(gt, traj)
        except (StereopathError, GeometryException) as exc:  # e.g. too little motion to align
            log.warning("evaluation against the ground truth failed: %s", exc)
            m = None
        if m is not None:
            out.update({k: m.get(k) for k in METRIC_KEYS})
            out["n_associated"] = m.get("n_associated")
    return out


def _ratio(a: dict | None, b: dict | None) -> float | None:
    if not a or not b or a.get("ate_rmse_m") is None or not b.get("ate_rmse_m"):
        return None
    return float(a["ate_rmse_m"]) / float(b["ate_rmse_m"])


def end_to_start_error(gt: Trajectory | None, traj: Trajectory | None) -> float | None:
    """|end-to-start translation of ``traj`` - that of the ground truth at the same times| (m), or None."""
    from stereopath.device.core.geometry import invert_pose

    if gt is None or traj is None or len(gt) < 2 or len(traj) < 2:
        return None
    t_gt = np.asarray(gt.t_ns, np.int64)
    ends = []
    for t in (int(traj.t_ns[0]), int(traj.t_ns[-1])):
        k = int(np.argmin(np.abs(t_gt - t)))
        if abs(int(t_gt[k]) - t) > 5_000_000:  # no ground truth within 5 ms
            return None
        ends.append(np.asarray(gt.T_world_cam[k]))
    rel_gt = invert_pose(ends[0]) @ ends[1]
    rel = invert_pose(np.asarray(traj.T_world_cam[0])) @ np.asarray(traj.T_world_cam[-1])
    return float(np.linalg.norm(rel[:3, 3] - rel_gt[:3, 3]))


def loop_report(s: RunSummary) -> dict[str, Any]:
    """Accepted loops, the end-to-start gap of each path, and its error against the ground truth."""
    stats = meta(s.ba, "stats")
    gt, _ = groundtruth(s.seq)  # a bad optional ground truth never costs the results
    paths = {"onboard": s.onboard, "reestimated": s.reest, "bundle_adjusted": s.final}
    return {"accepted": stats.get("loops", []), "end_to_start": stats.get("end_to_start"),
            "end_to_start_error_m": {k: end_to_start_error(gt, v) for k, v in paths.items()}}


def groundtruth(seq: Any) -> tuple[Any, str | None]:
    """(ground truth or None, why it is unusable): a bad optional ground truth never costs the results."""
    try:
        return getattr(seq, "groundtruth", None), None
    except StereopathError as exc:
        return None, str(exc)


def build_report(s: RunSummary) -> dict[str, Any]:
    """The report.json content of a run."""
    from stereopath.host.evaluation.report import make_report

    gt, gt_error = groundtruth(s.seq)
    if gt_error is not None:
        log.warning("ground truth unusable, results written without errors against it: %s", gt_error)
    info = meta(s.est, "meta")
    m_final, m_reest = metrics(gt, s.final), metrics(gt, s.reest)
    m_onboard = metrics(gt, s.onboard) if s.onboard is not None and len(s.onboard) else None
    before_after = {"onboard": m_onboard, "reestimated": m_reest, "bundle_adjusted": m_final,
                    "ate_ratio_vs_onboard": _ratio(m_final, m_onboard),
                    "ate_ratio_vs_reestimated": _ratio(m_final, m_reest)}
    extra = {
        "before_after": before_after,
        "preset": {"name": s.preset_name, **plain(dataclasses.asdict(s.preset))},
        "estimate": {"estimator": info.get("estimator"), "stats": info.get("stats"),
                     "keyframes": int(np.sum(s.est["keyframe"]))},
        "tracks": s.trk_stats,
        "bundle_adjustment": meta(s.ba, "stats"),
        "loops": loop_report(s),
        "stages": {k: {"status": s.status.get(k, "skipped"), "seconds": s.stage_seconds.get(k, 0.0)} for k in STAGES},
        "map": s.map_stats,
        "rig_refined": report_entry(s.seq.rig, meta(s.ba, "stats")),  # None: no offset applied, no file
    }
    if gt_error is not None:
        extra["groundtruth_error"] = gt_error
    skipped = list(getattr(s.seq, "skipped_frames", None) or [])
    extra["frames_skipped"] = len(skipped)
    if skipped:
        extra["skipped_frame_indexes"] = skipped[:1000]
    return make_report(source=s.label, estimator="stereo+ba", frames=len(s.final),
                       frames_tracked=int(np.sum(s.est["status"] == TrackStatus.OK.code)),
                       metrics=m_final if m_final and m_final.get("ate_rmse_m") is not None else None,
                       frame_ms=s.est["frame_ms"], extra=extra,
                       world_frame=meta(s.ba, "stats").get("world_frame") or info.get("world_frame", "first_camera"))


def _plots(s: RunSummary, report: dict[str, Any]) -> list[str]:
    from stereopath.host.evaluation.plots import plot_path
    from stereopath.host.reprocess.report_html import plot_errors

    gt, _ = groundtruth(s.seq)
    m_final = report["extra"]["before_after"]["bundle_adjusted"]
    m_onboard = report["extra"]["before_after"]["onboard"]
    gt_usable = gt is not None and m_final is not None and m_final.get("ate_rmse_m") is not None
    plot_path(s.out / "path.png", gt if gt_usable else None, s.final, world_frame=report.get("world_frame"),
              title="reprocessed path (bundle adjusted)")
    files = ["path.png"]
    curves = {"re-estimated": s.reest, "bundle adjusted": s.final}
    if m_onboard and m_onboard.get("ate_rmse_m") is not None:
        curves = {"on-board": s.onboard, **curves}
    if gt_usable and plot_errors(s.out / "errors.png", gt, curves):
        files.append("errors.png")
    elif (s.out / "errors.png").exists():
        (s.out / "errors.png").unlink()  # from an earlier run with other inputs
    return files


def write_outputs(s: RunSummary) -> tuple[dict[str, Any], list[str]]:
    """Write every output of a run into ``s.out``; returns (report, file names)."""
    from stereopath.device.formats.tum import write_tum
    from stereopath.host.evaluation.report import write_report
    from stereopath.host.reprocess.report_html import write_html_report

    report = build_report(s)
    s.out.mkdir(parents=True, exist_ok=True)
    write_tum(s.out / "trajectory.tum", s.final)
    write_report(s.out / "report.json", report)
    files = ["trajectory.tum", "report.json", *_plots(s, report)]
    files += write_refined_rig(s.out, s.seq.rig, report["extra"]["rig_refined"], s.label)
    if s.do_map and s.status.get("map") != "failed" and (s.out / "stages" / "map").is_dir():
        for f in MODEL_FILES:
            src = s.out / "stages" / "map" / f
            if src.is_file():
                copy_atomic(src, s.out / f)
                files.append(f)
    write_html_report(s.out / "report.html", report, [f for f in ("path.png", "errors.png", "model.png") if f in files])
    files.append("report.html")
    return report, files
