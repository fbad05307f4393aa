"""Shared fixtures: paths to the real data (skipped with a reason when absent) and tiny synthetic data."""
from __future__ import annotations

import os
from pathlib import Path

# As scripts/test sets it, for a bare `pytest` too: MKL's AVX-512 and AVX2 kernels round differently and the
# suite's 40x30 runs amplify that. MKL reads this when torch loads it, so it is set before anything imports torch.
os.environ.setdefault("MKL_ENABLE_INSTRUCTIONS", "AVX2")

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


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory) -> Path:
    """A 6-frame 40x30 data_synth loop (Replica layout)."""
    import data_synth

    out = tmp_path_factory.mktemp("synth") / "seq"
    data_synth.generate(out, layout="replica", trajectory="loop", width=40, height=30, frames=6, seed=0, supersample=2)
    return out


def _one_frame_map(tmp_path_factory, width: int, height: int):
    """(sequence folder, config, sequence, frozen map of frame 0) on a 2-frame width x height loop."""
    import data_synth
    from tiny_runs import map_of_first_frame

    seq = tmp_path_factory.mktemp(f"track{width}") / "seq"
    data_synth.generate(seq, layout="replica", trajectory="loop", width=width, height=height, frames=2, seed=0,
                        supersample=2)
    config, sequence, gmap, _, _ = map_of_first_frame(seq, 60)
    return seq, config, sequence, gmap.activated().detached()


@pytest.fixture(scope="module")
def one_frame_map(tmp_path_factory):
    """The one-frame map at 64x48: at 40x30 the map of one frame is too coarse to pin the pose to a few
    millimetres."""
    return _one_frame_map(tmp_path_factory, 64, 48)


@pytest.fixture(scope="module")
def one_frame_map_128(tmp_path_factory):
    """The one-frame map at 128x96: at 64x48 a 2 cm / 1 degree error moves the image by under a pixel, below
    what a render of a one-frame map resolves (the direct alignment's tests)."""
    return _one_frame_map(tmp_path_factory, 128, 96)
