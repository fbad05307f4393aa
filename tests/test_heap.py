"""Returning freed heap memory to the OS (mipslam.heap), and the pipeline's use of it."""
from __future__ import annotations

import ctypes
import ctypes.util
import os
from pathlib import Path

import pytest

import mipslam.pipeline as pipeline
import mipslam.run_control as run_control
from mipslam.config import load_config
from mipslam.errors import ConfigError
from mipslam.heap import heap_trim_available, release_free_heap, set_mmap_threshold

REPO = Path(__file__).resolve().parent.parent


def resident_bytes() -> int:
    with open("/proc/self/statm") as stream:
        return int(stream.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(not heap_trim_available() or not Path("/proc/self/statm").exists(),
                    reason="needs glibc's malloc_trim and /proc (Linux)")
def test_release_returns_fragmented_free_blocks_to_the_os():
    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]
    block = 64 * 1024  # below glibc's mmap threshold: these live in the arena
    blocks = [libc.malloc(block) for _ in range(1024)]  # 64 MiB
    for pointer in blocks:
        ctypes.memset(pointer, 1, block)  # touch every page
    for pointer in blocks[:-1]:  # the last block pins the top of the heap: free space cannot shrink by itself
        libc.free(pointer)
    before = resident_bytes()
    assert release_free_heap() is True
    after = resident_bytes()
    libc.free(blocks[-1])
    assert before - after > 32 * 2**20, f"RSS {before / 2**20:.0f} -> {after / 2**20:.0f} MiB"


MMAP_PROBE = """
import ctypes, ctypes.util, sys
from mipslam.heap import set_mmap_threshold
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
class Info(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()]
libc.mallinfo2.restype = Info
if sys.argv[1] == "fixed":
    assert set_mmap_threshold(64 * 1024)
libc.free(libc.malloc(4 << 20))  # glibc's dynamic rule now raises its threshold to 4 MiB
before = libc.mallinfo2().hblkhd
block = libc.malloc(256 << 10)
print(libc.mallinfo2().hblkhd - before)
libc.free(block)
"""


@pytest.mark.skipif(not hasattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), "mallinfo2"),
                    reason="needs glibc >= 2.33 (mallinfo2) to observe where a block comes from")
def test_fixed_mmap_threshold_keeps_large_blocks_out_of_the_heap_after_a_large_free():
    import subprocess
    import sys

    def mmapped_bytes(mode: str) -> int:  # a fresh process: mallopt changes the whole process
        done = subprocess.run([sys.executable, "-c", MMAP_PROBE, mode], capture_output=True, text=True, check=True,
                              cwd=REPO)
        return int(done.stdout.strip())

    assert mmapped_bytes("dynamic") == 0  # the 256 KiB block went into the heap, where it can fragment
    assert mmapped_bytes("fixed") >= 256 << 10  # mapped, so free() gives it back to the OS


def test_set_mmap_threshold_rejects_a_non_positive_value():
    with pytest.raises(ValueError, match="positive"):
        set_mmap_threshold(0)


def test_release_is_safe_to_call_repeatedly():
    for _ in range(3):
        assert isinstance(release_free_heap(), bool)


def test_pipeline_releases_memory_every_n_frames(monkeypatch, tmp_path):
    import data_synth

    sequence = tmp_path / "seq"
    data_synth.generate(sequence, layout="replica", trajectory="loop", width=24, height=18, frames=5, seed=0,
                        supersample=1)
    calls = []
    monkeypatch.setattr(run_control, "release_free_heap", lambda: calls.append(1) or True)
    monkeypatch.setattr(run_control, "RELEASE_MEMORY_EVERY", 2)
    config = load_config("synthetic", overrides=[
        f"dataset.path={sequence}", "run.threads=1", "tracking.iterations=3",
        "mapping.iterations=2", "mapping.first_frame_iterations=3", "run.evaluate_at_end=false"])
    pipeline.run_slam(config, tmp_path / "run")
    assert len(calls) == 2  # after frames 2 and 4 of 5


def test_the_memory_cadence_is_no_config_key():
    with pytest.raises(ConfigError, match="run.release_memory_every.*internal constant of mipslam/run_control.py"):
        load_config("synthetic", overrides=["run.release_memory_every=2"])
    with pytest.raises(ConfigError, match="run.mmap_threshold_kib.*removed"):
        load_config("synthetic", overrides=["run.mmap_threshold_kib=64"])
