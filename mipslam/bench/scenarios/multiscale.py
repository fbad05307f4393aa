"""Benchmark: PSNR against rendering scale for each footprint mode.

A data_synth loop sequence is mapped by the full pipeline (``mipslam run``, tracking included) at one
resolution; the final map is then rendered from the estimated poses at 1/8, 1/4, 1/2, 1 and 2 times the
mapping resolution with the point, mip, ewa and eaa footprints and compared with the exact ground truth
rendered by data_synth at each resolution (``mipslam eval RUN --scales ... --modes ...``; protocol in
mipslam/evaluation/render_eval.py). The same is done on ../shared/data/replica_room0_20 (mapped at
300x170, i.e. dataset.downscale 4, ground truth = the 1200x680 originals area-resampled), skipped with a
message when that folder is absent.

The checks printed at the end are the issue's: at 1/4 and 1/8 eaa beats point by >= 3 dB and matches
(within 0.05 dB) or beats mip; at 1 all modes within 0.2 dB; at 2 eaa no worse than point (within 0.05 dB).
The main table renders *one* map (trained with the run's mode, eaa) with every footprint. ``multiscale.own_maps``
adds the Mip-Splatting-style comparison: the synthetic sequence is mapped once more per other mode
(``render.mode=point`` / ``mip``, used in tracking and mapping too) and each map is rendered in its own mode.

Run: ``mipslam bench --scenario multiscale --out bench_out/multiscale`` (``--set multiscale.run_dir=RUN``
evaluates an existing run folder instead of mapping a new sequence). Tables and checks go to OUT/bench.md, the
record to OUT/bench.json, the sequence and the run folders stay in OUT.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

from mipslam.bench.record import write_benchmark
from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult
from mipslam.bench.scenarios.checkout import CONFIGS, SHARED_DATA, optional_path, parameters

log = logging.getLogger(__name__)
SCALES = (0.125, 0.25, 0.5, 1.0, 2.0)
MODES = ("point", "mip", "ewa", "eaa")
TOLERANCE_DB = 0.05


@dataclass(frozen=True)
class Options:
    width: int = 128  # the data_synth loop's mapping resolution
    height: int = 96
    frames: int = 16
    supersample: int = 4  # data_synth samples per pixel side
    every: int = 2  # evaluate every k-th frame
    run_dir: str = ""  # evaluate this existing run folder instead of mapping the synthetic sequence
    replica: str = str(SHARED_DATA / "replica_room0_20")
    replica_frames: int = 20
    skip_replica: bool = False
    skip_synthetic: bool = False
    own_maps: bool = False  # also map each sequence with point and mip and render each map in its own mode
    config_overrides: tuple[str, ...] = ()  # config KEY=VALUE of every run


SMOKE = dict(width=32, height=24, frames=3, supersample=2, every=1, skip_replica=True,
             config_overrides=("mapping.first_frame_iterations=10", "mapping.iterations=3", "tracking.iterations=3"))


def _table(evaluation, title: str) -> str:
    lines = [f"**{title}** (PSNR dB / SSIM, mean over {evaluation.rows[0].frames} frames)", "",
             "| scale | size | " + " | ".join(MODES) + " | eaa - point | eaa - mip |",
             "|---|---|" + "---|" * len(MODES) + "---|---|"]
    for scale in SCALES:
        cells = [evaluation.row(scale, mode) for mode in MODES]
        eaa, point, mip = (evaluation.row(scale, m).psnr for m in ("eaa", "point", "mip"))
        lines.append(f"| {scale:g} | {cells[0].width}x{cells[0].height} | "
                     + " | ".join(f"{c.psnr:.2f} / {c.ssim:.3f}" for c in cells)
                     + f" | {eaa - point:+.2f} | {eaa - mip:+.2f} |")
    return "\n".join(lines)


def _checks(evaluation) -> list[tuple[str, bool]]:
    p = {(s, m): evaluation.row(s, m).psnr for s in SCALES for m in MODES}
    out = []
    for s in (0.25, 0.125):
        out.append((f"scale {s:g}: eaa - point = {p[s, 'eaa'] - p[s, 'point']:+.2f} dB >= 3", p[s, "eaa"] - p[s, "point"] >= 3.0))
        out.append((f"scale {s:g}: eaa - mip = {p[s, 'eaa'] - p[s, 'mip']:+.2f} dB >= -{TOLERANCE_DB}",
                    p[s, "eaa"] - p[s, "mip"] >= -TOLERANCE_DB))
    spread = max(p[1.0, m] for m in ("point", "mip", "eaa")) - min(p[1.0, m] for m in ("point", "mip", "eaa"))
    out.append((f"scale 1: spread of point/mip/eaa = {spread:.3f} dB <= 0.2", spread <= 0.2))
    out.append((f"scale 2: eaa - point = {p[2.0, 'eaa'] - p[2.0, 'point']:+.3f} dB >= -{TOLERANCE_DB}",
                p[2.0, "eaa"] - p[2.0, "point"] >= -TOLERANCE_DB))
    return out


def _own_maps_table(name: str, config_path: Path, dataset_overrides: list[str], main_run: Path,
                    every: int | None, overrides: tuple[str, ...], results: dict) -> str:
    """Each mode's own map (trained with that footprint), rendered in that mode at every scale.

    ``main_run`` is the eaa run; the point and mip runs go beside it (``<main_run>_point``, ``_mip``).
    """
    from mipslam.evaluation.render_eval import RenderEvalOptions, evaluate_render

    runs = {"eaa": main_run}
    for mode in ("point", "mip"):
        runs[mode] = main_run.with_name(f"{main_run.name}_{mode}")
        if not (runs[mode] / "map.ply").is_file():
            _run(config_path, runs[mode], [*dataset_overrides, f"render.mode={mode}", *overrides])
    table = {}
    for mode, run_dir in runs.items():
        evaluation = evaluate_render(run_dir, RenderEvalOptions(frames="all", resolution="mapping", scales=SCALES,
                                                                modes=(mode,), every=every, lpips=False,
                                                                showcase=False))
        metrics = json.loads((run_dir / "metrics.json").read_text())
        table[mode] = {"rows": {row.scale: row for row in evaluation.rows},
                       "ate": metrics["trajectory"]["ate"]["rmse"], "gaussians": evaluation.protocol["map"]["gaussians"]}
    lines = [f"**{name}: each mode's own map** (the sequence mapped with render.mode = point / mip / eaa, each map "
             "rendered in its own mode; PSNR dB / SSIM)", "",
             "| scale | point (own map) | mip (own map) | eaa (own map) | eaa - point | eaa - mip |", "|---|---|---|---|---|---|"]
    for scale in SCALES:
        cells = {m: table[m]["rows"][scale] for m in ("point", "mip", "eaa")}
        lines.append(f"| {scale:g} | " + " | ".join(f"{cells[m].psnr:.2f} / {cells[m].ssim:.3f}" for m in cells)
                     + f" | {cells['eaa'].psnr - cells['point'].psnr:+.2f} | {cells['eaa'].psnr - cells['mip'].psnr:+.2f} |")
    lines += ["", "ATE RMSE " + ", ".join(f"{m} {table[m]['ate'] * 100:.2f} cm" for m in table)
              + "; Gaussians " + ", ".join(f"{m} {table[m]['gaussians']}" for m in table)]
    results[f"{name}, own maps"] = {m: {"run_dir": str(runs[m]), "ate_rmse_m": table[m]["ate"],
                               "rows": [r.to_dict() for r in table[m]["rows"].values()]} for m in table}
    return "\n".join(lines)


def _run(config_path: Path, run_dir: Path, overrides: list[str]) -> float:
    from mipslam.config import load_config
    from mipslam.pipeline import run_slam

    config = load_config(config_path, overrides=overrides)
    start = time.perf_counter()
    summary = run_slam(config, run_dir, evaluate=True)
    log.info("%s", summary.describe())
    return time.perf_counter() - start


def _evaluate(run_dir: Path, every: int | None):
    from mipslam.evaluation.render_eval import RenderEvalOptions, evaluate_render

    start = time.perf_counter()
    evaluation = evaluate_render(run_dir, RenderEvalOptions(frames="all", resolution="mapping", scales=SCALES,
                                                            modes=MODES, every=every, lpips=False,
                                                            showcase_scales=SCALES))
    return evaluation, time.perf_counter() - start


def _section(name: str, run_dir: Path, every: int | None, seconds_run: float | None, results: dict) -> str:
    evaluation, seconds_eval = _evaluate(run_dir, every)
    metrics = json.loads((run_dir / "metrics.json").read_text()) if (run_dir / "metrics.json").is_file() else {}
    ate = metrics.get("trajectory", {}).get("ate", {}).get("rmse")
    frames = evaluation.protocol["frames"]
    checks = _checks(evaluation)
    text = [_table(evaluation, name), "",
            f"run folder {run_dir}; {evaluation.protocol['map']['gaussians']} Gaussians; frames evaluated "
            f"{frames['evaluated']} ({frames['keyframes_among_evaluated']} keyframes); ground truth: "
            f"{evaluation.protocol['ground_truth']['source']}"
            + (f"; ATE RMSE {ate * 100:.2f} cm" if ate is not None else "")
            + (f"; mapping run {seconds_run:.0f} s" if seconds_run else "") + f"; evaluation {seconds_eval:.0f} s", ""]
    text += [f"- [{'x' if ok else ' '}] {what}" for what, ok in checks]
    results[name] = {"run_dir": str(run_dir), "rows": [r.to_dict() for r in evaluation.rows],
                     "protocol": evaluation.protocol, "ate_rmse_m": ate,
                     "checks": [{"check": w, "passed": ok} for w, ok in checks]}
    return "\n".join(text)


def run(options: Options, out_dir: Path) -> ScenarioResult:
    import torch

    sections, results = [], {"scales": SCALES, "modes": MODES, "torch_threads": torch.get_num_threads()}
    if not options.skip_synthetic:
        given = optional_path(options.run_dir)
        if given is not None:
            sections.append(_section("data_synth (given run)", given, options.every, None, results))
        else:
            import data_synth

            sequence = out_dir / "synth_sequence"
            data_synth.generate(sequence, layout="replica", trajectory="loop", width=options.width,
                                height=options.height, frames=options.frames, seed=0, supersample=options.supersample)
            run_dir = out_dir / "synth_run"
            seconds = _run(CONFIGS / "synthetic.yaml", run_dir, [f"dataset.path={sequence}", *options.config_overrides])
            name = f"data_synth loop, {options.frames} frames mapped at {options.width}x{options.height}"
            sections.append(_section(name, run_dir, options.every, seconds, results))
            if options.own_maps:
                sections.append(_own_maps_table(name, CONFIGS / "synthetic.yaml", [f"dataset.path={sequence}"],
                                                run_dir, options.every, options.config_overrides, results))
    if not options.skip_replica:
        replica = Path(options.replica)
        if not replica.is_dir():
            message = f"replica_room0_20 skipped: {replica} not found"
            log.warning("%s", message)
            sections.append(message)
        else:
            run_dir = out_dir / "replica_run"
            frames = options.replica_frames
            dataset = [f"dataset.path={replica}", f"dataset.max_frames={frames}"]
            seconds = _run(CONFIGS / "replica.yaml", run_dir, [*dataset, *options.config_overrides])
            name = f"Replica room0, {frames} frames mapped at 300x170 (downscale 4)"
            sections.append(_section(name, run_dir, options.every, seconds, results))
            if options.own_maps:
                sections.append(_own_maps_table(name, CONFIGS / "replica.yaml", dataset, run_dir, options.every,
                                                options.config_overrides, results))
    report = "\n\n".join(sections)
    files = write_benchmark(out_dir, RECORD_NAME, parameters(options), results, threads=torch.get_num_threads(),
                            markdown=report)
    return ScenarioResult(files, report)
