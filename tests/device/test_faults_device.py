"""Issue 15 device faults: a taken port (item 5)."""

from __future__ import annotations

import json
import socket
import subprocess
from pathlib import Path

import pytest

from tests.device.test_service_support import device_run, sim_tables, write_toml
from tests.device.test_streaming_support import loopback_stream, receive_until_done

pytestmark = pytest.mark.timeout(120)


@pytest.mark.parametrize("which", ["pose", "keyframe"])
def test_port_taken_exits_with_config_code_and_leaves_no_folder(tmp_path, which):
    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen()
    taken = blocker.getsockname()[1]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    ports = {"pose": taken, "keyframe": free} if which == "pose" else {"pose": free, "keyframe": taken}
    stream = {"insecure": True, "pose_endpoint": f"tcp://127.0.0.1:{ports['pose']}",
              "keyframe_endpoint": f"tcp://127.0.0.1:{ports['keyframe']}"}
    cfg = write_toml(tmp_path / "device.toml", sim_tables(tmp_path, frames=20, stream=stream))
    try:
        err = _config_failure(tmp_path, cfg, "a port taken")
    finally:
        blocker.close()
    assert "Address already in use" in err


def _config_failure(tmp_path: Path, cfg: Path, what: str) -> str:
    """Run `device run --config CFG`, expect exit 78 with one line and no session folder; its stderr."""
    proc = device_run(["--config", str(cfg)])
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        pytest.fail(f"device run hung with {what}:\n" + err[-2000:])
    assert proc.returncode == 78, err[-2000:]
    assert "Traceback" not in err
    sessions = tmp_path / "sessions"
    assert not sessions.exists() or list(sessions.iterdir()) == []
    return err


# item 7 (the service side): a bad rig is a configuration error ------------------------------------

def test_device_run_with_a_bad_rig_exits_with_the_config_code(tmp_path):
    import yaml

    data = yaml.safe_load((Path(__file__).resolve().parents[2] / "firmware_cfg" / "rig_paper.yaml").read_text())
    data["T_cam1_cam0_m"] = [-v for v in data["T_cam1_cam0_m"]]  # cam1 to the left of cam0
    rig = tmp_path / "neg.yaml"
    rig.write_text(yaml.safe_dump(data))
    tables = sim_tables(tmp_path, frames=5)
    tables["source"]["rig_file"] = str(rig)
    err = _config_failure(tmp_path, write_toml(tmp_path / "device.toml", tables), "a bad rig")
    assert "configuration error: unusable rig calibration (source.rig_file" in err, err[-2000:]
    assert "to the LEFT of cam0" in err


# item 2: device disk full -----------------------------------------------------------------------

def test_spool_keeps_keyframes_in_memory_when_the_disk_is_full(tmp_path, monkeypatch):
    import errno

    from stereopath.device.errors import DatasetError
    from stereopath.device.formats import fileio
    from stereopath.device.streaming import KeyframeSpool

    free = {"bytes": 10**9}
    spool = KeyframeSpool(tmp_path / "sp", fsync=False, reserve_bytes=1000, max_memory_bytes=25,
                          disk_free=lambda p: free["bytes"])
    spool.append(0, b"zero")
    free["bytes"] = 1003  # writing 4 more bytes would eat into the reserve
    spool.append(1, b"one!")
    assert spool.disk_full and spool.memory_count == 1 and not spool.path(1).exists()
    assert spool.read(1) == b"one!" and spool.read(0) == b"zero"
    for seq in range(2, 5):
        spool.append(seq, b"x" * 6)
    with pytest.raises(DatasetError, match="wait in memory"):
        spool.append(5, b"y" * 6)  # memory full too: refused (the streamer counts it)
    spool.release(3)  # a host holds everything up to 3
    assert spool.memory_count == 1 and spool.read(4) == b"x" * 6
    spool.append(5, b"y" * 6)
    with pytest.raises(DatasetError, match="delivered from memory"):
        spool.read(2)

    def enospc(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(fileio, "write_atomic", enospc)
    other = KeyframeSpool(tmp_path / "sp2", fsync=False)
    other.append(0, b"kf")
    assert other.disk_full == "No space left on device" and other.read(0) == b"kf"
    assert not [p for p in (tmp_path / "sp2").iterdir()]


def test_device_disk_full_mid_run_loses_no_keyframe_reaching_a_host_and_exits_74(tmp_path, monkeypatch):
    import collections
    import shutil as shutil_mod
    import threading

    from stereopath.device.service.components import RunSeams
    from stereopath.device.service.options import RunOptions, load_config
    from stereopath.device.service.service import EXIT_DISK_FULL, CaptureService
    from stereopath.host.live.receiver import Receiver, ReceiverConfig
    from tests.device.test_service_support import FakeEstimator, wait_until
    from tests.device.test_streaming_support import stored_seqs

    usage = collections.namedtuple("usage", "total used free")
    full = threading.Event()
    real_usage = shutil_mod.disk_usage
    monkeypatch.setattr(shutil_mod, "disk_usage",
                        lambda p: usage(10**12, 10**12, 0) if full.is_set() else real_usage(p))
    stream = loopback_stream(drain_s=5.0)
    tables = sim_tables(tmp_path, frames=40, rate_hz=20.0, stream=stream)
    cfg_path = write_toml(tmp_path / "device.toml", tables)
    opts = RunOptions(out=str(tmp_path / "s"), wait_for_host_s=10.0)
    service = CaptureService(load_config(cfg_path, opts), opts, cfg_path, environ={},
                             seams=RunSeams(estimator=FakeEstimator(kf_every=2)))
    rx = Receiver(ReceiverConfig(stream["pose_endpoint"], stream["keyframe_endpoint"], insecure=True, fsync=False,
                                 stall_timeout_s=0.5), tmp_path / "host")
    result = {}
    th = threading.Thread(target=lambda: result.setdefault("code", service.run()), daemon=True)
    th.start()
    try:
        assert wait_until(lambda: (rx.poll(0.02) or True) and service.frames_in >= 8, 30)
    finally:
        full.set()  # the device's disk fills up mid-scan
        receive_until_done(th, rx)
    assert result["code"] == EXIT_DISK_FULL
    status = json.loads((tmp_path / "status.json").read_text())
    assert status["recorder_state"] == "stopped_low_disk" and status["spool_disk_full"]
    spooled = status["keyframes_spooled"]
    assert spooled == 20 and status["keyframes_failed"] == 0
    assert stored_seqs(tmp_path / "host", service.session_id) == list(range(spooled))  # none lost
    on_disk = list((tmp_path / "s" / "keyframes").glob("*.kf"))
    assert len(on_disk) < spooled  # the rest never touched the reserve


def test_the_recording_is_closed_before_the_drain_waits_for_hosts(tmp_path, monkeypatch):
    """The end-of-run drain may wait up to stream.drain_s for hosts: the recording is already complete (rows
    flushed, manifest closed) by then, so a kill during the drain loses no frame that was recorded."""
    from stereopath.device.formats.asl import open_session
    from stereopath.device.service import sinks
    from stereopath.device.service.components import RunSeams
    from stereopath.device.service.options import RunOptions, load_config
    from stereopath.device.service.service import EXIT_OK, CaptureService
    from tests.device.test_service_support import FakeEstimator

    seen = {}

    def drain(self, seconds, clock):
        seen["manifest"] = json.loads((tmp_path / "s" / "manifest.json").read_text())
        seen["frames"] = len(open_session(tmp_path / "s"))

    monkeypatch.setattr(sinks.NoStreaming, "drain", drain)
    cfg_path = write_toml(tmp_path / "device.toml", sim_tables(tmp_path, frames=12))
    opts = RunOptions(out=str(tmp_path / "s"))
    service = CaptureService(load_config(cfg_path, opts), opts, cfg_path, environ={}, seams=RunSeams(estimator=FakeEstimator()))
    assert service.run() == EXIT_OK
    assert seen["manifest"]["status"] == "closed" and seen["manifest"]["counts"]["frames"] == 12
    assert seen["frames"] == 12
