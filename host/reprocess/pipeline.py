"""Offline reprocessing of a recorded session: re-estimate, bundle adjust, map, report.

Stages, one module each (``run(config, inputs) -> outputs``): ``estimate``, ``tracks``, ``ba``, ``map``
(:mod:`~stereopath.host.reprocess.stage_estimate` and its neighbours).  Every result is written
atomically into ``OUT/stages/`` and recorded in ``OUT/stages/manifest.json`` with a key (a hash of its
inputs and settings); a rerun reuses every stage whose key and files are still there.  Then the outputs
(:mod:`~stereopath.host.reprocess.outputs`): ``trajectory.tum``, ``report.json``, ``path.png``,
``errors.png``, the model files and ``report.html``.  Ctrl-C leaves only finished stages behind (files
appear by rename when complete, the manifest is updated after them).
See docs/architecture.md, "Reprocessing", and docs/reprocess.md.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from stereopath.device.errors import DatasetError, StereopathError
from stereopath.device.formats.tum import Trajectory
from stereopath.host.backend.parallel import local_spreader, spread_with
from stereopath.host.reprocess import stage_ba, stage_estimate, stage_map, stage_tracks
from stereopath.host.reprocess.config import (  # noqa: F401  (re-exported: the public names)
    DEFAULT_PRESET,
    REPROCESS_PRESETS,
    ReprocessPreset,
    StageInputs,
    resolve_preset,
)
from stereopath.host.reprocess.memory import MemoryLedger, process_cpu_s, reuse_freed_heap
from stereopath.host.reprocess.outputs import STAGES, RunSummary, write_outputs
from stereopath.host.reprocess.stage_ba import gyro_rotation_priors  # noqa: F401  (re-exported)
from stereopath.host.reprocess.stage_map import MODEL_FILES  # noqa: F401  (re-exported)
from stereopath.host.reprocess.store import (  # noqa: F401  (re-exported)
    PIPELINE_VERSION,
    StageStore,
    load_npz,
    save_npz,
    sequence_fingerprint,
    stage_key,
    stored_stats,
)

if TYPE_CHECKING:
    from stereopath.host.mapping.mapper import MapConfig

log = logging.getLogger(__name__)

_ARRAY_STAGES = {"estimate": stage_estimate, "tracks": stage_tracks, "ba": stage_ba}
_DEPENDS = {"estimate": (), "tracks": ("estimate",), "ba": ("estimate", "tracks")}


@dataclass
class ReprocessResult:
    out_dir: Path
    report: dict[str, Any]
    trajectory: Trajectory
    stages: dict[str, str]  # stage -> "computed" | "reused" | "skipped" | "failed"
    seconds: dict[str, float]
    files: list[str]


def _one_blas_thread() -> AbstractContextManager[object]:
    """A context with every BLAS (NumPy's, SciPy's and OpenCV's OpenBLAS) limited to one thread."""
    import cv2  # noqa: F401 - each library brings its own BLAS, which must be loaded to be limited
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


class _Runner:
    """Runs or reuses the stages of one reprocessing (keys, stored arrays, status)."""

    def __init__(self, seq: Any, stages_dir: Path, config: ReprocessPreset, force: bool,
                 progress: bool | None, after_stage: Callable[[str], None] | None) -> None:
        self.seq, self.dir, self.config, self.force = seq, stages_dir, config, force
        reuse_freed_heap()
        # what the stages after the estimate read: the right images in the left camera's grey levels
        self.matched = seq
        if config.match_exposure:
            from stereopath.host.reprocess.exposure import ExposureMatchedSequence

            self.matched = ExposureMatchedSequence(seq, config.tracks, config.exposure_tolerance)
        self.progress, self.after_stage = progress, after_stage
        self.store = StageStore(stages_dir)
        self.memory = MemoryLedger()
        self.status: dict[str, str] = {}
        self.cache: dict[str, dict[str, np.ndarray]] = {}
        self.keys: dict[str, str] = {}
        self.settings: dict[str, Any] = {}
        upstream = sequence_fingerprint(seq)
        for name, mod in _ARRAY_STAGES.items():
            self.settings[name] = mod.settings(config)
            self.keys[name] = stage_key(name, PIPELINE_VERSION, upstream, self.settings[name])
            upstream = self.keys[name]

    def run_stage(self, name: str, files: list[str], compute: Callable[[], Any]) -> Any:
        self.store.forget(name)
        self.memory.start()
        t0, c0 = time.perf_counter(), process_cpu_s()
        # one BLAS thread: a multi-threaded BLAS sums long dot products in an order that depends on
        # its thread count, so the adjusted poses would change in the last bits from a 2-core
        # laptop to a 16-core one or a Ray worker (OMP_NUM_THREADS=1); pinned, they do not
        with _one_blas_thread():
            result = compute()
        self.store.finish(name, self.keys[name], files, time.perf_counter() - t0, self.settings.get(name),
                          self.memory.summary(), process_cpu_s() - c0, self.memory.cpu_steps)
        shutil.rmtree(self.parts_dir(name), ignore_errors=True)  # the stage's partial results: stored whole now
        self.status[name] = "computed"
        log.info("stage %s: computed in %.1f s", name, time.perf_counter() - t0)
        if self.after_stage is not None:
            self.after_stage(name)
        return result

    def parts_dir(self, name: str) -> Path:
        """The folder of a stage's partial results (``OUT/stages/<stage>.parts``; one subfolder per key)."""
        return self.dir / f"{name}.parts"

    def reusable(self, name: str) -> bool:
        return not self.force and self.store.done(name, self.keys[name]) and self.status.get(name) != "computed"

    def get(self, name: str, need_data: bool = True) -> dict[str, np.ndarray]:
        """The stage's arrays: stored ones when finished with the same key, else computed now."""
        if name in self.cache:
            return self.cache[name]
        path = self.dir / f"{name}.npz"
        if self.reusable(name):
            if not need_data:
                self.status.setdefault(name, "reused")
                return {}
            data = load_npz(path)
            if data is not None:
                self.status[name] = "reused"
                self.cache[name] = data
                return data

        def compute() -> dict[str, np.ndarray]:
            if self.force:  # --force: nothing of an earlier run is read back, partial results neither
                shutil.rmtree(self.parts_dir(name), ignore_errors=True)
            inputs = StageInputs(self.seq if name == "estimate" else self.matched, self.progress,
                                 {d: self.get(d) for d in _DEPENDS[name]}, memory=self.memory,
                                 parts=self.parts_dir(name) / self.keys[name])
            data = _ARRAY_STAGES[name].run(self.config, inputs)
            save_npz(path, **data)
            return data

        self.cache[name] = self.run_stage(name, [path.name], compute)
        return self.cache[name]

    def map(self, map_cfg: MapConfig | str, final: Trajectory, label: str) -> dict[str, Any] | None:
        """Run or reuse the map stage; its map.json statistics (or the error)."""
        self.settings["map"] = stage_map.settings(map_cfg)
        self.keys["map"] = stage_key("map", PIPELINE_VERSION, self.keys["ba"], self.settings["map"])
        dst = self.dir / "map"
        if not self.force and self.store.done("map", self.keys["map"]):
            self.status["map"] = "reused"
        else:
            if self.force:
                shutil.rmtree(self.parts_dir("map"), ignore_errors=True)
            inputs = StageInputs(self.matched, self.progress, extra={"dst": dst, "trajectory": final, "label": label},
                                 memory=self.memory, parts=self.parts_dir("map") / self.keys["map"])
            spreader = local_spreader()  # the keyframes' depth maps side by side (none inside a fleet task)
            try:
                with spread_with(spreader) if spreader is not None else nullcontext():
                    self.run_stage("map", [f"map/{f}" for f in MODEL_FILES], lambda: stage_map.run(map_cfg, inputs))
            except StereopathError as exc:  # e.g. no valid depth with this map preset: keep the path outputs
                log.warning("dense model failed: %s", exc)
                self.status["map"] = "failed"
                return {"error": str(exc)}
        return stage_map.read_stats(dst)


@dataclass(frozen=True)
class RunChoices:
    """How one reprocessing run goes: the command line's choices, the same for any input."""

    do_map: bool = True             # build the dense model (the map stage)
    map_preset: str = "auto"        # the model's preset (``auto``: chosen from the scene)
    force: bool = False             # recompute every stage instead of reusing stored ones
    progress: bool | None = None    # progress bars (None: when the output is a terminal)
    imu_priors: bool = False        # gyro rotation priors between consecutive keyframes in the adjustment
    after_stage: Callable[[str], None] | None = None  # called with a stage's name once it is stored


def reprocess_sequence(seq: Any, out_dir: str | Path, preset: str | ReprocessPreset = DEFAULT_PRESET,
                       run: RunChoices = RunChoices(), onboard: Trajectory | None = None,
                       source_label: str | None = None) -> ReprocessResult:
    """Run the stages on any sequence (``rig``, ``t_ns``, ``frame(i)``, ``frames()``, ``imu``,
    ``groundtruth``) and write the outputs into ``out_dir`` (see the module doc).

    ``onboard``: the path estimated on the device (for the before/after figures).  ``run.force``
    recomputes every stage.  ``run.imu_priors`` adds gyro rotation priors between consecutive
    keyframes to the bundle adjustment (sequences with an IMU and ``rig.T_body_cam0``).
    ``run.after_stage(name)`` is called after each stage is stored (a hook for tests and progress).
    """
    do_map, map_preset = run.do_map, run.map_preset
    preset_name, P = resolve_preset(preset)
    if run.imu_priors:
        P = dataclasses.replace(P, imu_rotation_priors=True)
        preset_name += "+imu"
    map_cfg = None
    if do_map:
        from stereopath.host.mapping.mapper import AUTO, map_preset as _map_preset

        map_cfg = AUTO if map_preset == AUTO else _map_preset(map_preset)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise StereopathError(f"output {out} exists and is not a folder")
    stages_dir = out / "stages"
    stages_dir.mkdir(parents=True, exist_ok=True)
    runner = _Runner(seq, stages_dir, P, run.force, run.progress, run.after_stage)
    label = source_label or str(getattr(seq, "spec", "")) or "sequence"

    est = runner.get("estimate")
    runner.get("tracks", need_data=False)
    ba = runner.get("ba")
    trk_stats = (json.loads(str(runner.cache["tracks"]["stats"])) if "tracks" in runner.cache
                 else stored_stats(stages_dir / "tracks.npz"))
    final = Trajectory(est["t_ns"], ba["T_frames"])
    runner.cache.pop("tracks", None)  # the model needs only the path: the tracks are not held while it is built
    map_stats = None
    if map_cfg is not None:
        map_stats = runner.map(map_cfg, final, label)
    else:
        runner.status["map"] = "skipped"
    summary = RunSummary(out=out, seq=seq, est=est, ba=ba, trk_stats=trk_stats,
                         reest=Trajectory(est["t_ns"], est["T_world_cam"]), final=final, onboard=onboard,
                         label=label, preset_name=preset_name, preset=P, status=runner.status,
                         stage_seconds={s: runner.store.seconds(s) for s in STAGES}, map_stats=map_stats,
                         do_map=do_map)
    _, files = write_outputs(summary)
    report = json.loads((out / "report.json").read_text())
    return ReprocessResult(out, report, final, runner.status, summary.stage_seconds, files)


def open_session_checked(session_dir: str | Path) -> Any:
    """Open a recorded session for reprocessing; :class:`StereopathError` subclasses on bad input."""
    from stereopath.device.formats import open_source

    d = Path(session_dir)
    if not d.exists():
        raise DatasetError(f"session folder not found: {d}")
    if d.is_dir() and not any(d.iterdir()):
        raise DatasetError(f"{d}: the session folder is empty")
    seq = open_source(f"session:{d}")
    if len(seq) < 2:
        raise DatasetError(f"{d}: {len(seq)} stereo frame(s); reprocessing needs at least two")
    return seq


def reprocess_session(session_dir: str | Path, out_dir: str | Path, preset: str | ReprocessPreset = DEFAULT_PRESET,
                      run: RunChoices = RunChoices(), strict: bool = False) -> ReprocessResult:
    """``stereopath host reprocess``: a recorded session folder -> ``out_dir`` (see the module doc).

    The input is checked before anything is written: a missing or empty folder, a folder that is
    not a session, missing calibration, fewer than two frames, or an ``out_dir`` that is the
    session folder itself or cannot be written raise a
    :class:`stereopath.device.errors.StereopathError` and leave ``out_dir`` untouched.
    """
    from stereopath.device.formats.fileio import check_out_folder

    check_out_folder(out_dir, option="output folder", inputs=[session_dir], not_a_session=True)  # never over the recording
    seq = open_session_checked(session_dir)
    from stereopath.device.core.stereo_order import check_sequence_order

    check_sequence_order(seq)  # exchanged left/right images: say so before any stage runs
    seq.strict = strict  # False: unreadable frames are skipped and counted (report extra.frames_skipped)
    try:
        onboard = getattr(seq, "trajectory", None)
    except DatasetError as exc:  # only the before figures need it: the images are what is reprocessed
        log.warning("on-board path not used (no before/after figures): %s", exc)
        onboard = None
    return reprocess_sequence(seq, out_dir, preset=preset, run=run, onboard=onboard, source_label=str(session_dir))
