"""One record format for every benchmark scenario (``mipslam bench --scenario NAME``, :mod:`mipslam.bench.scenarios`).

A record is a JSON file ``OUT/NAME.json`` (and, when the benchmark has a table, ``OUT/NAME.md``):

    {"format": "mipslam benchmark 1", "benchmark": NAME, "command": [...argv...],
     "machine": machine_info(threads), "parameters": {...}, "results": ...}

``machine`` is :func:`mipslam.bench.report.machine_info`: CPU model, logical and usable cores, load
at the start, threads, Python/torch versions, render backends, git commit. Non-finite floats
(JSON has none) are written as null. Files are written atomically; an existing record is never
overwritten unless ``overwrite`` is set.
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mipslam.errors import MipslamError

__all__ = ["RECORD_FORMAT", "BenchmarkFiles", "benchmark_record", "finite_or_none", "machine_line",
           "write_benchmark"]

RECORD_FORMAT = "mipslam benchmark 1"


def finite_or_none(obj: Any) -> Any:
    """``obj`` with every NaN/inf float (also numpy scalars and arrays, via ``tolist``) replaced by None."""
    if hasattr(obj, "tolist") and not isinstance(obj, (str, bytes)):
        obj = obj.tolist()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_none(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def benchmark_record(name: str, parameters: dict[str, Any], results: Any, *, threads: int | list[int],
                     machine: dict[str, Any] | None = None) -> dict[str, Any]:
    """The record of one benchmark run (see the module docstring); ``machine`` defaults to this machine."""
    from mipslam.bench.report import machine_info

    program = Path(sys.argv[0]).name
    program = "mipslam" if program in ("__main__.py", "cli.py") else program  # python -m mipslam ...
    return {"format": RECORD_FORMAT, "benchmark": name, "command": [program, *sys.argv[1:]],
            "machine": machine if machine is not None else machine_info(threads),
            "parameters": finite_or_none(parameters), "results": finite_or_none(results)}


def machine_line(machine: dict[str, Any]) -> str:
    """One line for a report: CPU, cores, load, threads, torch, commit."""
    git = machine.get("git") or {}
    commit = (git.get("commit") or "unknown")[:12] + (" (with uncommitted changes)" if git.get("uncommitted_changes")
                                                      else "")
    return (f"{machine.get('cpu_model')}, {machine.get('usable_cores')} usable of {machine.get('logical_cores')} logical "
            f"cores, load average {machine.get('load_average_1_5_15_min_at_start')} at the start; "
            f"{machine.get('threads_per_job')} threads; torch {machine.get('torch')}; mipslam at {commit}")


@dataclass(frozen=True)
class BenchmarkFiles:
    json: Path
    markdown: Path | None


def write_benchmark(out_dir: str | Path, name: str, parameters: dict[str, Any], results: Any, *,
                    threads: int | list[int], markdown: str | None = None, overwrite: bool = False,
                    machine: dict[str, Any] | None = None) -> BenchmarkFiles:
    """Write ``OUT/NAME.json`` (the record) and, with ``markdown``, ``OUT/NAME.md`` headed by the machine line.

    Raises MipslamError when a file exists and ``overwrite`` is False (a benchmark never destroys an
    earlier result unasked)."""
    from mipslam.io.run_folder import write_json_atomic, write_text_atomic

    out_dir = Path(out_dir)
    json_path = out_dir / f"{name}.json"
    md_path = out_dir / f"{name}.md" if markdown is not None else None
    for path in (json_path, md_path):
        if path is not None and path.exists() and not overwrite:
            raise MipslamError(f"{path}: exists; choose another --out or remove it")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MipslamError(f"{out_dir}: cannot create the output folder ({exc.strerror or exc})") from None
    record = benchmark_record(name, parameters, results, threads=threads, machine=machine)
    write_json_atomic(json_path, record)
    if md_path is not None:
        text = f"Machine: {machine_line(record['machine'])}.\nCommand: `{' '.join(record['command'])}`\n\n{markdown}"
        write_text_atomic(md_path, text.rstrip("\n") + "\n")
    return BenchmarkFiles(json_path, md_path)
