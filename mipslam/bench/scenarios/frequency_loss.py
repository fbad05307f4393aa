"""Benchmark: the frequency-domain loss weight ``mapping.lambda_freq`` against rendering quality and tracking.

A data_synth ``line`` sequence (the camera slides along the +x wall, facing its test chart of fine print,
fine checkers and blinds, a checker ladder down to ~1 cm periods) is run through the full pipeline once per
weight, everything else equal (same seed, config, sequence). For each run: PSNR / SSIM / LPIPS of the final map
rendered from the estimated poses against the exact ground truth at the mapping resolution, on the keyframes
(training views) and on the other frames (novel views), the ATE RMSE of tracking, and the mapping time.

Run: ``mipslam bench --scenario frequency_loss --out bench_out/frequency`` (``--set frequency_loss.lambdas=0,10,100``
to choose the weights, ``--smoke`` for a smoke run). The table goes to OUT/bench.md and the record (machine,
parameters, rows; :mod:`mipslam.bench.record`) to OUT/bench.json; the sequence and one run folder per weight
stay in OUT.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mipslam.bench.record import write_benchmark
from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult
from mipslam.bench.scenarios.checkout import CONFIGS, parameters

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Options:
    lambdas: tuple[float, ...] = (0.0, 1.0, 10.0, 100.0)  # mapping.lambda_freq values, one run each
    width: int = 96
    height: int = 72
    frames: int = 12
    trajectory: str = "line"  # data_synth trajectory
    supersample: int = 4  # data_synth samples per pixel side
    config_overrides: tuple[str, ...] = ()  # config KEY=VALUE for every run


SMOKE = dict(lambdas=(0.0, 10.0), width=40, height=30, frames=3, supersample=2,
             config_overrides=("mapping.first_frame_iterations=10", "mapping.iterations=3", "tracking.iterations=3"))


def _run_one(sequence: Path, out: Path, weight: float, overrides: tuple[str, ...]) -> dict:
    from mipslam.config import load_config
    from mipslam.evaluation.render_eval import RenderEvalOptions, evaluate_render
    from mipslam.evaluation.run_eval import evaluate_run
    from mipslam.pipeline import run_slam

    run_dir = out / f"run_lambda_{weight:g}"
    config = load_config(CONFIGS / "synthetic.yaml",
                         overrides=[f"dataset.path={sequence}", f"mapping.lambda_freq={weight}", *overrides])
    start = time.perf_counter()
    run_slam(config, run_dir, evaluate=False)
    seconds = time.perf_counter() - start
    trajectory = evaluate_run(run_dir, render=False, report=False)["trajectory"]
    evaluation = evaluate_render(run_dir, RenderEvalOptions(frames="all", resolution="mapping", every=1,
                                                            showcase=False))
    timings = json.loads((run_dir / "timings.json").read_text())

    def mean(values):
        values = [v for v in values if v is not None]
        return float(np.mean(values)) if values else None

    row = {"lambda_freq": weight, "run_dir": str(run_dir), "seconds": seconds,
           "mapping_s": timings["stages"].get("mapping", {}).get("total_s"),
           "ate_rmse_m": trajectory["ate"]["rmse"], "gaussians": evaluation.protocol["map"]["gaussians"],
           "lpips_status": evaluation.lpips_status}
    for name, keep in (("train", True), ("novel", False)):
        views = [v for v in evaluation.views if v.is_keyframe == keep]
        row[name] = {"frames": len(views), "psnr": mean([v.psnr for v in views]), "ssim": mean([v.ssim for v in views]),
                     "lpips": mean([v.lpips for v in views]), "depth_l1_m": mean([v.depth_l1 for v in views])}
    return row


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _table(rows: list[dict], title: str) -> str:
    lines = [f"**{title}**", "",
             "| lambda_freq | PSNR train | SSIM train | LPIPS train | PSNR novel | SSIM novel | LPIPS novel | ATE RMSE [cm] "
             "| Gaussians | mapping [s] |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        t, n = r["train"], r["novel"]
        lines.append(f"| {r['lambda_freq']:g} | {_fmt(t['psnr'], '.2f')} | {_fmt(t['ssim'], '.4f')} | "
                     f"{_fmt(t['lpips'], '.4f')} | {_fmt(n['psnr'], '.2f')} | {_fmt(n['ssim'], '.4f')} | "
                     f"{_fmt(n['lpips'], '.4f')} | {r['ate_rmse_m'] * 100:.3f} | {r['gaussians']} | "
                     f"{_fmt(r['mapping_s'], '.0f')} |")
    return "\n".join(lines)


def run(options: Options, out_dir: Path) -> ScenarioResult:
    import data_synth

    sequence = out_dir / f"sequence_{options.trajectory}_{options.width}x{options.height}_{options.frames}"
    data_synth.generate(sequence, layout="replica", trajectory=options.trajectory, width=options.width,
                        height=options.height, frames=options.frames, seed=0, supersample=options.supersample)
    rows = []
    for weight in options.lambdas:
        rows.append(_run_one(sequence, out_dir, weight, options.config_overrides))
        log.info("lambda_freq=%g done: %s", weight, rows[-1])
        write_benchmark(out_dir, RECORD_NAME, parameters(options), rows, threads=torch.get_num_threads(),
                        overwrite=True)  # kept after every weight, so an interrupted run keeps what it measured
    title = (f"data_synth {options.trajectory}, {options.frames} frames at {options.width}x{options.height}, "
             f"mean over keyframes (train) and other frames (novel)")
    report = _table(rows, title)
    files = write_benchmark(out_dir, RECORD_NAME, parameters(options), rows, threads=torch.get_num_threads(),
                            markdown=report, overwrite=True)
    return ScenarioResult(files, report)
