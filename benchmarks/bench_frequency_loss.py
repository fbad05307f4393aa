"""Benchmark: the frequency-domain loss weight ``mapping.lambda_freq`` against rendering quality and tracking.

A data_synth ``line`` sequence (the camera slides along the +x wall, facing its test chart of fine print,
fine checkers and blinds, a checker ladder down to ~1 cm periods) is run through the full pipeline once per
weight, everything else equal (same seed, config, sequence). For each run: PSNR / SSIM / LPIPS of the final map
rendered from the estimated poses against the exact ground truth at the mapping resolution, on the keyframes
(training views) and on the other frames (novel views), the ATE RMSE of tracking, and the mapping time.

Run: ``.venv/bin/python benchmarks/bench_frequency_loss.py --out bench_out/frequency`` (``--lambdas 0,10,100``
to choose the weights, ``--quick`` for a smoke run). The table goes to OUT/frequency_loss.md and the record
(machine, parameters, rows; :mod:`mipslam.bench.record`) to OUT/frequency_loss.json.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch

from mipslam.bench.record import write_benchmark

REPO = Path(__file__).resolve().parent.parent


def _run_one(sequence: Path, out: Path, weight: float, overrides: list[str]) -> dict:
    from mipslam.config import load_config
    from mipslam.evaluation.render_eval import RenderEvalOptions, evaluate_render
    from mipslam.evaluation.run_eval import evaluate_run
    from mipslam.pipeline import run_slam

    run_dir = out / f"run_lambda_{weight:g}"
    config = load_config(REPO / "configs" / "synthetic.yaml",
                         overrides=[f"dataset.path={sequence}", f"mapping.lambda_freq={weight}", *overrides])
    start = time.perf_counter()
    run_slam(config, run_dir, evaluate=False)
    seconds = time.perf_counter() - start
    trajectory = evaluate_run(run_dir, render=False, report=False)["trajectory"]
    evaluation = evaluate_render(run_dir, RenderEvalOptions(frames="all", every=1, showcase=False))
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "bench_out" / "frequency")
    parser.add_argument("--lambdas", default="0,1,10,100", help="comma-separated weights")
    parser.add_argument("--width", type=int, default=96)
    parser.add_argument("--height", type=int, default=72)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--trajectory", default="line")
    parser.add_argument("--supersample", type=int, default=4)
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="extra config override")
    parser.add_argument("--quick", action="store_true", help="smoke run: 48x36, 4 frames, weights 0 and 10")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    if args.quick:
        args.width, args.height, args.frames, args.lambdas = 48, 36, 4, "0,10"
    weights = [float(v) for v in args.lambdas.split(",") if v.strip()]
    args.out.mkdir(parents=True, exist_ok=True)
    import data_synth

    sequence = args.out / f"sequence_{args.trajectory}_{args.width}x{args.height}_{args.frames}"
    if not (sequence / "synth.json").is_file():
        data_synth.generate(sequence, layout="replica", trajectory=args.trajectory, width=args.width,
                            height=args.height, frames=args.frames, seed=0, supersample=args.supersample,
                            overwrite=True)
    rows = []
    for weight in weights:
        rows.append(_run_one(sequence, args.out, weight, args.overrides))
        logging.getLogger("bench").info("lambda_freq=%g done: %s", weight, rows[-1])
        write_benchmark(args.out, "frequency_loss", _parameters(args), rows, threads=torch.get_num_threads(),
                        overwrite=True)  # kept after every weight, so an interrupted run keeps what it measured
    title = (f"data_synth {args.trajectory}, {args.frames} frames at {args.width}x{args.height}, "
             f"mean over keyframes (train) and other frames (novel)")
    report = _table(rows, title)
    print(report)
    write_benchmark(args.out, "frequency_loss", _parameters(args), rows, threads=torch.get_num_threads(),
                    markdown=report, overwrite=True)
    return 0


def _parameters(args) -> dict:
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}


if __name__ == "__main__":
    sys.exit(main())
