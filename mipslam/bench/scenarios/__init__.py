"""Benchmark scenarios: ``mipslam bench --scenario NAME [--out DIR] [--smoke] [--set NAME.KEY=VALUE]...``.

A scenario is one module of this package with

* ``Options``: a frozen dataclass, every setting of the scenario with its default (the one place they live);
  ``mipslam bench --scenario NAME --set NAME.KEY=VALUE`` overrides a field (cli.py turns the text into the
  field's type); scenarios that run the SLAM pipeline also take config overrides (``--set mapping.iterations=8``)
  through their ``config_overrides`` field;
* ``SMOKE``: the field values of its smallest size (``--smoke``: a few frames of tiny synthetic data, to check
  that it runs; its numbers describe nothing);
* ``run(options, out_dir) -> ScenarioResult``: measures and writes ``OUT/bench.json`` (the record of
  :mod:`mipslam.bench.record`: machine with thread count, parameters, results) and ``OUT/bench.md`` (the table),
  plus plots where the scenario has them.

Modules are imported only when their scenario runs (some need open3d or OpenCV). Scenarios marked
``needs_checkout`` use helpers of the test suite (``tests/``) and run only from a source checkout.
docs/bench.md lists what each one measures.
"""
from __future__ import annotations

import importlib
import time
from dataclasses import dataclass, fields
from pathlib import Path
from types import ModuleType

from mipslam.bench.record import BenchmarkFiles
from mipslam.errors import MipslamError

__all__ = ["SCENARIOS", "ScenarioInfo", "ScenarioResult", "default_scenario_out_dir", "load_scenario",
           "option_fields", "run_scenario", "smoke_options"]

RECORD_NAME = "bench"  # every scenario writes OUT/bench.json and OUT/bench.md


@dataclass(frozen=True)
class ScenarioInfo:
    name: str
    summary: str  # one line for --list-scenarios
    needs_checkout: bool = False  # imports a helper from tests/ (a source checkout only)


@dataclass(frozen=True)
class ScenarioResult:
    files: BenchmarkFiles
    summary: str  # a few lines for the terminal
    passed: bool = True  # False when a scenario with checks (kill_resume, long_run) found a failure
    plots: tuple[Path, ...] = ()


SCENARIOS: dict[str, ScenarioInfo] = {info.name: info for info in (
    ScenarioInfo("aliasing", "renderer footprints point/mip/ewa/eaa against the exact pixel integral at 1/8..1 "
                             "scale, and the EAA node cap"),
    ScenarioInfo("basin", "ATE and lost frames against the frame stride, mipslam beside its peers (a sweep of "
                          "mipslam bench)"),
    ScenarioInfo("frequency_loss", "mapping.lambda_freq against PSNR/SSIM/LPIPS on training and novel views and ATE"),
    ScenarioInfo("frontend", "frame-to-frame odometry of the front-end candidates (ORB+PnP, OpenCV, Open3D) "
                             "against ground truth"),
    ScenarioInfo("kill_resume", "kill -9 / Ctrl-C a run at random moments, resume it, compare with the "
                                "uninterrupted run"),
    ScenarioInfo("long_run", "a data_synth loop revisited for many laps: memory, time per frame, map size, "
                             "checkpoint files stay flat"),
    ScenarioInfo("loop_edges", "loop verification's error against ground truth beside the error its information "
                               "claims, on frame pairs of a sequence"),
    ScenarioInfo("loop_closure", "loop closure off / full LM / SA-PGO variants inside the SLAM loop on a "
                                 "drifting lap", needs_checkout=True),
    ScenarioInfo("multiscale", "one SLAM map rendered at 1/8..2 of its resolution with each footprint mode"),
    ScenarioInfo("pgo", "SA-PGO switches against plain full LM and Open3D on noisy synthetic pose graphs",
                 needs_checkout=True),
    ScenarioInfo("render_speed", "cpu and torch renderer backends: forward/backward time, rate, peak memory"),
    ScenarioInfo("scaling", "renderer time against Gaussian and pixel count, PGO time against keyframe count",
                 needs_checkout=True),
    ScenarioInfo("ssim_speed", "SSIM loss forward+backward: the torch reference against the compiled kernel"),
    ScenarioInfo("tracking_bias", "where tracking settles against a map fitted to one true view (coverage, "
                                  "depth bias, pose error)"),
)}


def load_scenario(name: str) -> ModuleType:
    """The module of scenario ``name`` (raises MipslamError for an unknown name)."""
    if name not in SCENARIOS:
        raise MipslamError(f"unknown benchmark scenario {name!r}; choose one of {', '.join(SCENARIOS)}")
    return importlib.import_module(f"mipslam.bench.scenarios.{name}")


def option_fields(name: str) -> dict[str, type]:
    """Field name -> the field's declared type (a string under postponed annotations) of scenario ``name``."""
    return {f.name: f.type for f in fields(load_scenario(name).Options)}


def smoke_options(name: str):
    """The scenario's Options at its smallest size."""
    module = load_scenario(name)
    return module.Options(**module.SMOKE)


def default_scenario_out_dir(name: str) -> Path:
    return Path("runs") / f"bench-{name}-{time.strftime('%Y%m%d-%H%M%S')}"


def run_scenario(name: str, options, out_dir: str | Path) -> ScenarioResult:
    """Run scenario ``name`` with ``options`` (its Options) into ``out_dir``, a new or empty folder."""
    from mipslam.bench.spec import check_out_dir

    out_dir = Path(out_dir)
    check_out_dir(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MipslamError(f"{out_dir}: cannot create the output folder ({exc.strerror or exc})") from None
    return load_scenario(name).run(options, out_dir)
