"""Run an estimator over a sequence and write ``trajectory.tum``, ``report.json``, ``path.png``.

CPU accounting: :func:`estimate_sequence` measures the process CPU time of the frame loop (all
threads: the estimator, its keyframe worker, OpenCV and BLAS) and, of it, the CPU time the reading
thread spends producing the frames (reading and decoding recorded images, or rendering simulated
ones: what a live camera does not cost the device), and each frame's CPU time.  The report gives them
per frame (``extra.cpu_ms_per_frame``: ``frame_loop``, ``live_frames`` the loop without producing the
frames, ``live_median`` and ``live_p95`` over the frames).
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from stereopath.device.estimation.base import EstimateRun, run_estimator
from stereopath.host.evaluation.baselines import make_estimator
from stereopath.device.formats.tum import Trajectory, write_tum
from stereopath.host.progress import Bar

log = logging.getLogger(__name__)


def optional_groundtruth(seq) -> tuple[Trajectory | None, str | None]:
    """(the sequence's ground truth or None, why it is unusable): a bad optional ground truth only drops
    the errors against it (the estimate and its outputs are written all the same)."""
    from stereopath.device.errors import StereopathError

    try:
        return getattr(seq, "groundtruth", None), None
    except StereopathError as exc:
        return None, str(exc)


def _frames(seq, limit: int | None):
    it = seq.frames()
    return it if limit is None else itertools.islice(it, limit)


class _CpuMeter:
    """Wraps the frame iterator: CPU time of this thread producing the frames, and the process CPU time
    (all threads) between one frame handed out and the next asked for, minus producing it: what each
    frame cost the estimator and its workers."""

    def __init__(self) -> None:
        self.reading_s = 0.0
        self.per_frame_s: list[float] = []

    def frames(self, frames: Iterable) -> Iterator:
        it = iter(frames)
        handed = None
        while True:
            p0, t0 = time.process_time(), time.thread_time()
            if handed is not None:
                self.per_frame_s.append(p0 - handed)
            try:
                frame = next(it)
            except StopIteration:
                return
            finally:
                self.reading_s += time.thread_time() - t0
            handed = time.process_time()
            yield frame


def estimate_sequence(seq, estimator: str = "stereo", preset: str | None = None, max_frames: int | None = None,
                      options: dict[str, Any] | None = None, progress: bool = True) -> EstimateRun:
    if callable(getattr(seq, "frame", None)):  # refuse exchanged left/right images before running
        from stereopath.device.core.stereo_order import check_sequence_order

        check_sequence_order(seq)
    if estimator == "sfm":  # its step lengths come from the ground truth: an unusable one stops it
        gt = getattr(seq, "groundtruth", None)
    else:  # a hint only (the simulator's first pose); a bad one is reported with the results
        gt, _ = optional_groundtruth(seq)
    est = make_estimator(estimator, seq.rig, preset=preset, groundtruth=gt, options=options)
    total = len(seq) if max_frames is None else min(len(seq), max_frames)
    meter = _CpuMeter()
    cpu0 = time.process_time()
    with Bar(total, f"{estimator} odometry", None if progress else False, unit="frame") as tick:
        run = run_estimator(est, meter.frames(_frames(seq, max_frames)), getattr(seq, "imu", None), progress=tick)
    run.extra["cpu_s"] = {"frame_loop": time.process_time() - cpu0, "reading_frames": meter.reading_s,
                          "per_frame": meter.per_frame_s}
    return run


def cpu_ms_per_frame(run: EstimateRun) -> dict[str, float] | None:
    """CPU ms per frame: ``frame_loop`` (the loop's mean), ``live_frames`` (its mean without producing the
    frames), and ``live_median`` / ``live_p95`` over the frames (each frame's process CPU from its hand-over
    to the next frame's request, all threads); None for a run :func:`estimate_sequence` did not measure."""
    import numpy as np

    cpu = run.extra.get("cpu_s")
    n = len(run.frame_ms)
    if not cpu or not n:
        return None
    per = np.asarray(cpu.get("per_frame") or [np.nan], float) * 1e3
    return {"frame_loop": 1e3 * cpu["frame_loop"] / n,
            "live_frames": 1e3 * (cpu["frame_loop"] - cpu["reading_frames"]) / n,
            "live_median": float(np.median(per)), "live_p95": float(np.percentile(per, 95))}


def report_for(run: EstimateRun, seq, source_label: str) -> tuple[dict, Trajectory | None]:
    from stereopath.host.evaluation.evaluate import evaluate
    from stereopath.host.evaluation.report import make_report

    gt, gt_error = optional_groundtruth(seq)
    if gt_error is not None:
        log.warning("ground truth unusable, results written without errors against it: %s", gt_error)
    metrics = evaluate(gt, run.trajectory) if gt is not None else None
    report = make_report(
        source=source_label, estimator=run.estimator, frames=int(run.extra.get("frames_in", len(run.estimates))),
        frames_tracked=run.frames_tracked, metrics=metrics, frame_ms=run.frame_ms,
        world_frame=run.world_frame,
    )
    report.setdefault("extra", {}).update({"estimator_stats": {k: v for k, v in run.extra.items() if k != "cpu_s"}})
    skipped = list(getattr(seq, "skipped_frames", None) or [])
    report["extra"]["frames_skipped"] = len(skipped)
    cpu = cpu_ms_per_frame(run)
    if cpu is not None:
        report["extra"]["cpu_ms_per_frame"] = cpu
    if gt_error is not None:
        report["extra"]["groundtruth_error"] = gt_error
    if skipped:
        report["extra"]["skipped_frame_indexes"] = skipped[:1000]
    return report, gt


def write_outputs(out_dir: str | Path, run: EstimateRun, seq, source_label: str) -> dict:
    from stereopath.host.evaluation.plots import plot_path
    from stereopath.host.evaluation.report import write_report

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.tum", run.trajectory)
    report, gt = report_for(run, seq, source_label)
    write_report(out / "report.json", report)
    plot_path(out / "path.png", gt, run.trajectory)
    return report
