"""Reprocessing a session whose right camera records darker than its left (two cameras, two AGCs):
the offline stages read the right images in the left camera's grey levels."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from stereopath.device.errors import ConfigError, DatasetError
from stereopath.device.formats.sequence import SequenceBase
from stereopath.device.formats.source import open_source
from stereopath.host.reprocess.config import REPROCESS_PRESETS
from stereopath.host.reprocess.exposure import ExposureMatchedSequence, probe_relation
from stereopath.host.reprocess.pipeline import RunChoices, reprocess_session
from stereopath.host.backend.tracks import TrackConfig

GAIN, OFFSET = 0.75, -12.0  # the right camera: right = 0.75 * left - 12, so left = 1.333 * right + 16


def _lut(gain: float, offset: float) -> np.ndarray:
    return np.clip(np.rint(gain * np.arange(256) + offset), 0, 255).astype(np.uint8)


class _Darker(SequenceBase):
    """A simulated sequence whose right images went through ``lut``; frames in ``broken`` are unreadable."""

    def __init__(self, inner, lut: np.ndarray | None, broken: tuple[int, ...] = ()) -> None:
        super().__init__(inner.rig, inner.t_ns)
        self.inner, self.lut, self.broken, self.name = inner, lut, broken, "darker"
        self.loads = 0

    def _load(self, i: int):
        self.loads += 1
        if i in self.broken:
            raise DatasetError(f"frame {i}: truncated PNG")
        fr = self.inner.frame(i)
        return fr if self.lut is None else dataclasses.replace(fr, right=cv2.LUT(fr.right, self.lut))


@pytest.fixture(scope="module")
def sim():
    return open_source("sim:1", frames=30)


def test_a_darker_right_camera_is_measured_and_corrected(sim):
    seq = ExposureMatchedSequence(_Darker(sim, _lut(GAIN, OFFSET)), TrackConfig())
    rel = seq.relation(12)
    assert rel is not None
    assert rel.gain == pytest.approx(1 / GAIN, abs=0.06) and rel.offset == pytest.approx(-OFFSET / GAIN, abs=3.0)
    fixed, truth = seq.frame(12).right.astype(int), sim.frame(12).right.astype(int)
    raw = cv2.LUT(sim.frame(12).right, _lut(GAIN, OFFSET)).astype(int)
    assert np.median(np.abs(fixed - truth)) <= 2 < np.median(np.abs(raw - truth))
    s = seq.summary(np.arange(0, 30, 3))
    assert s["frames"] == s["measured"] == s["corrected"] == 10 and s["change"] > 20


def test_matched_cameras_are_read_as_recorded(sim):
    seq = ExposureMatchedSequence(sim, TrackConfig())
    assert seq.measured(7) is not None and seq.relation(7) is None
    assert seq.frame(7).right is not None and np.array_equal(seq.frame(7).right, sim.frame(7).right)
    assert seq.summary(np.arange(30))["corrected"] == 0
    # the wrapper shares the sequence's state
    assert seq.rig is sim.rig and seq.t_ns is sim.t_ns and seq.groundtruth is sim.groundtruth and len(seq) == 30
    seq.strict = True
    assert sim.strict is True
    sim.strict = False


def test_an_unreadable_frame_costs_its_fit_and_is_skipped_as_before(sim):
    inner = _Darker(sim, _lut(GAIN, OFFSET), broken=(10,))
    seq = ExposureMatchedSequence(inner, TrackConfig())
    rel = seq.relation(10)  # the grid frame 10 is unreadable: the other four nearest fits decide
    assert rel is not None and rel.gain == pytest.approx(1 / GAIN, abs=0.06)
    with pytest.raises(DatasetError, match="frame 10"):
        seq.frame(10)
    got = [f.seq for f in seq.frames(8, 13)]
    assert got == [8, 9, 11, 12] and inner.skipped_frames == [10] and seq.skipped_frames is inner.skipped_frames


@pytest.mark.slow
def test_the_relations_do_not_depend_on_the_order_frames_are_read(sim):
    a = ExposureMatchedSequence(_Darker(sim, _lut(GAIN, OFFSET)), TrackConfig())
    b = ExposureMatchedSequence(_Darker(sim, _lut(GAIN, OFFSET)), TrackConfig())
    for i in range(30):
        a.frame(i)
    for i in reversed(range(0, 30, 4)):
        b.frame(i)
    frames = np.arange(30)
    assert a.summary(frames) == b.summary(frames)
    assert np.array_equal(a.frame(17).right, b.frame(17).right)


def test_frames_read_in_order_are_each_read_once(sim):
    """A fit reads the grid frames ahead of the frame asked for; reading on, a stage gets those
    frames again from the frames kept, and the images it gets are not to be changed."""
    inner = _Darker(sim, _lut(GAIN, OFFSET))
    seq = ExposureMatchedSequence(inner, TrackConfig())
    got = [f.seq for f in seq.frames(0, 20)]
    assert got == list(range(20))
    assert inner.loads == 20 + 2  # and the grid frames 20 and 22, whose fits frames 18 and 19 use
    fr = seq.frame(19)
    assert inner.loads == 22 and not fr.left.flags.writeable
    with pytest.raises(ValueError):
        fr.left[0, 0] = 0


class _Swinging(SequenceBase):
    """The right camera's gain swinging 0.75-1.25 within 30 frames (an AGC of its own)."""

    def __init__(self, inner) -> None:
        super().__init__(inner.rig, inner.t_ns)
        self.inner, self.name = inner, "swinging"

    @staticmethod
    def gain(i: int) -> float:
        return 1.0 + 0.25 * np.sin(2 * np.pi * i / 30)

    def _load(self, i: int):
        fr = self.inner.frame(i)
        return dataclasses.replace(fr, right=cv2.LUT(fr.right, _lut(self.gain(i), 0.0)))


def test_the_correction_follows_a_changing_exposure(sim):
    seq = ExposureMatchedSequence(_Swinging(sim), TrackConfig())
    for i in (4, 8, 12, 19, 23, 26):  # around the swing's extremes (frames 7.5 and 22.5)
        rel = seq.relation(i)
        assert rel is not None and rel.gain == pytest.approx(1 / _Swinging.gain(i), abs=0.08), i


def test_probe_and_settings_refuse_what_they_cannot_use(sim):
    flat = np.full((480, 640), 90, np.uint8)
    assert probe_relation(sim.rig, flat, flat, TrackConfig()) is None  # no corner, no relation
    with pytest.raises(ConfigError, match="stride"):
        ExposureMatchedSequence(sim, TrackConfig(), stride=0)


@pytest.fixture(scope="module")
def dark_session(tmp_path_factory) -> Path:
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim

    d = tmp_path_factory.mktemp("exposure") / "session"
    record_sequence(open_sim(SimConfig(frames=60)), d, config_dict={"source": "sim"})
    lut = _lut(GAIN, OFFSET)
    for p in sorted((d / "mav0" / "cam1" / "data").glob("*.png")):
        cv2.imwrite(str(p), cv2.LUT(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), lut))
    return d


@pytest.mark.slow
def test_reprocessing_a_darker_right_camera_keeps_its_tracks(dark_session, tmp_path):
    """The same recorded frames with and without the matching: the stereo keypoints the tracks are
    built from, and the adjusted path's error."""
    # plain SIFT keyframe features (preset 'quick', about half the time): the matching is the same
    on = REPROCESS_PRESETS["quick"]
    assert on.match_exposure
    res = reprocess_session(dark_session, tmp_path / "on", preset=on, run=RunChoices(do_map=False, progress=False))
    off = dataclasses.replace(on, match_exposure=False)
    res_off = reprocess_session(dark_session, tmp_path / "off", preset=off, run=RunChoices(do_map=False, progress=False))
    trk = res.report["extra"]["tracks"]
    trk_off = res_off.report["extra"]["tracks"]
    assert trk["exposure"]["corrected"] == trk["exposure"]["frames"] > 0
    assert trk["exposure"]["gain"] == pytest.approx(1 / GAIN, abs=0.06)
    assert "exposure" not in trk_off
    assert trk["keypoints"] > 3 * trk_off["keypoints"] and trk["tracks"] > 3 * trk_off["tracks"]
    # the keyframes' stereo gains 3x the tracks; the frames between keyframes are fitted on their left
    # images alone, so the path's error depends little on the right camera: no worse with the matching
    assert res.report["ate_rmse_m"] <= 1.1 * res_off.report["ate_rmse_m"]
