"""The right camera's grey levels measured against the left's on stereo matches, and the estimator on a
rig whose right camera is exposed darker (two cameras with their own exposure control)."""

import dataclasses

import cv2
import numpy as np
import pytest

from stereopath.device.core.photometric import GainOffset, correct_right, fit_gain_offset, relation_matters
from stereopath.device.estimation.base import run_estimator
from stereopath.device.estimation.registry import make_estimator
from stereopath.device.formats.source import open_source
from stereopath.host.evaluation.evaluate import evaluate


def _texture(seed=0, shape=(240, 320)):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, shape).astype(np.float32), (0, 0), 3)
    img = (img - img.min()) / (img.max() - img.min()) * 200 + 20
    return img.astype(np.uint8)


def _lut(gain, offset):
    return np.clip(np.rint(gain * np.arange(256) + offset), 0, 255).astype(np.uint8)


def test_fit_recovers_a_known_gain_and_offset_and_the_correction_undoes_it():
    left = _texture()
    right = cv2.LUT(left, _lut(0.8, -10.0))  # right = 0.8 left - 10, so left = 1.25 right + 12.5
    rng = np.random.default_rng(1)
    xy = rng.uniform(20, [300, 220], (200, 2))
    rel = fit_gain_offset(left, right, xy, xy)
    assert rel is not None and rel.n >= 180
    assert rel.gain == pytest.approx(1.25, abs=0.02)
    assert rel.offset == pytest.approx(12.5, abs=1.5)
    assert relation_matters(rel)
    back = correct_right(right, rel).astype(int)
    assert np.median(np.abs(back - left)) <= 1


def test_fit_ignores_mismatched_points_and_leaves_matched_cameras_alone():
    left = _texture(2)
    rng = np.random.default_rng(3)
    xy = rng.uniform(20, [300, 220], (200, 2))
    xy_r = xy.copy()
    xy_r[:20] = rng.uniform(20, [300, 220], (20, 2))  # 10 % wrong matches
    rel = fit_gain_offset(left, left, xy, xy_r)
    assert rel is not None and rel.n < 200  # the wrong matches are dropped
    assert rel.gain == pytest.approx(1.0, abs=0.02) and abs(rel.offset) < 2
    assert not relation_matters(rel)


def test_fit_says_when_the_relation_is_not_identifiable():
    left = _texture(4)
    xy = np.random.default_rng(5).uniform(20, [300, 220], (200, 2))
    assert fit_gain_offset(left, left, xy[:10], xy[:10]) is None  # too few matches
    flat = np.full_like(left, 90)
    assert fit_gain_offset(flat, flat, xy, xy) is None  # a uniform scene fixes no gain
    assert fit_gain_offset(left, 255 - left, xy, xy) is None  # inverted: not one camera's exposure
    assert not relation_matters(None)
    assert relation_matters(GainOffset(1.0, 6.0, 50, 6.0)) and not relation_matters(GainOffset(1.0, 3.0, 50, 3.0))


def test_correction_saturates_instead_of_wrapping():
    img = np.array([[0, 100, 250]], np.uint8)
    out = correct_right(img, GainOffset(1.5, -20.0))
    assert out.dtype == np.uint8 and out.tolist() == [[0, 130, 255]]


@pytest.fixture(scope="module")
def sim_short():
    seq = open_source("sim:1", frames=100)
    return seq, list(seq.frames())


def _run(seq, frames, **options):
    est = make_estimator("stereo", seq.rig, options=options)
    run = run_estimator(est, iter(frames), seq.imu)
    return run, evaluate(seq.groundtruth, run.trajectory), est.stats()


@pytest.mark.slow
def test_estimator_measures_a_darker_right_camera_and_tracks_as_with_matched_cameras(sim_short):
    seq, frames = sim_short
    dark = [dataclasses.replace(f, right=cv2.LUT(f.right, _lut(0.75, -12.0))) for f in frames]
    run0, m0, c0 = _run(seq, frames)
    assert c0["exposure_corrected_frames"] == 0  # matched cameras: the images as captured
    run, m, c = _run(seq, dark)
    assert run.frames_tracked == len(frames)
    assert c["right_gain_milli"] == pytest.approx(1333, abs=40) and c["right_offset_centi"] == pytest.approx(1600, abs=300)
    assert c["exposure_corrected_frames"] >= len(frames) - 2
    assert c["keyframes"] <= c0["keyframes"] + 4
    assert m["ate_rmse_m"] < 1.5 * m0["ate_rmse_m"] + 2e-4
    # without the correction the same frames lose most stereo matches: a keyframe at nearly every frame
    run_off, m_off, c_off = _run(seq, dark, exposure={"match": False})
    assert c_off["keyframes"] > 3 * c["keyframes"]


@pytest.mark.slow
def test_estimator_follows_a_right_camera_whose_exposure_keeps_changing(sim_short):
    """Two AGCs that do not agree: the right camera's gain swings 0.75-1.25 and its offset +-10 levels
    within 2.5 s.  The relation is measured at every frame (on the stereo matches of the pose solve),
    so the correction follows it; a correction measured only at keyframes lags half a swing behind."""
    seq, frames = sim_short
    t0 = frames[0].t_ns
    agc = []
    for f in frames:
        t = (f.t_ns - t0) * 1e-9
        lut = _lut(1.0 + 0.25 * np.sin(2 * np.pi * t / 2.5), -10.0 * np.sin(2 * np.pi * t / 4.25))
        agc.append(dataclasses.replace(f, right=cv2.LUT(f.right, lut)))
    run0, m0, c0 = _run(seq, frames)
    run, m, c = _run(seq, agc)
    run_off, m_off, _ = _run(seq, agc, exposure={"match": False})
    assert run.frames_tracked == len(frames)
    assert c["exposure_fits"] >= len(frames) - 2  # every tracked frame measures the relation
    assert c["exposure_corrected_frames"] > len(frames) // 2
    assert c["keyframes"] <= c0["keyframes"] + 2
    assert m["ate_rmse_m"] < 1.5 * m0["ate_rmse_m"] + 2e-4
    assert m["ate_rmse_m"] < 0.75 * m_off["ate_rmse_m"]
