"""picamera2 software sync as libcamera runs it: SyncFrames, the SyncReady latch, the multicast route.

The fake copies raspberrypi/libcamera ``sync.cpp`` (``Sync::process``) and ``ipa_base.cpp``
(``IpaBase::prepareIsp``/``processStats``); see ``tests/fakes/fake_picamera2.py``.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import pytest

from stereopath.device.errors import CaptureError, ConfigError
from stereopath.device.capture.multicast_route import (SYNC_GROUP, multicast_route, parse_proc_net_route,
                                                       route_to)
from stereopath.device.capture.sources import create_source
from stereopath.device.settings import load_device_config
from tests.fakes.fake_picamera2 import FakeCameraWorld, _SyncAlgorithm, _SyncModeEnum, decode_slot
from tests.fakes.standins import source_settings, take

pytestmark = pytest.mark.timeout(60)

REPO = Path(__file__).resolve().parents[2]
HEADER = "Iface\tDestination\tGateway \tFlags\tRefCnt\tUse\tMetric\tMask\t\tMTU\tWindow\tIRTT\n"
# /proc/net/route as read on this machine and in a network namespace after `ip route add ... dev lo`
ETH_DEFAULT = HEADER + ("eth0\t00000000\t010200C0\t0003\t0\t0\t0\t00000000\t0\t0\t0\n"
                        "eth0\t000200C0\t00000000\t0001\t0\t0\t0\t00FFFFFF\t0\t0\t0\n")
LO_HOST = HEADER + "lo\tFAFFFFEF\t00000000\t0005\t0\t0\t0\tFFFFFFFF\t0\t0\t0\n"
LO_MULTICAST = HEADER + "lo\t000000E0\t00000000\t0001\t0\t0\t0\t000000F0\t0\t0\t0\n"
SUBNET_ONLY = HEADER + "eth0\t000200C0\t00000000\t0001\t0\t0\t0\t00FFFFFF\t0\t0\t0\n"


def with_route(text: str = LO_HOST):
    return lambda: text


def shipped_source(**changes):
    cfg = load_device_config(REPO / "firmware_cfg" / "device.toml")
    return replace(cfg.source, rig_file="", **changes)


# ---------------------------------------------------------------------------------- route check

def test_route_parser_reads_proc_net_route():
    assert multicast_route(SYNC_GROUP, with_route(ETH_DEFAULT)) == "eth0"     # the default route carries it
    assert multicast_route(SYNC_GROUP, with_route(LO_HOST)) == "lo"
    assert multicast_route(SYNC_GROUP, with_route(LO_MULTICAST)) == "lo"
    assert multicast_route(SYNC_GROUP, with_route(SUBNET_ONLY)) is None       # 192.168.0.0/24 only
    assert multicast_route(SYNC_GROUP, with_route(HEADER)) is None
    both = parse_proc_net_route(ETH_DEFAULT + LO_HOST.split("\n", 1)[1])
    assert route_to(SYNC_GROUP, both).iface == "lo"                           # longest prefix wins
    rejected = HEADER + "lo\tFAFFFFEF\t00000000\t0205\t0\t0\t0\tFFFFFFFF\t0\t0\t0\n"
    assert multicast_route(SYNC_GROUP, with_route(rejected)) is None          # RTF_REJECT


def test_no_multicast_route_refuses_software_sync_naming_the_route():
    world = FakeCameraWorld(multicast_route=False)
    src = create_source(shipped_source(), api=world.api(), route_reader=with_route(SUBNET_ONLY))
    with pytest.raises(ConfigError) as err:
        src.open()
    msg = str(err.value)
    assert "\n" not in msg and SYNC_GROUP in msg and "ip route add 239.255.255.250/32 dev lo" in msg
    assert 'sync = "off"' in msg
    assert all(cam.closed for cam in world.instances) and world.start_order == []


def test_no_multicast_route_exits_78_on_one_line(tmp_path, caplog):
    from stereopath.device.service.components import RunSeams
    from stereopath.device.service.main import run_service
    from stereopath.device.service.options import RunOptions
    from tests.device.test_service_support import write_toml

    tables = {
        "source": {"backend": "picamera2", "rig_file": str(REPO / "firmware_cfg" / "rig_paper.yaml")},
        "imu": {"backend": "none"}, "stream": {"enabled": False},
        "recorder": {"dir": str(tmp_path / "sessions"), "reserve_mb": 1.0},
        "service": {"status_file": str(tmp_path / "status.json")},
    }
    cfg_path = write_toml(tmp_path / "device.toml", tables)
    world = FakeCameraWorld(multicast_route=False)
    with caplog.at_level(logging.WARNING):
        code = run_service(cfg_path, RunOptions(out=str(tmp_path / "s")), environ={},
                           seams=RunSeams(source_inject={"api": world.api(), "route_reader": with_route(SUBNET_ONLY)}))
    assert code == 78
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and SYNC_GROUP in errors[0] and "ip route add" in errors[0], errors
    assert not (tmp_path / "s").exists()


def test_unreadable_routing_table_is_a_warning_not_a_refusal(caplog):
    def unreadable():
        raise PermissionError("/proc/net/route: permission denied")

    world = FakeCameraWorld()
    src = create_source(source_settings("picamera2", [64, 48], 500, picamera2={"sync_frames": 30}),
                        api=world.api(), route_reader=unreadable)
    with caplog.at_level(logging.WARNING), src:
        assert len(take(src, 2)) == 2
    assert any("routing table" in r.getMessage() for r in caplog.records)
    assert src.sync_state.route == "?"


def test_client_without_multicast_names_the_route_when_the_check_passed():
    """A route the check cannot see (another policy table) that does not work: the timeout names it."""
    world = FakeCameraWorld(multicast_route=False)
    seen_keys = []
    api = world.api()
    real = api.Picamera2._process_request

    def spy(self, req, tid):
        if self is world.instances[1] and "SyncReady" in req._metadata:
            seen_keys.append(self.num)
        return real(self, req, tid)

    api.Picamera2._process_request = spy
    src = create_source(source_settings("picamera2", [64, 48], 500, picamera2={"sync_frames": 30}),
                        api=api, route_reader=with_route(LO_HOST))
    with pytest.raises(CaptureError) as err:
        with src:
            take(src, 1)
    msg = str(err.value)
    assert "right camera never reported SyncReady" in msg and SYNC_GROUP in msg and "ip route" in msg
    client_num = world.instances[1].num
    assert client_num not in seen_keys                      # the client's frames carry no sync status at all
    assert src.sync_state.frames_to_ready[0] is not None    # the server was ready (its sendto errors are logged only)


# ----------------------------------------------------------------------- SyncFrames and the latch

@pytest.mark.slow
@pytest.mark.parametrize("fps, skip_phase", [(30.0, (0, 0)), (60.0, (0, 1))])
def test_shipped_config_first_pair_after_sync_frames(fps, skip_phase):
    """Shipped device.toml (SyncFrames 100, timeout 2 s): no CaptureError at 30 fps (3.3 s of
    start-up) nor at 60 fps with the cameras' controller skips in opposite phase."""
    settings = shipped_source(fps=fps, exposure_us=8000)
    assert settings.picamera2.sync_frames == 100 and settings.timeout_s == 2.0
    world = FakeCameraWorld()
    for cam, phase in zip(world.cameras, skip_phase):
        cam.skip_phase = phase
    api = world.api()
    src = create_source(settings, api=api, route_reader=with_route(ETH_DEFAULT))
    with src:
        frames = take(src, 6)
    server, client = world.instances
    assert server.configured["controls"]["SyncFrames"] == 100 and "SyncFrames" not in client.configured["controls"]
    server_start = server.sync_algorithm.first_slot
    slots = [decode_slot(f.left)[0] for f in frames]
    assert all(decode_slot(f.right)[0] == s for f, s in zip(frames, slots))
    # the first pair is the first frame both sides call ready: SyncFrames after the server started
    ready = max(world.sync_ready_slot.values())
    assert slots[0] == ready and server_start + 100 <= ready <= server_start + 101
    assert slots == list(range(slots[0], slots[0] + 6))     # nothing lost once ready, keys or not
    state = src.sync_state
    assert state.mode == "software" and state.route == "eth0" and state.sync_frames == 100
    assert all(n is not None and n >= 50 for n in state.frames_to_ready)


def test_frames_without_the_key_after_ready_are_kept_at_60_fps():
    """Above 33 fps the IPA skips its controller on alternate frames: no SyncReady key there."""
    world = FakeCameraWorld(tuning_ready_frame=30)  # as SyncFrames 30 (a tuning file's "ready_frame")
    keyless = []
    api = world.api()
    real = api.Picamera2._process_request

    def spy(self, req, tid):
        if "SyncReady" not in req._metadata:
            keyless.append(self.num)
        return real(self, req, tid)

    api.Picamera2._process_request = spy
    src = create_source(source_settings("picamera2", [64, 48], 500, fps=60.0, timeout_s=1.0,
                                        picamera2={"sync_frames": 30}),
                        api=api, route_reader=with_route())
    with src:
        frames = take(src, 12)
    slots = [decode_slot(f.left)[0] for f in frames]
    assert slots == list(range(slots[0], slots[0] + 12))
    assert len(keyless) >= 12                               # about half the frames carried no key


def test_sync_frames_outside_the_advertised_range_is_applied_with_a_warning(caplog):
    world = FakeCameraWorld()
    src = create_source(source_settings("picamera2", [64, 48], 500, picamera2={"sync_frames": 40}),
                        api=world.api(), route_reader=with_route())
    with caplog.at_level(logging.WARNING), src:
        take(src, 1)
    assert any("sync_frames = 40" in r.getMessage() and "100..100000" in r.getMessage() for r in caplog.records)
    assert world.instances[0].configured["controls"]["SyncFrames"] == 40


def test_first_pair_timeout_follows_sync_frames_and_fps():
    src = create_source(shipped_source(), api=FakeCameraWorld().api(), route_reader=with_route())
    src._sync = True
    assert src.first_pair_timeout_s == pytest.approx(102 / 30.0 + 2.0)
    src = create_source(shipped_source(fps=60.0, picamera2=replace(shipped_source().picamera2, sync_frames=500)),
                        api=FakeCameraWorld().api(), route_reader=with_route())
    src._sync = True
    assert src.first_pair_timeout_s == pytest.approx(502 / 60.0 + 2.0)
    src._sync = False
    assert src.first_pair_timeout_s == 2.0


# ------------------------------------------------------------------ the fake against libcamera's rules

def _run_sync(world, role, fps, frames, sync_frames=None, skip_phase=0, start=0):
    period = int(round(1e9 / fps))
    alg = _SyncAlgorithm(world, role, period, sync_frames, skip_phase)
    return [alg.status(slot, slot * period) for slot in range(start, start + frames)]


def test_fake_server_ready_after_sync_frames_and_latched():
    world = FakeCameraWorld()
    md = _run_sync(world, _SyncModeEnum.Server, 30.0, 140)            # tuning default: kDefaultReadyFrame 100
    ready = [m["SyncReady"] for m in md]
    assert ready.index(True) == 100 and all(ready[100:])
    assert md[100]["SyncTimer"] == 0 and md[0]["SyncTimer"] > 0 and md[120]["SyncTimer"] < 0
    md = _run_sync(FakeCameraWorld(), _SyncModeEnum.Server, 30.0, 60, sync_frames=40)
    assert [m["SyncReady"] for m in md].index(True) == 40


def test_fake_client_waits_for_the_server_packet():
    world = FakeCameraWorld()
    server = _SyncAlgorithm(world, _SyncModeEnum.Server, 33_333_333, 100, 0)
    client = _SyncAlgorithm(world, _SyncModeEnum.Client, 33_333_333, None, 0)
    out = []
    for slot in range(120):
        t = slot * 33_333_333
        out.append((server.status(slot, t), client.status(slot, t)))
    assert all("SyncTimer" not in c and c["SyncReady"] is False for _, c in out[:30])  # no packet before frame 30
    assert "SyncTimer" in out[30][1] and out[30][1]["SyncReady"] is False
    assert [c["SyncReady"] for _, c in out].index(True) == 100 == [s["SyncReady"] for s, _ in out].index(True)


def test_fake_skips_the_controller_above_33_fps_and_without_a_route():
    md = _run_sync(FakeCameraWorld(), _SyncModeEnum.Server, 60.0, 20)
    assert ["SyncReady" in m for m in md] == [True, False] * 10
    md = _run_sync(FakeCameraWorld(), _SyncModeEnum.Server, 60.0, 20, skip_phase=1)
    assert ["SyncReady" in m for m in md] == [False, True] * 10
    md = _run_sync(FakeCameraWorld(), _SyncModeEnum.Server, 30.0, 20)
    assert all("SyncReady" in m for m in md)
    md = _run_sync(FakeCameraWorld(multicast_route=False), _SyncModeEnum.Client, 30.0, 20)
    assert md == [{}] * 20


def test_a_sync_start_longer_than_the_unit_allows_is_refused_before_systemd_kills_it():
    """1000 SyncFrames (libcamera's advertised default) at 15 fps: 67 s, past TimeoutStartSec=60."""
    from stereopath.device.errors import ConfigError

    slow = shipped_source(fps=15.0, picamera2=replace(shipped_source().picamera2, sync_frames=1000))
    src = create_source(slow, api=FakeCameraWorld().api(), route_reader=with_route())
    with pytest.raises(ConfigError, match=r"sync_frames = 1000 at 15 fps.*TimeoutStartSec"):
        with src:
            pass
    unit = (Path(__file__).resolve().parents[2] / "systemd" / "stereopath-capture.service").read_text()
    assert "TimeoutStartSec=60" in unit  # START_BUDGET_S leaves 15 s of it for the rest of the start
