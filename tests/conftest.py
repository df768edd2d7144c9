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
