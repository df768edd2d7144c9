"""The capture service in-process: readiness, watchdog on a hung camera, stop, reload, status.

The service runs on a worker thread with the simulator (a fast fake estimator keeps the runs
short); systemd's notify socket is a datagram socket bound by the test.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading

import pytest

from stereopath.device.formats import open_source
from stereopath.device.service.components import RunSeams
from stereopath.device.service.options import RunOptions, load_config
from stereopath.device.service.service import CaptureService
from stereopath.device.formats.tum import read_tum
from tests.device.test_service_support import FakeEstimator, HangingSimSource, NotifyListener, sim_tables, wait_until, \
    write_toml

pytestmark = pytest.mark.timeout(60)

WATCHDOG_S = 1.5  # pings every 0.75 s; data older than 0.5 s (max_data_age_s) stops them


def _start(service: CaptureService) -> tuple[threading.Thread, dict]:
    result: dict = {}
    thread = threading.Thread(target=lambda: result.setdefault("code", service.run()), daemon=True)
    thread.start()
    return thread, result


@pytest.mark.slow
@pytest.mark.parametrize("fault", ["camera", "imu"])
def test_ready_after_sources_open_watchdog_stops_when_a_sensor_hangs(tmp_path, fault):
    listener = NotifyListener(tmp_path)
    cfg_path = write_toml(tmp_path / "device.toml", sim_tables(tmp_path, max_data_age_s=0.5))
    out = tmp_path / "session"
    source = HangingSimSource(hang_after=40) if fault == "camera" else HangingSimSource(imu_silent_after=40)
    estimator = FakeEstimator()
    service = CaptureService(load_config(cfg_path, RunOptions()), RunOptions(out=str(out)), cfg_path,
                             environ={"NOTIFY_SOCKET": listener.address, "WATCHDOG_USEC": str(int(WATCHDOG_S * 1e6))},
                             seams=RunSeams(source=source, estimator=estimator))
    thread, result = _start(service)
    try:
        assert listener.wait_for("READY", "1", timeout_s=30)
        ready_at = listener.times("READY", "1")[0]
        # READY=1 only after the cameras were open and paired frames (with IMU samples) had arrived
        assert source.opened_at is not None and source.first_frame_at is not None
        assert source.first_frame_at <= ready_at
        assert service.last_imu_at is not None
        assert (out / "manifest.json").is_file()  # the recorder was open
        # pings flow while frames and IMU samples flow, then one of them stops
        assert wait_until(lambda: source.fault_started_at is not None, 30)
        hang = source.fault_started_at
        pings_before = [t for t in listener.times("WATCHDOG", "1") if t <= hang]
        assert len(pings_before) >= 2, f"only {len(pings_before)} watchdog pings while data flowed"
        wait_until(lambda: False, 2.5 * WATCHDOG_S)
        late = [t - hang for t in listener.times("WATCHDOG", "1") if t > hang + WATCHDOG_S]
        assert not late, f"watchdog pings {late} s after the {fault} hung (systemd would not restart us)"
        assert thread.is_alive()  # still running: it is systemd's watchdog that restarts a hung service
        status = json.loads((tmp_path / "status.json").read_text())
        assert status["state"] == "running" and status["data_fresh"] is False
        if fault == "imu":  # frames kept coming without IMU samples
            assert source.delivered > 40 and service.frames_in > 40
    finally:
        service.request_stop("test over")
        thread.join(30)
        listener.close()
    assert not thread.is_alive() and result["code"] == 0
    order = listener.keys_in_order()
    assert order[0] == "READY=1" and order[-1] == "STOPPING=1"
    assert all(k == "WATCHDOG=1" for k in order[1:-1])
    # the session is complete: every frame delivered is on disk, with its pose
    seq = open_source(f"session:{out}")
    assert seq.manifest["status"] == "closed"
    assert len(seq) == source.delivered == len(estimator.frames)
    assert len(read_tum(out / "trajectory.tum")) == len(seq)
    assert estimator.closed
    assert all(n > 0 for n in estimator.imu_blocks[1:40])  # frames carried their IMU blocks
    assert len(seq.groundtruth) == len(seq)  # simulated run: ground truth for exactly the recorded frames
    if fault == "camera":
        assert len(seq) == 40


def test_duration_limit(tmp_path):
    cfg_path = write_toml(tmp_path / "device.toml", sim_tables(tmp_path, rate_hz=20.0))
    opts = RunOptions(duration_s=1.0, out=str(tmp_path / "s"))
    service = CaptureService(load_config(cfg_path, opts), opts, cfg_path, environ={}, seams=RunSeams(estimator=FakeEstimator()))
    assert service.run() == 0
    assert service.stop_reason == "1 s elapsed" and 0 < service.frames_in < 200
    assert len(open_source(f"session:{tmp_path / 's'}")) == service.frames_in


def test_frame_limit_ends_cleanly_and_reports_status(tmp_path):
    cfg_path = write_toml(tmp_path / "device.toml", sim_tables(tmp_path))
    opts = RunOptions(frames=12, out=str(tmp_path / "s"))
    estimator = FakeEstimator(kf_every=4)
    service = CaptureService(load_config(cfg_path, opts), opts, cfg_path, environ={}, seams=RunSeams(estimator=estimator))
    assert service.run() == 0
    status = json.loads((tmp_path / "status.json").read_text())
    assert status["state"] == "stopped" and status["stop_reason"] == "12 frames captured"
    assert status["frames"] == 12 and status["frames_estimated"] == 12 and status["keyframes"] == 3
    assert status["recorder_state"] == "closed" and status["recorder_counts"]["poses"] == 12
    assert status["imu_samples"] > 0 and status["source"] == "sim" and status["imu"] == "source"
    assert len(open_source(f"session:{tmp_path / 's'}")) == 12
    # `stereopath device status` reads it (exit 1: the service is not running any more)
    from stereopath.device.commands import status as status_cmd

    args = argparse.Namespace(config=None, status_file=str(tmp_path / "status.json"), json=False)
    assert status_cmd.run(args) == 1


def test_sighup_reload_applies_live_settings_and_names_the_others(tmp_path, caplog):
    tables = sim_tables(tmp_path, rate_hz=20.0)
    cfg_path = write_toml(tmp_path / "device.toml", tables)
    opts = RunOptions(out=str(tmp_path / "s"))
    service = CaptureService(load_config(cfg_path, opts), opts, cfg_path, environ={},
                             seams=RunSeams(source=HangingSimSource(rate_hz=20.0), estimator=FakeEstimator()))
    thread, result = _start(service)
    try:
        assert wait_until(lambda: service.ready, 30)
        # `stereopath device status` on a running service: exit 0 and the rates
        from stereopath.device.commands import status as status_cmd

        assert wait_until(lambda: json.loads((tmp_path / "status.json").read_text())["frames"] > 0, 10)
        args = argparse.Namespace(config=None, status_file=str(tmp_path / "status.json"), json=False)
        assert status_cmd.run(args) == 0
        caplog.set_level(logging.INFO, logger="stereopath.device.service.service")
        # a bad file is refused and the running configuration kept
        (tmp_path / "device.toml").write_text(cfg_path.read_text() + "\n[timealign]\nbogus = 1\n")
        service.request_reload()
        assert wait_until(lambda: "reload of" in caplog.text, 10)
        assert "bogus" in caplog.text and thread.is_alive()
        # a good file: the time offset applies at the next frame, the frame rate needs a restart
        tables["timealign"] = {"time_offset_us": 1500.0}
        tables["source"]["fps"] = 25.0
        tables["service"]["max_data_age_s"] = 1.5
        write_toml(cfg_path, tables)
        service.request_reload()
        assert wait_until(lambda: "configuration reloaded" in caplog.text, 10)
        assert wait_until(lambda: service.aligner.time_offset_ns == 1_500_000, 10)
        line = next(r.getMessage() for r in caplog.records if "configuration reloaded" in r.getMessage())
        assert "timealign.time_offset_us" in line.split("needs a restart")[0]
        assert "needs a restart: source.fps" in line
        assert service.cfg.service.max_data_age_s == 1.5 and service.cfg.source.fps == 30.0
    finally:
        service.request_stop("test over")
        thread.join(30)
    assert result["code"] == 0


def test_capture_failure_exits_1_with_one_log_line(tmp_path, caplog):
    from stereopath.device.errors import CaptureError

    class Broken(HangingSimSource):
        def _frames(self):
            yield from list(super()._frames())[:3]
            raise CaptureError("picamera2: no frame pair for 2.0 s (left camera silent)")

    cfg_path = write_toml(tmp_path / "device.toml", sim_tables(tmp_path, frames=5))
    opts = RunOptions(out=str(tmp_path / "s"))
    service = CaptureService(load_config(cfg_path, opts), opts, cfg_path, environ={},
                             seams=RunSeams(source=Broken(frames=5), estimator=FakeEstimator()))
    caplog.set_level(logging.INFO)
    assert service.run() == 1
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "left camera silent" in errors[0].getMessage() and errors[0].exc_info is None
    status = json.loads((tmp_path / "status.json").read_text())
    assert status["state"] == "failed" and "left camera silent" in status["last_error"]
    assert open_source(f"session:{tmp_path / 's'}").manifest["status"] == "closed"


class _LevellingEstimator(FakeEstimator):
    """Levels its world once at its 5th frame (as a start in motion does): the poses before it were given in
    the first camera's world, the later ones in the levelled world."""

    world_frame = "first_camera"

    def __init__(self) -> None:
        super().__init__()
        import numpy as np

        from stereopath.device.core.geometry import make_pose, so3_exp

        self.G = make_pose(so3_exp(np.array([0.3, -0.1, 0.05])), np.zeros(3))
        self.world_rebase = None

    def process(self, frame, imu):
        est = super().process(frame, imu)
        if len(self.frames) >= 5:
            est.T_world_cam = self.G @ est.T_world_cam
            if self.world_rebase is None:
                self.world_rebase, self.world_frame = (frame.seq, self.G), "gravity_aligned"
        return est


def test_a_world_levelled_during_the_run_is_recorded_and_the_path_reads_in_one_world(tmp_path):
    import numpy as np

    cfg_path = write_toml(tmp_path / "device.toml", sim_tables(tmp_path))
    opts = RunOptions(frames=12, out=str(tmp_path / "s"))
    estimator = _LevellingEstimator()
    service = CaptureService(load_config(cfg_path, opts), opts, cfg_path, environ={}, seams=RunSeams(estimator=estimator))
    assert service.run() == 0
    info = json.loads((tmp_path / "s" / "estimator.json").read_text())
    seq = open_source(f"session:{tmp_path / 's'}")
    raw = read_tum(tmp_path / "s" / "trajectory.tum")
    assert info["world_frame"] == "gravity_aligned"
    assert info["world_rebase"]["from_t_ns"] == int(raw.t_ns[4])
    np.testing.assert_allclose(info["world_rebase"]["T_new_old"], estimator.G, atol=1e-12)
    # as recorded, the first four poses are in the first camera's world; read back, all are in the new one
    traj = seq.trajectory
    expect = np.stack([estimator.G @ np.r_[np.c_[np.eye(3), [0.01 * k, 0, 0]], [[0, 0, 0, 1]]] for k in range(1, 13)])
    np.testing.assert_allclose(traj.T_world_cam, expect, atol=1e-6)
    assert not np.allclose(raw.T_world_cam[:4], expect[:4], atol=1e-3)


def test_the_sinks_are_told_of_the_world_rebase_once():
    """The streaming sink must tell the hosts how to map the poses it already sent: every sink hears of the
    rebase once, at the frame it happened, before that frame's estimate."""
    import numpy as np

    from stereopath.device.core.frames import StereoFrame
    from stereopath.device.service.pipeline import FrameInputs, FramePipeline
    from stereopath.device.service.sinks import NullSink

    class Sink(NullSink):
        name = "probe"

        def __init__(self) -> None:
            self.calls: list[tuple[str, int, object]] = []

        def add_estimate(self, frame, est) -> None:
            self.calls.append(("pose", frame.t_ns, None))

        def world_rebased(self, from_t_ns, T_new_old) -> None:
            self.calls.append(("rebase", from_t_ns, T_new_old))

    estimator, sink = _LevellingEstimator(), Sink()
    pipe = FramePipeline(FrameInputs([], None, None, estimator), [sink], stop=threading.Event(),
                         request_stop=lambda reason: None)
    img = np.zeros((4, 4), np.uint8)
    for k in range(8):
        pipe._handle(StereoFrame(k, 1_000 + 50 * k, img, img))
    rebases = [c for c in sink.calls if c[0] == "rebase"]
    assert len(rebases) == 1 and rebases[0][1] == 1_000 + 50 * 4
    np.testing.assert_allclose(rebases[0][2], estimator.G)
    at = sink.calls.index(rebases[0])
    assert sink.calls[at + 1] == ("pose", 1_000 + 50 * 4, None)  # before the first estimate in the new world


def test_an_unreadable_world_rebase_is_named(tmp_path):
    import numpy as np

    from stereopath.device.errors import DatasetError
    from stereopath.device.formats.asl import rebased_trajectory
    from stereopath.device.formats.tum import Trajectory

    traj = Trajectory(np.arange(3, dtype=np.int64), np.stack([np.eye(4)] * 3))
    p = tmp_path / "estimator.json"
    p.write_text(json.dumps({"world_rebase": {"from_t_ns": 1, "T_new_old": [[1, 0], [0, 1]]}}))
    with pytest.raises(DatasetError, match="world_rebase"):
        rebased_trajectory(traj, p)
    p.write_text(json.dumps({"frames": 3}))
    assert rebased_trajectory(traj, p) is traj
