"""The stereo estimator's frame loop: keyframe work off the loop, bounded; fast motion; the shared stereo step."""

import os
import threading

import cv2
import numpy as np
import pytest

from stereopath.device.core.features import gray
from stereopath.device.core.frames import StereoFrame
from stereopath.device.formats.rig_files import load_kitti_calib
from stereopath.device.core.stereo import stereo_right
from stereopath.device.estimation.base import run_estimator
from stereopath.device.estimation.registry import make_estimator
from stereopath.device.core.stereo_config import AsiftWork, DisparityOffsetConfig, KeyframePolicy, StereoConfig
from stereopath.device.estimation.stereo_measure import StereoMeasure
from stereopath.device.estimation.stereo_vo import StereoEstimator
from stereopath.device.errors import ConfigError


def _kitti_frames(data_dir, idx):
    seq = data_dir / "kitti_odometry/sequences/06"
    rig = load_kitti_calib(seq / "calib.txt", (1226, 370))
    frames = [StereoFrame(j, int(i * 103_000_000), cv2.imread(str(seq / f"image_0/{i:06d}.png"), 0),
                          cv2.imread(str(seq / f"image_1/{i:06d}.png"), 0)) for j, i in enumerate(idx)]
    return rig, frames


def test_stereo_right_recovers_a_subpixel_disparity_and_rejects_row_mismatch(data_dir):
    seq = data_dir / "kitti_odometry/sequences/06"
    rig = load_kitti_calib(seq / "calib.txt", (1226, 370))
    rng = np.random.default_rng(0)
    left = cv2.GaussianBlur(rng.integers(0, 255, (370, 1226)).astype(np.uint8), (0, 0), 2.0)
    left = cv2.normalize(left, None, 0, 255, cv2.NORM_MINMAX)
    d = 7.3
    shift = np.float32([[1, 0, -d], [0, 1, 0]])  # right(x) = left(x + d): disparity d
    right = cv2.warpAffine(left, shift, (1226, 370), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    pts = cv2.goodFeaturesToTrack(left, 200, 0.01, 10).reshape(-1, 2)
    pts = pts[(pts[:, 0] > 40) & (pts[:, 0] < 1180) & (pts[:, 1] > 40) & (pts[:, 1] < 330)]
    cfg = StereoConfig()
    xr, ok = stereo_right(rig, left, right, pts, pts - [4.0, 0.0], cfg.klt)
    assert ok.mean() > 0.9
    assert np.median(np.abs(pts[ok, 0] - xr[ok, 0] - d)) < 0.05
    assert np.all(np.abs(xr[ok, 1] - pts[ok, 1]) < 0.2)
    # the same points 3 px lower in the right image: not on the rectified row, rejected
    down = cv2.warpAffine(right, np.float32([[1, 0, 0], [0, 1, 3]]), (1226, 370), borderMode=cv2.BORDER_REFLECT)
    _, ok2 = stereo_right(rig, left, down, pts, pts - [4.0, 0.0], cfg.klt)
    assert ok2.mean() < 0.1
    assert stereo_right(rig, left, right, np.zeros((0, 2)), np.zeros((0, 2)), cfg)[0].shape == (0, 2)


def test_gray_accepts_colour_and_single_channel():
    img = np.zeros((4, 5, 3), np.uint8)
    img[..., 2] = 200
    assert gray(img).shape == (4, 5) and gray(img)[0, 0] > 0
    g = np.full((4, 5), 7, np.uint8)
    assert gray(g) is g
    assert gray(g[:, :, None]).shape == (4, 5)


def test_keyframe_work_never_stalls_the_frame_loop_and_its_queue_is_bounded(data_dir):
    rig, frames = _kitti_frames(data_dir, range(12))
    # a keyframe at every frame, each asking for ASIFT work
    est = StereoEstimator(rig, StereoConfig(KeyframePolicy(max_frames=1), asift=AsiftWork(min_rotation_deg=0.0)))
    release = threading.Event()
    started = []
    real_job = est._worker.run

    def slow_job(job, prev):
        started.append(job.seq)
        release.wait(30)  # the worker is stuck until the test lets it go
        return real_job(job, prev)

    est._worker.run = slow_job
    try:
        out = [est.process(f, None) for f in frames]  # must return although no job can finish
        assert all(e.status == "ok" for e in out)
        assert sum(e.keyframe for e in out) >= 10
        assert est._worker.in_flight <= 2  # one running, one waiting: never a pile-up
        assert est.counts.kf_jobs_skipped >= 8
        assert started == [0]  # only the first job started; the waiting one was replaced
    finally:
        release.set()
        est.close()
    est2 = StereoEstimator(rig, StereoConfig())
    run = run_estimator(est2, iter(frames), None)
    assert run.frames_tracked == len(frames)


@pytest.mark.slow
@pytest.mark.parametrize("step", [2, 3])
def test_fast_motion_every_nth_kitti_frame_is_tracked(data_dir, step):
    from stereopath.host.evaluation.evaluate import evaluate
    from stereopath.device.formats.source import open_source

    seq = open_source(f"kitti:{data_dir / 'kitti_odometry/sequences/06'}")
    frames = list(seq.frames(step=step))
    run = run_estimator(make_estimator("stereo", seq.rig), iter(frames), None)
    assert run.frames_tracked == len(frames)  # 0 lost
    m = evaluate(seq.groundtruth, run.trajectory)
    assert m["end_error_m"] / m["path_length_m"] < 0.02


def test_online_disparity_offset_is_estimated_bounded_and_used(data_dir):
    rig, frames = _kitti_frames(data_dir, range(14))
    est = StereoEstimator(rig, StereoConfig(KeyframePolicy(max_frames=2, background=False),
                                            disparity_offset=DisparityOffsetConfig(estimate=True)))
    run = run_estimator(est, iter(frames), None)
    out = run.estimates
    assert len(out) == len(frames) and all(e.status == "ok" for e in out)
    assert est._offset.n >= 3 and est._offset.ready
    assert abs(est._offset.value) <= est._offset.bound
    # from the third keyframe on, each estimate is solved over the last four keyframes
    assert est.counts.disparity_offset_windows >= est.counts.keyframes - 3 >= 3
    # the fused value is what the triangulation and the pose refinement now remove
    assert est._geo.disparity_offset_px == est._offset.value != 0.0
    assert est.counts.disparity_offset_mpx == round(1000 * est._offset.value)


def test_each_offset_estimate_is_solved_over_the_last_four_keyframes_stereo_observations(data_dir, monkeypatch):
    """What the window solve gets: at each keyframe the views of the last three keyframes and this one, each
    holding exactly the points measured in stereo there (new points and re-observed ones) with their rows
    as measured at that keyframe; and what it returns is what the filter fuses."""
    from stereopath.device.estimation import disparity_offset, stereo_vo

    calls, fused = [], []
    real_window, real_update = stereo_vo.offset_over_keyframes, disparity_offset.OffsetFilter.update

    def window(rect, views, max_inflation=None):
        out = real_window(rect, views, max_inflation)
        calls.append(([(ids.copy(), rows.copy(), T.copy()) for ids, rows, T in views], out))
        return out

    def update(self, est):
        fused.append(est)
        return real_update(self, est)

    kept = []  # per keyframe: its pose, the points measured in stereo there (ids, rows), the ids mapped before
    measured: list = []  # the rectified rows measured while a keyframe is made
    real_new_keyframe = stereo_vo.StereoEstimator._new_keyframe
    real_rows = StereoMeasure.rectified_observations

    def rows_of(self, uv_left, uv_right):
        out = real_rows(self, uv_left, uv_right)
        measured.append(out.copy())
        return out

    def new_keyframe(self, img, T_world_cam, map_right=None):
        before = set(self._state.map.ids.tolist())
        measured.clear()
        n = real_new_keyframe(self, img, T_world_cam, map_right)
        m = self._state.map
        at = m.obs_kf == self.counts.keyframes - 1
        kept.append((T_world_cam.copy(), m.ids[at].copy(), m.obs[at].copy(), before, np.vstack(measured)))
        return n

    monkeypatch.setattr(stereo_vo, "offset_over_keyframes", window)
    monkeypatch.setattr(disparity_offset.OffsetFilter, "update", update)
    monkeypatch.setattr(stereo_vo.StereoEstimator, "_new_keyframe", new_keyframe)
    monkeypatch.setattr(StereoMeasure, "rectified_observations", rows_of)
    rig, frames = _kitti_frames(data_dir, range(14))
    est = StereoEstimator(rig, StereoConfig(KeyframePolicy(max_frames=2, background=False)))
    for f in frames:
        est.process(f, None)
    est.close()
    assert len(calls) >= 3 and [len(v) for v, _ in calls[:2]] == [3, 4] and all(len(v) == 4 for v, _ in calls[1:])
    for views, out in calls:
        assert any(out is e for e in fused)  # the window's estimate, not another
        for n, (ids, rows, T) in enumerate(views):
            T_kf, kf_ids, kf_rows, before, kf_measured = next(k for k in kept if np.array_equal(k[0], T))
            # rows as measured at that keyframe
            assert all(np.any(np.all(kf_measured == r, axis=1)) for r in rows)
            if n < len(views) - 1:  # an earlier keyframe: every point measured in stereo there
                assert sorted(ids) == sorted(kf_ids)
            else:  # this keyframe, before its new points are made: the mapped points measured in stereo
                assert set(ids) == set(kf_ids.tolist()) & before
            order = {int(i): r for i, r in zip(kf_ids, kf_rows)}
            np.testing.assert_array_equal(rows, np.array([order[int(i)] for i in ids]).reshape(-1, 3))


def test_the_path_measured_before_the_offset_was_learned_is_re_measured_once(data_dir):
    """KITTI's offset is learned after a few keyframes: the motion made until then with the prior is
    re-measured with it once, which brings the path closer to the truth than leaving it."""
    gt = np.loadtxt(data_dir / "kitti_odometry/poses/06.txt").reshape(-1, 3, 4)
    end_error = {}
    for correct in (True, False):
        rig, frames = _kitti_frames(data_dir, range(14))
        est = StereoEstimator(rig, StereoConfig(KeyframePolicy(max_frames=2, background=False)))
        if not correct:
            real = est._prior_path.correction  # computed (the pairs are forgotten), never applied
            est._prior_path.correction = lambda *args: [real(*args), None][1]
        out = [est.process(f, None) for f in frames]
        est.close()
        assert all(e.status == "ok" for e in out) and est._offset.ready
        assert est.counts.disparity_offset_path_corrections == int(correct)
        assert not est._prior_path.pairs  # kept only until the offset is learned
        end_error[correct] = np.linalg.norm(out[-1].T_world_cam[:3, 3] - gt[13][:, 3])
    assert end_error[True] < end_error[False] - 0.01


@pytest.mark.slow
def test_online_disparity_offset_stays_at_the_prior_around_an_object():
    """An orbit around the table objects cannot tell an offset from a turn: every estimate is ignored (the
    windows of four keyframes reach down to an inflation of 8.3 here, over the limit of 7)."""
    from stereopath.device.sim.session import open_sim

    seq = open_sim(seed=2, frames=60, trajectory="orbit")
    est = StereoEstimator(seq.rig, StereoConfig(KeyframePolicy(max_frames=2, background=False)))
    assert est.cfg.disparity_offset.estimate  # on by default
    out = [est.process(seq.frame(i), None) for i in range(len(seq))]
    est.close()
    assert all(e.status == "ok" for e in out)
    assert est.counts.disparity_offset_unidentified >= 5
    assert est._offset.n == 0 and est._geo.disparity_offset_px == 0.0
    assert est.counts.disparity_offset_windows >= 5
    assert est.counts.disparity_offset_mpx == 0
    assert est.counts.disparity_offset_path_corrections == 0


@pytest.mark.slow
def test_asift_work_is_scheduled_by_view_change_not_at_every_keyframe(data_dir):
    rig, frames = _kitti_frames(data_dir, range(12))  # driving straight: little rotation
    est = StereoEstimator(rig, StereoConfig(KeyframePolicy(max_frames=1, background=False), asift=AsiftWork(max_frames=5)))
    run = run_estimator(est, iter(frames), None)
    out = run.estimates
    assert len(out) == len(frames) and all(e.status == "ok" for e in out) and sum(e.keyframe for e in out) >= 10
    # the first keyframe and then one by age (5 frames) at most: the rest only top up the map
    assert 2 <= est.counts.kf_jobs <= 3
    assert est.counts.kf_jobs_deferred == est.counts.keyframes - est.counts.kf_jobs
    turning = StereoEstimator(rig, StereoConfig(KeyframePolicy(max_frames=1, background=False),
                                                asift=AsiftWork(min_rotation_deg=0.0)))
    for f in frames[:4]:
        turning.process(f, None)
    turning.close()
    assert turning.counts.kf_jobs == 4  # any rotation asks for it: every keyframe


def _look_at(c, target=np.zeros(3), up=np.array([0.0, -1.0, 0.0])):
    """Camera-to-world pose at ``c`` looking at ``target`` (x right, y down, z forward)."""
    z = target - c
    z = z / np.linalg.norm(z)
    x = np.cross(up, z)
    x = x / np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = c
    return T


def test_predicted_view_change_gives_the_tilt_and_its_direction():
    from stereopath.device.estimation.keyframe_jobs import predicted_view_change

    rng = np.random.default_rng(0)
    X = rng.normal(0, 0.05, (200, 3))  # a small cloud around the origin, 2 m ahead
    T0 = _look_at(np.array([0.0, 0.0, -2.0]))
    # a pure rotation changes no viewing direction: no tilt
    T_rot = T0.copy()
    T_rot[:3, :3] = T0[:3, :3] @ cv2.Rodrigues(np.array([0.0, 0.3, 0.0]))[0]
    assert predicted_view_change(X, T0, T_rot)[0] == pytest.approx(1.0, abs=1e-9)
    # orbiting 60 deg sideways (about the vertical): tilt 2 along the image x axis
    a = np.radians(60)
    tilt, phi = predicted_view_change(X, T0, _look_at(2.0 * np.array([np.sin(a), 0.0, -np.cos(a)])))
    assert tilt == pytest.approx(2.0, rel=0.03)
    assert min(phi, 180 - phi) < 3.0
    # orbiting 45 deg upwards: tilt sqrt(2) along the image y axis
    a = np.radians(45)
    tilt, phi = predicted_view_change(X, T0, _look_at(2.0 * np.array([0.0, -np.sin(a), -np.cos(a)])))
    assert tilt == pytest.approx(np.sqrt(2), rel=0.03)
    assert abs(phi - 90.0) < 3.0
    assert predicted_view_change(np.zeros((0, 3)), T0, T0) == (1.0, 0.0)


def test_keyframe_match_simulates_views_only_for_a_large_predicted_view_change(data_dir):
    from stereopath.device.core.features import Features

    rig, frames = _kitti_frames(data_dir, [0])
    est = StereoEstimator(rig, StereoConfig(KeyframePolicy(background=False)))
    left = frames[0].left
    feats0 = est._worker.features(left, views=[0])
    X = np.random.default_rng(1).normal(0, 0.5, (100, 3)) + [0.0, 0.0, 10.0]
    T0 = _look_at(np.zeros(3), np.array([0.0, 0.0, 10.0]))
    small = _look_at(np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 10.0]))  # ~6 deg: SIFT bridges it
    same = est._worker._with_predicted_views(left, feats0, X, T0, small)
    assert same is feats0
    big = _look_at(np.array([10.0 * np.sin(1.0), 0.0, 10.0 - 10.0 * np.cos(1.0)]), np.array([0.0, 0.0, 10.0]))
    out = est._worker._with_predicted_views(left, feats0, X, T0, big)  # 57 deg: tilt ~1.85
    assert isinstance(out, Features) and set(np.unique(out.view)) == {0, 1, 2}
    assert len(out) > len(feats0)
    est.close()
    from stereopath.device.errors import ConfigError

    with pytest.raises(ConfigError):
        AsiftWork(views="sometimes")


@pytest.mark.skipif(not hasattr(threading, "get_native_id") or not hasattr(os, "sched_getaffinity"),
                    reason="per-thread priority is a Linux feature")
def test_keyframe_worker_runs_below_the_frame_loop_when_it_shares_its_core(data_dir, monkeypatch):
    from stereopath.device.estimation.keyframe_jobs import lower_thread_priority, worker_niceness

    rig, _ = _kitti_frames(data_dir, range(1))
    loop_nice = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    def worker_nice(policy):
        est = StereoEstimator(rig, StereoConfig(policy))
        try:  # the worker's own thread reports its niceness
            return est._worker._executor.submit(
                lambda: os.getpriority(os.PRIO_PROCESS, threading.get_native_id())).result(10)
        finally:
            est.close()

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})  # one core: worker and loop share it
    assert worker_niceness(KeyframePolicy()) == 10
    assert worker_nice(KeyframePolicy()) == min(19, loop_nice + 10)
    assert worker_nice(KeyframePolicy(worker_nice=0)) == loop_nice
    assert worker_nice(KeyframePolicy(worker_nice_max_cores=0)) == loop_nice  # never
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})  # a core of its own: the loop's priority
    assert worker_niceness(KeyframePolicy()) == 0
    assert worker_nice(KeyframePolicy()) == loop_nice
    assert worker_nice(KeyframePolicy(worker_nice=5, worker_nice_max_cores=2)) == min(19, loop_nice + 5)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == loop_nice  # the caller's is untouched
    assert lower_thread_priority(0) is None
    with pytest.raises(ConfigError, match="worker_nice"):
        KeyframePolicy(worker_nice=20)


@pytest.mark.slow
def test_fast_motion_keyframes_top_up_the_map_by_klt_corners_without_sift(data_dir):
    from stereopath.host.evaluation.evaluate import evaluate
    from stereopath.device.formats.source import open_source

    seq = open_source(f"kitti:{data_dir / 'kitti_odometry/sequences/06'}")
    frames = list(seq.frames(step=3))[:17]  # 30 m in 17 frames: most frames become keyframes
    est = StereoEstimator(seq.rig, StereoConfig(KeyframePolicy(background=False), asift=AsiftWork(enabled=False)))
    sizes = []
    real_new = est._new_keyframe

    def new_keyframe(img, T, map_right=None):
        n = real_new(img, T, map_right)
        sizes.append(n)
        return n

    est._new_keyframe = new_keyframe
    run = run_estimator(est, iter(frames), None)
    out = run.estimates
    assert len(out) == len(frames) and all(e.status == "ok" for e in out)  # no SIFT, no relocalisation, nothing lost
    assert est.counts.kf_jobs == 0 and est.counts.asift_views == 0 and est.counts.relocalised == 0
    kf = [e for e in out[1:] if e.keyframe]
    assert len(kf) >= len(frames) // 2
    # each keyframe tops the map up from new corners away from the tracked points, well above what was tracked
    assert len(sizes) == len(kf) + 1
    assert all(n >= e.inliers + 50 for n, e in zip(sizes[1:], kf))
    assert min(sizes) >= 0.5 * est.cfg.keyframes.max_points
    m = evaluate(seq.groundtruth, run.trajectory)
    assert m["end_error_m"] / m["path_length_m"] < 0.02


def test_a_settled_estimator_pickles_mid_run_and_goes_on_like_the_original(data_dir):
    """Keyframe jobs in flight on the worker thread keep the estimator from pickling; settled (the jobs
    finished, their results held for the next frame) it pickles, and the copy tracks the next frames
    with the poses the original gives (to the threaded mode's run-to-run spread, a fraction of a
    millimetre here: two runs without pickling differ as much; in line, a resumed run is exact, see
    tests/host/test_reprocess.py)."""
    import pickle

    from stereopath.device.errors import EstimationError

    rig, frames = _kitti_frames(data_dir, range(10))
    est = StereoEstimator(rig, StereoConfig(KeyframePolicy(max_frames=1), asift=AsiftWork(min_rotation_deg=0.0)))
    release = threading.Event()
    real_job = est._worker.run

    def held_job(job, prev):
        release.wait(30)
        return real_job(job, prev)

    est._worker.run = held_job
    try:
        for f in frames[:5]:
            est.process(f, None)
        assert est._worker.in_flight >= 1
        with pytest.raises(EstimationError, match="settle"):
            pickle.dumps(est._worker)
        release.set()
        est._worker.run = real_job
        est.settle()
        copy = pickle.loads(pickle.dumps(est))
        try:
            assert copy._worker.in_flight == est._worker.in_flight >= 1
            for f in frames[5:]:
                a, b = est.process(f, None), copy.process(f, None)
                est.settle(), copy.settle()  # the same order of events in both
                assert a.status == b.status == "ok" and np.allclose(a.T_world_cam, b.T_world_cam, atol=2e-3)
        finally:
            copy.close()
    finally:
        release.set()
        est.close()


def test_points_predicted_beyond_klt_reach_outside_the_image_are_not_tracked(data_dir, monkeypatch):
    """Fast motion: a tracked point predicted farther outside the image than KLT's coarsest level reaches
    has left the view; it is dropped before the KLT, the others are tracked (KITTI 06, every 3rd frame)."""
    from stereopath.device.estimation import stereo_vo
    from stereopath.device.formats.source import open_source

    seq = open_source(f"kitti:{data_dir / 'kitti_odometry/sequences/06'}")
    frames = list(seq.frames(step=3))[:8]
    est = StereoEstimator(seq.rig, StereoConfig(KeyframePolicy(background=False), asift=AsiftWork(enabled=False)))
    real_track, real_klt = stereo_vo.track_scaled, stereo_vo.StereoEstimator._klt_track
    passed, dropped = [], []

    def track(prev, cur, p0, guess, *args):
        passed.append(np.asarray(guess).copy())
        return real_track(prev, cur, p0, guess, *args)

    def klt(self, left, T_pred, levels):
        n = len(self._state.map)
        uv, good = real_klt(self, left, T_pred, levels)
        reach = (self.cfg.klt.klt_window // 2 + 2) * 2**levels + 2
        w, h = self.rig.cam0.size
        tracked = len(passed[-1]) if passed else n
        dropped.append((n - tracked, reach, w, h))
        return uv, good

    monkeypatch.setattr(stereo_vo, "track_scaled", track)
    monkeypatch.setattr(stereo_vo.StereoEstimator, "_klt_track", klt)
    run = run_estimator(est, iter(frames), None)
    assert all(e.status == "ok" for e in run.estimates)
    assert sum(d for d, *_ in dropped) > 20  # points leave the view every frame at this speed
    for g, (_, reach, w, h) in zip(passed, dropped):
        assert ((g >= -reach) & (g < (w - 1 + reach, h - 1 + reach))).all()
