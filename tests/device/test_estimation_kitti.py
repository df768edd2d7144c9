"""The stereo estimator on real KITTI 06 frames, and its behaviour on broken frames."""

import numpy as np
import pytest

from stereopath.device.estimation.base import run_estimator
from stereopath.device.estimation.registry import make_estimator
from stereopath.device.core.frames import StereoFrame
from stereopath.device.formats.rig_files import load_kitti_calib


def _kitti(data_dir, n):
    import cv2

    seq = data_dir / "kitti_odometry/sequences/06"
    rig = load_kitti_calib(seq / "calib.txt", (1226, 370))
    imgs = [(cv2.imread(str(seq / f"image_0/{i:06d}.png"), 0), cv2.imread(str(seq / f"image_1/{i:06d}.png"), 0))
            for i in range(n)]
    return rig, imgs


@pytest.mark.slow
def test_stereo_on_kitti06_end_error_below_2_percent(data_dir):
    from stereopath.host.evaluation.evaluate import evaluate
    from stereopath.device.formats.source import open_source

    seq = open_source(f"kitti:{data_dir / 'kitti_odometry/sequences/06'}")
    run = run_estimator(make_estimator("stereo", seq.rig), seq.frames(), None)
    m = evaluate(seq.groundtruth, run.trajectory)
    assert run.frames_tracked == len(seq) == 51
    assert m["path_length_m"] == pytest.approx(59.9, abs=0.5)
    assert m["end_error_m"] / m["path_length_m"] < 0.02
    assert m["ate_rmse_m"] < 0.3


def test_black_lens_cap_and_foreign_frames_are_flagged_and_tracking_continues(data_dir):
    import cv2

    rig, imgs = _kitti(data_dir, 16)
    graf = data_dir / "affine/graf"
    foreign = (cv2.resize(cv2.imread(str(graf / "img1.png"), 0), (1226, 370)),
               cv2.resize(cv2.imread(str(graf / "img2.png"), 0), (1226, 370)))
    noise = np.clip(np.random.default_rng(0).normal(3, 1.5, imgs[0][0].shape), 0, 255).astype(np.uint8)
    bad = {4: (np.zeros_like(noise), np.zeros_like(noise)), 8: (noise, noise), 12: foreign}

    def frames():
        for i, (l, r) in enumerate(imgs):
            l, r = bad.get(i, (l, r))
            yield StereoFrame(i, i * 100_000_000, l, r)

    run = run_estimator(make_estimator("stereo", rig), frames(), None)
    status = [e.status for e in run.estimates]
    assert len(status) == 16
    assert all(status[i] == "lost" for i in bad)  # no IMU on KITTI: flagged lost, not an exception
    assert all(status[i] == "ok" for i in range(16) if i not in bad)
    z = np.array([e.T_world_cam[2, 3] for e in run.estimates])
    assert np.all(np.diff(z) > 0.5)  # the car keeps driving forward about 1.2 m per frame, no jumps back
    assert np.all(np.diff(z) < 2.0)


@pytest.mark.slow
def test_tracking_at_the_predicted_scale_keeps_the_path_of_fast_driving(data_dir):
    """KITTI 06 taken every 2nd frame (2.4 m between frames): the tracked points' windows grow by 13 % from
    one frame to the next at the median, the nearest by 40 % and more.  Plain KLT drifts off them and the disparity offset read from the tracks comes out
    too small (the path 0.4 % too long); tracked at their predicted scale, the offset is close to what every
    frame gives (-0.19 px) and the error halves."""
    from stereopath.host.evaluation.evaluate import evaluate
    from stereopath.device.formats.source import open_source

    seq = open_source(f"kitti:{data_dir / 'kitti_odometry/sequences/06'}")
    frames = [f for f in seq.frames() if f.seq % 2 == 0]
    out = {}
    for step in (0.0, 0.05):
        # keyframe work in line: the same result every run
        est = make_estimator("stereo", seq.rig, options={"klt": {"klt_scale_step": step}, "keyframes": {"background": False}})
        run = run_estimator(est, iter(frames), None)
        assert run.frames_tracked == len(frames) == 26
        out[step] = (evaluate(seq.groundtruth, run.trajectory)["ate_rmse_m"], est.stats()["disparity_offset_mpx"])
    (ate_plain, offset_plain), (ate, offset) = out[0.0], out[0.05]
    assert ate < 0.045 and ate < 0.6 * ate_plain  # measured 0.0310 against 0.0714 m
    # measured -160 against -146 mpx (every frame: -205; tiny changes of the tracks move it by ~10 mpx)
    assert offset < offset_plain - 5 and -250 < offset < -140
