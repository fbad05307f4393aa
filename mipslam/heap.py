"""Give freed heap memory back to the operating system (glibc ``malloc_trim``).

Why: a long run allocates and frees tensors of ever-changing sizes (the map grows and is pruned,
checkpoints are serialised). glibc keeps the freed blocks inside its arenas, fragmented, so the
process's resident memory creeps up although the live data does not: on the 80x60 data_synth loop
the arenas' free space grew from 7 to 15 MiB over 300 frames while the allocated bytes grew by
1 MiB (docs/robustness.md, "Long runs"). ``malloc_trim(0)`` returns every free page of every arena.

:func:`set_mmap_threshold` attacks the cause: glibc serves a block from ``mmap`` (returned to the OS
on ``free``) only above a threshold that it raises after every large free, up to 32 MiB, so a run's
tensors soon all come from the heap and fragment it. A fixed threshold keeps them out of the heap:
at 64 KiB the heap stopped growing over the second lap of that run (docs/robustness.md, "Long runs", memory).
The price is a page-faulting ``mmap``/``munmap`` pair for every large tensor: 11 % fewer frames/s
on the 160x120 ``fast`` benchmark, so the pipeline does not apply it (a long-run measurement may).

On a C library without ``malloc_trim``/``mallopt`` (macOS, musl, Windows) both do nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
from functools import lru_cache


@lru_cache(maxsize=None)
def _libc_function(name: str, argtypes: tuple, restype):
    """A function of the process's C library, or None where the library has none of that name."""
    library = ctypes.util.find_library("c")
    if library is None:
        return None
    try:
        function = getattr(ctypes.CDLL(library), name)
    except (OSError, AttributeError):
        return None
    function.argtypes = list(argtypes)
    function.restype = restype
    return function


def _malloc_trim():
    """``int malloc_trim(size_t pad)``, or None."""
    return _libc_function("malloc_trim", (ctypes.c_size_t,), ctypes.c_int)


_M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter number (malloc.h)


def _mallopt():
    """``int mallopt(int param, int value)``, or None."""
    return _libc_function("mallopt", (ctypes.c_int, ctypes.c_int), ctypes.c_int)


def set_mmap_threshold(threshold_bytes: int) -> bool:
    """Serve every allocation of at least ``threshold_bytes`` from ``mmap``, with the threshold fixed
    (glibc's dynamic raising switched off); True if the C library took it. Affects the whole process."""
    if threshold_bytes <= 0:
        raise ValueError(f"mmap threshold must be positive, got {threshold_bytes}")
    mallopt = _mallopt()
    return bool(mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes))) if mallopt is not None else False


def heap_trim_available() -> bool:
    """Whether this process's C library can return free heap pages (glibc)."""
    return _malloc_trim() is not None


def release_free_heap() -> bool:
    """Return the free pages of every malloc arena to the OS; True if memory was released.

    Cost: one pass over the free lists (about a millisecond for a few hundred MiB of heap).
    """
    trim = _malloc_trim()
    return bool(trim(0)) if trim is not None else False
