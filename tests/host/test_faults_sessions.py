"""Issue 15, items 6 and 8: the device's rig reaches the host store; a killed device's keyframes are delivered."""

from __future__ import annotations

import logging
import subprocess
from pathlib import Path

import numpy as np
import pytest

from stereopath.device.errors import CalibrationError
from stereopath.device.wire.protocol import DecodeError, decode_session, encode_session, make_session_info, \
    rig_of, rig_reference
from tests.device.test_streaming_support import make_device, receive_until_done, small_images, stored_seqs, wait_for

REPO = Path(__file__).resolve().parents[2]
PAPER_YAML = REPO / "firmware_cfg" / "rig_paper.yaml"


def _receiver(pose_endpoint: str, keyframe_endpoint: str, out: Path, **kw):
    from stereopath.host.live.receiver import Receiver, ReceiverConfig
    from stereopath.host.live.receiver_config import SocketTiming

    return Receiver(ReceiverConfig(pose_endpoint, keyframe_endpoint, insecure=True, fsync=False,
                                   sockets=SocketTiming(heartbeat_ivl_ms=250, heartbeat_timeout_ms=1500,
                                                        reconnect_ivl_ms=50, reconnect_ivl_max_ms=400),
                                   stall_timeout_s=1.0), out, **kw)


def _deliver(dev, out: Path, session: str, n: int) -> None:
    """Offer ``n`` keyframes to a connected host and wait until it stored them and the device has the acks."""
    rx = _receiver(dev.pose_endpoint, dev.keyframe_endpoint, out)
    try:
        for i in range(n):
            assert dev.offer_keyframe(i, i, np.eye(4), *small_images(i))
        assert wait_for(lambda: len(stored_seqs(out, session)) == n, 20, between=lambda: rx.poll(0.02))
        assert wait_for(lambda: dev.stats()["keyframes_acked"] == n, 10, between=lambda: rx.poll(0.02))
    finally:
        rx.close()


def _sim_keyframes(dev, n: int = 6, step: int = 4):
    """Offer ``n`` simulated keyframes with their true poses; returns the sequence."""
    from stereopath.device.formats.source import open_source

    seq = open_source("sim:0", frames=30 + step * n)
    for k, i in enumerate(range(30, 30 + step * n, step)):
        f = seq.render(i)
        assert dev.offer_keyframe(i, f.t_ns, f.meta["T_world_cam0"], f.left, f.right)
    assert dev.wait_spooled(n, 20)
    return seq


# item 8: the session message --------------------------------------------------------------------

def test_session_message_carries_the_rig_and_is_checked_against_its_hash():
    from stereopath.device.formats.rig_files import load_rig_yaml

    rig = load_rig_yaml(PAPER_YAML)
    ref = rig_reference(rig)
    msg = decode_session(encode_session(make_session_info("s1", rig, ref, keyframes=7)))
    assert (msg.rig_name, msg.rig_hash, msg.keyframes, msg.live) == (ref[0], ref[1], 7, True)
    assert rig_reference(rig_of(msg)) == ref
    forged = make_session_info("s1", rig, (ref[0], "0" * 16))
    with pytest.raises(DecodeError, match="hashes to"):
        decode_session(encode_session(forged))
    bad = make_session_info("s1", rig, ref)
    bad.rig["T_cam1_cam0_m"] = [-v for v in bad.rig["T_cam1_cam0_m"]]  # cameras exchanged
    with pytest.raises(DecodeError, match="invalid rig"):
        decode_session(encode_session(bad))


def test_host_stores_the_device_rig_and_host_map_uses_it(tmp_path):
    from stereopath.device.streaming import DeviceStreamer, KeyframeSpool
    from stereopath.host.mapping.inputs import keyframes_input
    from tests.device.test_streaming_support import device_config

    from stereopath.device.formats.source import open_source

    rig = open_source("sim:0", frames=2).rig
    dev = DeviceStreamer(device_config(None), KeyframeSpool(tmp_path / "spool", fsync=False), "sessR", rig=rig,
                         status_interval_s=0.2)
    out = tmp_path / "host"
    try:
        _deliver(dev, out, "sessR", 3)
    finally:
        dev.close()
    stored = out / "sessR" / "rig.yaml"
    assert stored.is_file() and not list((out / "sessR").glob("*.tmp"))
    from stereopath.device.formats.rig_files import load_rig_yaml

    assert rig_reference(load_rig_yaml(stored)) == rig_reference(rig)
    mi = keyframes_input(out / "sessR")  # no --rig: the stored device rig
    assert rig_reference(mi.rig) == rig_reference(rig) and len(mi.keyframes) == 3
    with pytest.raises(CalibrationError, match="drop --rig"):
        keyframes_input(out / "sessR", rig=PAPER_YAML)
    from stereopath.host.live.receiver_sessions import session_states

    (state,) = session_states(out)
    assert (state.session_id, state.stored, state.on_device, state.state) == ("sessR", 3, 3, "complete")


@pytest.mark.slow
def test_host_live_map_with_the_shipped_rig_maps_with_the_device_rig(tmp_path, caplog):
    """`host live --map --rig firmware_cfg/rig_paper.yaml` against a device on another rig: mesh, rc 0."""
    from stereopath.device.streaming import DeviceStreamer, KeyframeSpool
    from stereopath.host.cli import main
    from tests.device.test_streaming_support import device_config, port_of

    from stereopath.device.formats.source import open_source

    rig = open_source("sim:0", frames=2).rig
    dev = DeviceStreamer(device_config(None), KeyframeSpool(tmp_path / "spool", fsync=False), "sessM", rig=rig,
                         status_interval_s=0.2)
    try:
        _sim_keyframes(dev)
        out = tmp_path / "host"
        with caplog.at_level(logging.WARNING):
            rc = main(["host", "live", "--device", f"127.0.0.1:{port_of(dev.pose_endpoint)}", "--keyframe-port",
                       str(port_of(dev.keyframe_endpoint)), "--insecure", "--out", str(out), "--no-fsync",
                       "--map", "--map-every", "2", "--rig", str(PAPER_YAML), "--duration", "4"])
    finally:
        dev.close()
    assert rc == 0
    assert stored_seqs(out, "sessM") == list(range(6))
    assert (out / "sessM" / "rig.yaml").is_file()
    assert (out / "sessM" / "model" / "mesh.ply").stat().st_size > 0
    assert any("is not the rig session sessM was taken with" in r.getMessage() for r in caplog.records)
    assert not any("not fused" in r.getMessage() for r in caplog.records)


def test_host_live_map_without_any_matching_rig_is_an_error(tmp_path, capsys):
    """A device that sends no calibration and a --rig that does not match: rc 1 and one clear line."""
    from stereopath.host.cli import main
    from tests.device.test_streaming_support import port_of

    dev = make_device(tmp_path, None, "sessX")  # rig reference only, no calibration to send
    try:
        for i in range(2):
            assert dev.offer_keyframe(i, i, np.eye(4), *small_images(i))
        assert dev.wait_spooled(2, 10)
        rc = main(["host", "live", "--device", f"127.0.0.1:{port_of(dev.pose_endpoint)}", "--keyframe-port",
                   str(port_of(dev.keyframe_endpoint)), "--insecure", "--out", str(tmp_path / "host"), "--no-fsync",
                   "--map", "--rig", str(PAPER_YAML), "--duration", "2"])
    finally:
        dev.close()
    assert rc == 1
    assert "none of the 2 keyframe(s) could be mapped" in capsys.readouterr().err


# item 6: a killed device's spool -----------------------------------------------------------------

def test_restarted_device_offers_earlier_unacknowledged_keyframes_after_the_live_ones(tmp_path):
    old = make_device(tmp_path, None, "sessOld")
    for i in range(6):
        assert old.offer_keyframe(i, i, np.eye(4), *small_images(i))
    assert old.wait_spooled(6, 10)
    old.close(timeout_s=1)  # nothing reached a host
    old_dir = tmp_path / "spool_sessOld"
    new = make_device(tmp_path, None, "sessNew", backlog_roots=[tmp_path])
    assert new.stats()["backlog_keyframes"] == 6
    out = tmp_path / "host"
    order: list[str] = []
    rx = _receiver(new.pose_endpoint, new.keyframe_endpoint, out,
                   on_keyframe=lambda kf, is_new: order.append(kf.session_id))
    try:
        for i in range(3):
            assert new.offer_keyframe(i, i, np.eye(4), *small_images(10 + i))
        assert new.wait_spooled(3, 10)
        assert wait_for(lambda: len(stored_seqs(out, "sessOld")) == 6 and len(stored_seqs(out, "sessNew")) == 3,
                        20, between=lambda: rx.poll(0.02))
        assert wait_for(lambda: not list(old_dir.glob("*.kf")), 10, between=lambda: rx.poll(0.02))
    finally:
        rx.close()
        new.close()
    assert order == ["sessNew"] * 3 + ["sessOld"] * 6  # the live session first
    assert rx.store.last_session == "sessNew"  # the hello state stays on the live session
    assert new.stats()["backlog_keyframes"] == 0 and new.stats()["backlog_delivered"] == 6
    from stereopath.host.live.receiver_sessions import session_states

    states = {s.session_id: s for s in session_states(out)}
    assert states["sessOld"].state == "complete" and states["sessOld"].on_device == 6
    # a third run finds nothing left to offer
    again = make_device(tmp_path, None, "sessThird", backlog_roots=[tmp_path])
    assert again.stats()["backlog_keyframes"] == 0
    again.close()


def test_acknowledged_keyframes_are_not_offered_again(tmp_path):
    dev = make_device(tmp_path, None, "sessA")
    _deliver(dev, tmp_path / "host", "sessA", 4)
    for i in range(4, 6):  # spooled after the host left: never acknowledged
        assert dev.offer_keyframe(i, i, np.eye(4), *small_images(i))
    assert dev.wait_spooled(6, 10)
    dev.close(timeout_s=1)
    nxt = make_device(tmp_path, None, "sessB", backlog_roots=[tmp_path])
    try:
        assert nxt.stats()["backlog_keyframes"] == 2
        assert [s.pending for s in nxt.backlog.sessions] == [[4, 5]]
    finally:
        nxt.close()


def _device_run(tmp: Path, stream: dict, frames: int, *args: str) -> tuple[subprocess.Popen, Path]:
    from tests.device.test_service_support import device_run, sim_tables, write_toml

    tables = sim_tables(tmp, frames=frames, rate_hz=20.0, stream=stream)
    cfg = write_toml(tmp / "device.toml", tables)
    return device_run(["--config", str(cfg), *args]), tmp / "sessions"


@pytest.mark.slow
def test_kill_9_device_then_restart_delivers_the_unacknowledged_keyframes(tmp_path):
    """End to end: `device run` killed mid-session with keyframes no host had; restarted; `host live`
    receives the earlier session's keyframes under its own id and the device deletes them."""
    from tests.device.test_streaming_support import kill_9_once_spooled, loopback_stream

    stream = loopback_stream(spool_fsync=False)
    proc, sessions = _device_run(tmp_path, stream, 400)
    first = kill_9_once_spooled(proc, sessions, 4)  # no host ever connected: nothing acknowledged
    killed = sorted(p.name for p in (first / "keyframes").glob("*.kf"))
    assert len(killed) >= 4
    proc2, _ = _device_run(tmp_path, stream, 40, "--wait-for-host", "60")
    out = tmp_path / "host"
    rx = _receiver(stream["pose_endpoint"], stream["keyframe_endpoint"], out)
    try:
        assert wait_for(lambda: len(stored_seqs(out, first.name)) == len(killed), 60,
                        between=lambda: rx.poll(0.05)), f"host holds {stored_seqs(out, first.name)} of {killed}"
        assert wait_for(lambda: not list((first / "keyframes").glob("*.kf")), 20, between=lambda: rx.poll(0.05))
        _, err = proc2.communicate(timeout=60)
    finally:
        rx.close()
        if proc2.poll() is None:
            proc2.kill()
            proc2.communicate()
    assert proc2.returncode == 0, err[-2000:]
    assert "no host acknowledged" in err and "Traceback" not in err
    assert (out / first.name / "rig.yaml").is_file()
    from stereopath.host.live.receiver_sessions import session_states

    states = {s.session_id: s for s in session_states(out)}
    assert states[first.name].state == "complete" and states[first.name].stored == len(killed)
    assert len(list(sessions.iterdir())) == 2


def test_host_sessions_lists_incomplete_sessions(tmp_path, capsys):
    import json

    from stereopath.host.cli import main

    out = tmp_path / "host"
    for sid, stored, on_device in (("sessDone", 3, 3), ("sessCut", 2, 5), ("sessOld", 2, None)):
        d = out / sid / "keyframes"
        d.mkdir(parents=True)
        for seq in range(stored):
            (d / f"kf_{seq:08d}.msgpack").write_bytes(b"x")
        if on_device is not None:
            (out / sid / "session.json").write_text(json.dumps({"session_id": sid, "keyframes_on_device": on_device}))
    (out / "sessDone" / "rig.yaml").write_text("name: x\n")
    assert main(["host", "sessions", str(out)]) == 1
    text = capsys.readouterr().out
    lines = {ln.split()[0]: ln.split() for ln in text.splitlines()[1:]}
    assert lines["sessCut"][1:5] == ["incomplete", "2", "5", "3"]
    assert lines["sessDone"][1:5] == ["complete", "3", "3", "0"] and lines["sessDone"][5] == "rig.yaml"
    assert lines["sessOld"][1:5] == ["unknown", "2", "?", "0"]
    assert main(["host", "sessions", str(out), "--incomplete"]) == 1
    assert [ln.split()[0] for ln in capsys.readouterr().out.splitlines()[1:]] == ["sessCut"]
    assert main(["host", "sessions", str(tmp_path / "nope")]) == 2


def test_earlier_session_keyframes_wait_for_host_space(tmp_path, monkeypatch):
    """Host disk full while an earlier session's keyframes arrive: none acknowledged (so none deleted on
    the device), all delivered once there is space, in the same host process."""
    from stereopath.host.live import store as store_mod
    from tests.device.test_streaming_support import write_or_enospc

    old = make_device(tmp_path, None, "sessOld")
    for i in range(4):
        assert old.offer_keyframe(i, i, np.eye(4), *small_images(i))
    assert old.wait_spooled(4, 10)
    old.close(timeout_s=1)
    full = {"on": True}
    monkeypatch.setattr(store_mod, "write_atomic", write_or_enospc(store_mod.write_atomic, full))
    new = make_device(tmp_path, None, "sessNew", backlog_roots=[tmp_path])
    out = tmp_path / "host"
    rx = _receiver(new.pose_endpoint, new.keyframe_endpoint, out)
    try:
        assert wait_for(lambda: rx.stats.link.store_failures >= 2, 20, between=lambda: rx.poll(0.02))
        assert len(list((tmp_path / "spool_sessOld").glob("*.kf"))) == 4  # nothing acknowledged, nothing deleted
        full["on"] = False
        assert wait_for(lambda: len(stored_seqs(out, "sessOld")) == 4, 30, between=lambda: rx.poll(0.02))
        assert wait_for(lambda: not list((tmp_path / "spool_sessOld").glob("*.kf")), 10,
                        between=lambda: rx.poll(0.02))
    finally:
        rx.close()
        new.close()


def test_keyframes_refused_before_later_ones_stored_are_fetched_again(tmp_path, monkeypatch):
    """The first two keyframes of an earlier session hit a full disk, the next two are stored: the
    host must still ask for the first two again (a stored keyframe does not mean nothing is missing)."""
    import errno

    from stereopath.host.live import store as store_mod

    old = make_device(tmp_path, None, "sessOld")
    for i in range(4):
        assert old.offer_keyframe(i, i, np.eye(4), *small_images(i))
    assert old.wait_spooled(4, 10)
    old.close(timeout_s=1)
    real = store_mod.write_atomic
    refused: list[str] = []

    def first_two_keyframes_fail(path, *a, **k):
        if str(path).endswith(".msgpack") and "sessOld" in str(path) and len(refused) < 2:
            refused.append(str(path))
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(store_mod, "write_atomic", first_two_keyframes_fail)
    new = make_device(tmp_path, None, "sessNew", backlog_roots=[tmp_path])
    out = tmp_path / "host"
    rx = _receiver(new.pose_endpoint, new.keyframe_endpoint, out)
    try:
        assert wait_for(lambda: len(stored_seqs(out, "sessOld")) == 4, 30, between=lambda: rx.poll(0.02))
        assert len(refused) == 2 and rx.stats.link.store_failures == 2
        assert wait_for(lambda: not list((tmp_path / "spool_sessOld").glob("*.kf")), 10,
                        between=lambda: rx.poll(0.02))
    finally:
        rx.close()
        new.close()


def test_a_refused_out_does_not_strand_its_spool(tmp_path):
    """The killed run's --out is refused (78); a run with a new --out beside it offers the killed
    session's keyframes and, at its stop, waits (up to stream.drain_s) until a host has them."""
    import threading

    from stereopath.device.service.components import RunSeams
    from stereopath.device.service.main import run_service
    from stereopath.device.service.options import RunOptions, load_config
    from stereopath.device.service.service import CaptureService
    from stereopath.device.streaming import DeviceStreamer, KeyframeSpool
    from tests.device.test_service_support import FakeEstimator, sim_tables, write_toml
    from tests.device.test_streaming_support import device_config, loopback_stream

    scans = tmp_path / "scans"
    killed = DeviceStreamer(device_config(None), KeyframeSpool(scans / "a" / "keyframes", fsync=False), "sessA",
                            status_interval_s=0.2)  # stands in for the killed run of `device run --out scans/a`
    for i in range(3):
        assert killed.offer_keyframe(i, i, np.eye(4), *small_images(i))
    assert killed.wait_spooled(3, 10)
    killed.close(timeout_s=1)
    stream = loopback_stream(drain_s=5.0, spool_fsync=False)
    cfg_path = write_toml(tmp_path / "device.toml", sim_tables(tmp_path, frames=10, rate_hz=20.0, stream=stream))
    assert run_service(cfg_path, RunOptions(out=str(scans / "a")), environ={}) == 78
    opts = RunOptions(out=str(scans / "b"), wait_for_host_s=20.0)
    service = CaptureService(load_config(cfg_path, opts), opts, cfg_path, environ={},
                             seams=RunSeams(estimator=FakeEstimator(kf_every=2)))
    out = tmp_path / "host"
    result: dict = {}
    th = threading.Thread(target=lambda: result.setdefault("code", service.run()), daemon=True)
    th.start()
    receive_until_done(th, _receiver(stream["pose_endpoint"], stream["keyframe_endpoint"], out))
    assert result["code"] == 0
    assert stored_seqs(out, "sessA") == [0, 1, 2]
    assert not list((scans / "a" / "keyframes").glob("*.kf"))
    assert stored_seqs(out, service.session_id) == list(range(5))
