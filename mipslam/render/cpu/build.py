"""Compile the C++ rasterizer (raster_ext.cpp) into plain shared libraries, once, when mipslam is installed.

No mipslam command compiles: ``pip install`` (setup.py) and ``./scripts/setup`` call :func:`build_all`, and
:mod:`mipslam.render.cpu.library` only loads what they left. This module uses the standard library only, so
setup.py runs it without torch (the package builds in pip's isolated environment, which never has to
download torch) and scripts/setup runs it as a plain script. The library has no torch or Python headers and
a C interface; mipslam loads it with ctypes.

Portability: each ISA is one library, ``_raster_baseline`` (the compiler's default target, x86-64 SSE2
on PCs) and, on x86-64, ``_raster_avx2`` (``-mavx2 -mfma``). Never ``-march=native``: the loader asks the
baseline library whether this CPU runs AVX2 and FMA (``__builtin_cpu_supports``) and loads the avx2 one
only then, so one build runs on every x86-64 CPU. Separate libraries (not two object files in one) keep
the inline functions and std templates of the two ISAs apart: a linker merging them could hand AVX2 code
to the baseline path.

Each library embeds :func:`source_hash` (the sources and the flags); the loader refuses a library whose
hash differs from the sources next to it (a checkout changed after the build) and says to rebuild.

Developer command (rebuild after editing the C++; ``--if-stale`` does nothing when the libraries are current)::

    python -m mipslam.render.cpu.build [--if-stale] [--isa baseline|avx2]
    python mipslam/render/cpu/build.py  [--if-stale]          # the same, without importing mipslam (torch)

Environment: ``CXX`` (compiler, default ``c++``), ``MIPSLAM_CPU_CFLAGS`` (extra flags appended at build
time, e.g. ``-march=native`` for a build that only ever runs on this machine; not part of the hash).
"""
from __future__ import annotations

import argparse
import hashlib
import os
import platform
import shlex
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

SOURCE_DIR = Path(__file__).resolve().parent
SOURCES = ("raster_ext.cpp",)
HEADERS = ("check.h", "direct_align.h", "feature_match.h", "footprint_simd.h", "simd_math.h", "projection.h",
           "rgbd_loss.h", "ssim_loss.h")
#: -O3, OpenMP, IEEE-exact maths (no -ffast-math: the kernels rely on NaN tests and the exp rounding trick).
COMMON_FLAGS = ("-O3", "-std=c++17", "-fopenmp", "-fno-math-errno", "-fno-trapping-math", "-fPIC", "-shared",
                "-fvisibility=hidden", "-fvisibility-inlines-hidden", "-Wno-psabi")
#: Flags of each ISA build (x86-64: baseline and avx2; elsewhere baseline only).
ISA_FLAGS = {"baseline": (), "avx2": ("-mavx2", "-mfma")}
LIBRARY_STEM = "_raster_"


class BuildError(RuntimeError):
    """The compiler is missing or failed (the message holds the end of its output)."""


def is_x86_64() -> bool:
    return platform.machine().lower() in ("x86_64", "amd64")


def isas() -> tuple[str, ...]:
    """The library builds of this platform, baseline first."""
    return ("baseline", "avx2") if is_x86_64() else ("baseline",)


def library_path(isa: str, folder: Path = SOURCE_DIR) -> Path:
    """Where the library of ``isa`` lives: next to the sources, named like an extension module of this
    interpreter (``_raster_avx2.cpython-311-x86_64-linux-gnu.so``), which is where setuptools puts it."""
    return folder / f"{LIBRARY_STEM}{isa}{sysconfig.get_config_var('EXT_SUFFIX') or '.so'}"


def source_hash(isa: str, folder: Path = SOURCE_DIR) -> str:
    """Hash of the sources, the headers and the flags of ``isa`` (16 hex digits); embedded in the library."""
    digest = hashlib.sha256()
    for name in SOURCES + HEADERS:
        digest.update(name.encode())
        digest.update((folder / name).read_bytes())
    digest.update(" ".join(COMMON_FLAGS + ISA_FLAGS[isa]).encode())
    return digest.hexdigest()[:16]


def compiler() -> list[str]:
    """The C++ compiler command (``$CXX`` or ``c++``; may be several words, e.g. ``ccache g++``)."""
    return shlex.split(os.environ.get("CXX", "").strip() or "c++")


def compile_command(isa: str, output: Path) -> list[str]:
    flags = list(COMMON_FLAGS + ISA_FLAGS[isa]) + shlex.split(os.environ.get("MIPSLAM_CPU_CFLAGS", ""))
    defines = [f'-DMIPSLAM_SOURCE_HASH="{source_hash(isa)}"']
    return compiler() + flags + defines + ["-o", str(output)] + [str(SOURCE_DIR / s) for s in SOURCES]


def start_compile(isa: str, output: Path) -> tuple[subprocess.Popen, Path]:
    """Start compiling ``isa`` into a temporary file beside ``output``; :func:`finish_compile` installs it."""
    output.parent.mkdir(parents=True, exist_ok=True)
    handle, partial = tempfile.mkstemp(prefix=f".{output.name}.", suffix=".partial", dir=output.parent)
    os.close(handle)
    command = compile_command(isa, Path(partial))
    try:
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    except OSError as exc:
        Path(partial).unlink(missing_ok=True)
        raise BuildError(f"cannot run the C++ compiler '{command[0]}' ({exc.strerror or exc}); install g++ or "
                         "clang++ (Debian/Ubuntu: apt-get install g++) or set CXX") from None
    return process, Path(partial)


def finish_compile(isa: str, output: Path, process: subprocess.Popen, partial: Path) -> None:
    """Wait for the compiler; on success atomically replace ``output`` (a running process keeps the old one)."""
    log_text, _ = process.communicate()
    if process.returncode != 0:
        partial.unlink(missing_ok=True)
        tail = "\n".join(log_text.strip().splitlines()[-25:])
        raise BuildError(f"compiling the {isa} rasterizer failed ({' '.join(process.args[:1])} exit "
                         f"{process.returncode}):\n{tail}")
    partial.chmod(0o755)  # mkstemp made it private; an installed library is readable by every user
    os.replace(partial, output)


def compile_library(isa: str, output: Path) -> None:
    """Compile the library of ``isa`` into ``output`` (raises :class:`BuildError`)."""
    finish_compile(isa, output, *start_compile(isa, output))


def embedded_hash(path: Path) -> str | None:
    """The source hash a built library carries (read from the file, without loading it), or None."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    marker = b"mipslam-source-hash:"
    at = data.find(marker)
    return data[at + len(marker):at + len(marker) + 16].decode("ascii", "replace") if at >= 0 else None


def is_current(isa: str, folder: Path = SOURCE_DIR) -> bool:
    """True if the library of ``isa`` exists and was built from the sources next to it."""
    return embedded_hash(library_path(isa, folder)) == source_hash(isa, folder)


def build_all(selected: tuple[str, ...] | None = None, *, if_stale: bool = False) -> dict[str, str]:
    """Build the libraries of this platform in place, in parallel. Returns {isa: "built" | "current" | error}.

    The baseline library is required (raises :class:`BuildError` when it fails); an avx2 failure (an old
    compiler) is reported in the result and the baseline library is used.
    """
    selected = selected or isas()
    results, running = {}, {}
    for isa in selected:
        if if_stale and is_current(isa):
            results[isa] = "current"
            continue
        try:
            running[isa] = start_compile(isa, library_path(isa))
        except BuildError as exc:
            results[isa] = str(exc)
    for isa, (process, partial) in running.items():
        try:
            finish_compile(isa, library_path(isa), process, partial)
            results[isa] = "built"
        except BuildError as exc:
            results[isa] = str(exc)
    if "baseline" in selected and results["baseline"] not in ("built", "current"):
        raise BuildError(results["baseline"])
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mipslam.render.cpu.build",
                                     description="Compile mipslam's C++ rasterizer in place (next to its sources).")
    parser.add_argument("--if-stale", action="store_true", help="only rebuild libraries that are missing or stale")
    parser.add_argument("--isa", choices=sorted(ISA_FLAGS), action="append",
                        help="build only this ISA (repeatable; default: all of this platform)")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    try:
        results = build_all(tuple(args.isa) if args.isa else None, if_stale=args.if_stale)
    except BuildError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    for isa, result in results.items():
        print(f"{library_path(isa).name}: {result}")
    print(f"({time.perf_counter() - start:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
