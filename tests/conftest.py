"""Shared fixtures: paths to the real data (skipped with a reason when absent) and tiny synthetic data."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = Path(os.environ.get("MIPSLAM_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))


def shared_data_path(name: str) -> Path:
    """Path to a folder of ../shared/data, or skip the test (a user's clone has no real data)."""
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"real data '{name}' not found at {path} (set MIPSLAM_SHARED_DATA to its folder)")
    return path


@pytest.fixture
def replica_room0_path() -> Path:
    return shared_data_path("replica_room0_20")


@pytest.fixture
def tum_fr1_xyz_path() -> Path:
    return shared_data_path("tum_fr1_xyz_10")


@pytest.fixture
def tum_trajectories_path() -> Path:
    return shared_data_path("tum_trajectories")
