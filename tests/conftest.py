"""Shared fixtures: the real-data folder (skip when absent, fail when CI=true), and hypothesis's CI profile."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

# CI draws the same examples on every run (a red CI is then reproducible, and a new counterexample is found
# by the random local runs and recorded, not by the gate of a submission); locally examples stay random.
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
if os.environ.get("CI") == "true":
    settings.load_profile("ci")

REAL_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "real_data"


@pytest.fixture(scope="session")
def real_data() -> Path:
    """``../shared/real_data`` beside the checkout."""
    if not REAL_DATA.is_dir():
        msg = f"real GIS data not found at {REAL_DATA}"
        if os.environ.get("CI") == "true":
            pytest.fail(msg + " (CI=true: real-data tests must run)")
        pytest.skip(msg)
    return REAL_DATA


@pytest.fixture(scope="session")
def swellendam(real_data: Path) -> Path:
    """The Swellendam folder of real OSM layers and SRTM DEM."""
    path = real_data / "swellendam"
    if not path.is_dir():
        if os.environ.get("CI") == "true":
            pytest.fail(f"{path} missing (CI=true)")
        pytest.skip(f"{path} missing")
    return path
