"""Resuming inside a stage of `stereopath host reprocess`: the estimate's stored chunks and the map's
stored volume (the stage-level resume is in test_reprocess.py)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from stereopath.host.reprocess.pipeline import RunChoices, reprocess_session
from tests.host.test_reprocess import FRAMES, session  # noqa: F401  (the same 60-frame session fixture)


class _StopAfterEstimate(Exception):
    pass


def _stop_after_estimate(name: str) -> None:
    if name == "estimate":
        raise _StopAfterEstimate


def test_estimate_interrupted_resumes_from_its_last_stored_chunk(session, tmp_path, monkeypatch):
    """The estimate stage stores the estimator and its results every CHUNK_FRAMES frames (made small
    here); a run stopped between two chunks goes on from the last one and writes the estimate an
    uninterrupted run writes (keyframe work in line: the same order of events in both runs)."""
    import dataclasses

    from stereopath.device.estimation import stereo_vo
    from stereopath.host.reprocess import estimate_progress, stage_estimate
    from stereopath.host.reprocess.config import resolve_preset

    monkeypatch.setattr(stage_estimate, "CHUNK_FRAMES", 20)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # the progress files' key
    _, preset = resolve_preset("standard")
    opts = preset.estimator_options
    preset = dataclasses.replace(preset, estimator_options=dataclasses.replace(
        opts, keyframes=dataclasses.replace(opts.keyframes, background=False)))
    only_estimate = RunChoices(do_map=False, progress=False, after_stage=_stop_after_estimate)
    whole = tmp_path / "whole"
    with pytest.raises(_StopAfterEstimate):
        reprocess_session(session, whole, preset=preset, run=only_estimate)
    process, calls = stereo_vo.StereoEstimator.process, []

    def stopping(self, frame, imu):
        calls.append(frame.seq)
        if len(calls) == 45:
            raise KeyboardInterrupt
        return process(self, frame, imu)

    monkeypatch.setattr(stereo_vo.StereoEstimator, "process", stopping)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        reprocess_session(session, out, preset=preset, run=only_estimate)
    stored = list((out / "stages" / "estimate.parts").rglob(estimate_progress.FILE))
    assert len(stored) == 1
    assert not (out / "stages" / "estimate.npz").exists()
    calls.clear()
    with pytest.raises(_StopAfterEstimate):
        reprocess_session(session, out, preset=preset, run=only_estimate)
    assert calls[0] == 40 and len(calls) == FRAMES - 40
    assert not (out / "stages" / "estimate.parts").exists()  # stored whole: its partial results are gone
    a, b = np.load(whole / "stages" / "estimate.npz"), np.load(out / "stages" / "estimate.npz")
    for key in ("t_ns", "seq", "T_world_cam", "status", "keyframe"):
        assert np.array_equal(a[key], b[key]), key


def test_estimate_progress_of_another_build_or_cut_short_is_not_used(tmp_path, caplog, monkeypatch):
    from stereopath.device.estimation.base import EstimateProgress
    from stereopath.device.estimation.registry import make_estimator
    from stereopath.device.core.rig import paper_rig
    from stereopath.host.reprocess.estimate_progress import EstimateCheckpoint

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    store = EstimateCheckpoint(tmp_path / "parts")
    assert store.load() is None  # nothing stored
    est = make_estimator("stereo", paper_rig())
    store.save(est, EstimateProgress(next_seq=7, prev_t=123))
    assert (tmp_path / "cache" / "stereopath" / "progress.key").stat().st_mode & 0o777 == 0o600
    loaded = store.load()
    assert loaded is not None and loaded[1].next_seq == 7 and loaded[1].prev_t == 123
    loaded[0].close()
    est.close()
    data = store.path.read_bytes()
    store.path.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))  # altered: its HMAC no longer matches
    with caplog.at_level(logging.WARNING):
        assert store.load() is None
    assert "altered" in caplog.text
    caplog.clear()
    store.path.write_bytes(data[:50])  # cut short
    with caplog.at_level(logging.WARNING):
        assert store.load() is None
    assert "not usable" in caplog.text and "first frame" in caplog.text
    import pickle

    store.path.write_bytes(pickle.dumps((None, EstimateProgress())))
    store.sidecar.write_text(json.dumps({"format": 2, "code": "another build", "python": [3, 11], "hmac": ""}))
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert store.load() is None
    assert "another version" in caplog.text


def test_map_stage_interrupted_resumes_from_its_stored_volume(session, tmp_path, monkeypatch):
    """The map stage stores its volume every CHUNK_KEYFRAMES keyframes (made small here) in
    ``map.parts``; the next run fuses only the keyframes after the stored ones, and the stage's parts
    are gone once it is stored."""
    from stereopath.host.mapping import fusion, map_progress, mapper

    monkeypatch.setattr(map_progress, "CHUNK_KEYFRAMES", 2)
    monkeypatch.setattr(mapper, "DEPTH_BATCH", 2)
    integrate, calls = fusion.TsdfVolume.integrate_depth_map, []

    def stopping(self, dm, T):
        calls.append(1)
        if len(calls) == 5 and stop:
            raise KeyboardInterrupt
        return integrate(self, dm, T)

    monkeypatch.setattr(fusion.TsdfVolume, "integrate_depth_map", stopping)
    out = tmp_path / "out"
    run, stop = RunChoices(progress=False, map_preset="object"), [True]
    with pytest.raises(KeyboardInterrupt):
        reprocess_session(session, out, run=run)
    chunks = list((out / "stages" / "map.parts").rglob("chunk-*"))
    assert [c.name for c in chunks] == ["chunk-000004"] and (chunks[0] / "mapper.json").is_file()
    calls.clear()
    stop.clear()
    res = reprocess_session(session, out, run=run)
    n = json.loads((out / "map.json").read_text())["keyframes"]
    assert res.stages["map"] == "computed" and len(calls) == n - 4
    assert not (out / "stages" / "map.parts").exists()
