"""``mipslam bench``: run settings (presets x sweeps) on a sequence, repeated, and measure the speed/accuracy trade.

Pieces (each usable alone, most of them pure):

* :mod:`~mipslam.bench.spec`     what to run: :class:`BenchSpec`, :func:`parse_sweep`, :func:`plan_jobs`;
* :mod:`~mipslam.bench.execute`  how: :func:`execute_job` (``mipslam run`` + ``mipslam eval`` child
  processes), :class:`LocalExecutor` (default, sequential), :class:`RayExecutor` (``--ray``), :func:`run_jobs`;
* :mod:`~mipslam.bench.summary`  statistics: :func:`summarize`, :func:`pareto_front`, :func:`fit_power_law`;
* :mod:`~mipslam.bench.report`   files: :func:`write_outputs` (bench.json, bench.md, bench.png);
* :mod:`~mipslam.bench.scenarios` the project's other benchmarks (``mipslam bench --scenario NAME``), each
  writing its record through :mod:`~mipslam.bench.record`.

:func:`run_bench` chains them. docs/bench.md describes the protocol.
"""
from __future__ import annotations

import importlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path

from typing import TYPE_CHECKING

from mipslam.errors import MipslamError

if TYPE_CHECKING:
    from mipslam.bench.execute import Executor, JobResult
    from mipslam.bench.report import BenchFiles
    from mipslam.bench.spec import BenchSpec, Setting
    from mipslam.bench.summary import SettingSummary

# The public names, imported on first use: ``import mipslam.bench`` (and its ``scenarios`` and ``record``)
# stays free of torch, so a scenario can set the thread environment before torch and numpy load.
_EXPORTS = {
    "mipslam.bench.execute": ("Executor", "JobResult", "LocalExecutor", "RayExecutor", "execute_job", "run_jobs"),
    "mipslam.bench.report": ("BenchFiles", "machine_info", "write_outputs"),
    "mipslam.bench.spec": ("BenchSpec", "Job", "Setting", "Sweep", "Target", "check_out_dir", "default_out_dir",
                           "parse_presets", "parse_sweep", "plan_jobs", "plan_settings", "resolve_target"),
    "mipslam.bench.summary": ("PowerLaw", "SettingSummary", "Spread", "fit_power_law", "pareto_front", "spread",
                              "summarize"),
}
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted([*_MODULE_OF, "BenchOutcome", "run_bench"])


def __getattr__(name: str):
    if name in _MODULE_OF:
        return getattr(importlib.import_module(_MODULE_OF[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


log = logging.getLogger(__name__)

PROGRESS_FILE = "jobs.jsonl"  # one finished job per line, written as the bench goes (kept after an interrupt)


@dataclass(frozen=True)
class BenchOutcome:
    files: BenchFiles
    rows: tuple[JobResult, ...]
    settings: tuple[SettingSummary, ...]

    @property
    def failed(self) -> int:
        return sum(not r.ok for r in self.rows)

    def describe(self) -> str:
        lines = [f"bench: {len(self.rows)} jobs, {len(self.settings)} settings, {self.failed} failed"]
        for s in self.settings:
            def med(x, digits):
                return "–" if x is None else f"{x.median:.{digits}f}"
            front = "".join(f for f, on in (("A", s.on_front_ate), ("P", s.on_front_psnr)) if on)
            lines.append(f"  {s.setting}: {med(s.fps, 2)} frames/s, ATE {med(s.ate_rmse_cm, 3)} cm, "
                         f"lost {med(s.lost_frames, 0)}, PSNR {med(s.psnr_db, 2)} dB novel / "
                         f"{med(s.psnr_train_db, 2)} dB train "
                         f"({s.jobs - s.failed}/{s.jobs} ok){' front ' + front if front else ''}")
        names = [self.files.markdown.name, self.files.plot.name, *(p.name for p in self.files.sweep_plots)]
        lines.append(f"results: {self.files.json}, {', '.join(names)}")
        return "\n".join(lines)


def _request(spec: BenchSpec, settings: list[Setting]) -> dict:
    return {
        "target": str(spec.target.source),
        "kind": spec.target.kind, "config": str(spec.target.config_path),
        "presets": [p or "none" for p in spec.presets],
        "sweeps": {s.key: list(s.texts) for s in spec.sweeps}, "overrides": list(spec.overrides),
        "repeat": spec.repeat, "threads": spec.threads, "seed": spec.seed, "max_frames": spec.max_frames,
        "timeout_s": spec.timeout_s, "mipslam": spec.run_mipslam,
        "peers": list(spec.peers), "peer_repeat": spec.peer_repeat, "peer_python": spec.peer_python,
        "peer_options": {p.replace("-", "_"): spec.peer_options.to_dict()[p.replace("-", "_")] for p in spec.peers},
        "settings": [{"index": s.index, "label": s.label, "system": s.system, "overrides": list(s.overrides),
                      "threads": s.threads, "seed": s.seed, "repeats": s.repeats or spec.repeat} for s in settings],
    }


def run_bench(spec: BenchSpec, executor: Executor | None = None) -> BenchOutcome:
    """Plan, run (``executor``, default sequential local processes), summarise and write the outputs."""
    from mipslam.bench.execute import LocalExecutor, run_jobs
    from mipslam.bench.report import machine_info, write_outputs
    from mipslam.bench.spec import check_out_dir, plan_jobs, plan_settings
    from mipslam.bench.summary import summarize

    out_dir = Path(spec.out_dir)
    check_out_dir(out_dir)
    settings = plan_settings(spec)
    jobs = plan_jobs(spec, settings)
    executor = executor or LocalExecutor()
    threads = sorted({s.threads for s in settings})
    machine = machine_info(threads[0] if len(threads) == 1 else threads)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MipslamError(f"{out_dir}: cannot create the output folder ({exc.strerror or exc})") from None
    progress = out_dir / PROGRESS_FILE
    log.info("bench: %d settings, %d jobs into %s (%s)", len(settings), len(jobs), out_dir,
             executor.describe()["executor"])

    def on_result(i: int, row: JobResult) -> None:
        with progress.open("a", encoding="utf-8") as handle:
            handle.write(json.dumps(row.to_dict()) + "\n")
        if row.ok:
            log.info("[%d/%d] %s r%d: %.2f frames/s, ATE %.3f cm, lost %s, PSNR %s dB", i + 1, len(jobs), row.setting,
                     row.repeat, row.fps or float("nan"), row.ate_rmse_cm or float("nan"),
                     "–" if row.lost_frames is None else row.lost_frames,
                     "–" if row.psnr_db is None else f"{row.psnr_db:.2f}")
        else:
            log.warning("[%d/%d] %s r%d failed: %s", i + 1, len(jobs), row.setting, row.repeat, row.error)

    rows = run_jobs(jobs, executor, on_result)
    summaries = summarize(rows)
    files = write_outputs(out_dir, machine, executor.describe(), _request(spec, settings), rows, summaries)
    return BenchOutcome(files, tuple(rows), tuple(summaries))
