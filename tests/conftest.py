"""Shared fixtures: the real third-party data lives in ../shared/data beside the project root."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("STEREOPATH_DATA", ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA.is_dir():
        pytest.skip(f"real test data not found at {DATA} (set STEREOPATH_DATA)")
    return DATA


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return ROOT


# /proc/net/route with a host route to libcamera's sync group through lo: what `device install`
# gives a box, so picamera2 tests never depend on this machine's network
LOOPBACK_SYNC_ROUTE = ("Iface\tDestination\tGateway \tFlags\tRefCnt\tUse\tMetric\tMask\t\tMTU\tWindow\tIRTT\n"
                       "lo\tFAFFFFEF\t00000000\t0005\t0\t0\t0\tFFFFFFFF\t0\t0\t0\n")


@pytest.fixture(autouse=True)
def _routing_table_stand_in(monkeypatch):
    """The picamera2 backend's route check reads this instead of the real /proc/net/route."""
    monkeypatch.setattr("stereopath.device.capture.sources.csi.read_proc_net_route", lambda: LOOPBACK_SYNC_ROUTE)
