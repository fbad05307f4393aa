"""Benchmark: loop closure and SA-PGO inside the SLAM loop on a drifting data_synth loop sequence.

The sequence is data_synth's ``loop`` trajectory (by default 241 frames: one lap of the room, the
camera looking outwards and turning 360 degrees, back exactly at its start). Drift is injected
with a biased odometer (``BiasedOdometer`` of tests/fault_injection.py): each frame's pose is the
previous estimate times the ground-truth motion times ``Exp(bias)``; mapping, keyframes and loop
closure run as usual on those poses. The same sequence and bias run with

* loop closure off (``loop.enabled=false``),
* full LM (both spectral switches off),
* SA-PGO with spectral edge weighting only, with the low-frequency correction only, and with both
  (the default).

Reported per variant: ATE RMSE over all frames (SE(3) alignment, metres), loops verified / applied /
pruned, optimiser time; the map's PSNR at the loop's keyframes just before the lap-closing
correction (the first applied one), with only the poses corrected, after the Gaussians moved
with their anchors, and after the refinement steps that follow (from loops.json); and the final map's PSNR rendered at the estimated poses of
the keyframes after the lap (from frame 216 of 241 on, where the camera revisits the start; from
frame 22 in the quick run, where the small circle's loop first closes),
at the estimated poses of all keyframes, and at the ground-truth poses of all keyframes (the map
in the world frame).

Run: ``mipslam bench --scenario loop_closure --out bench_out/loop_closure`` (``--set loop_closure.size=quick``:
a 48-frame small circle at 40x30, about a minute). The biased odometer is a helper of the test suite: this
scenario runs from a source checkout only.
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import json  # noqa: E402
import logging  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

import data_synth  # noqa: E402
from mipslam.bench.record import write_benchmark  # noqa: E402
from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult  # noqa: E402
from mipslam.bench.scenarios.checkout import CONFIGS, import_test_helper, parameters  # noqa: E402
from mipslam.config import load_config  # noqa: E402
from mipslam.datasets import make_sequence  # noqa: E402
from mipslam.evaluation.image_metrics import psnr  # noqa: E402
from mipslam.evaluation.trajectory import evaluate_trajectory  # noqa: E402
from mipslam.geometry import se3_inverse  # noqa: E402
from mipslam.io.ply import read_map_ply  # noqa: E402
from mipslam.io.tum import read_tum_trajectory  # noqa: E402
from mipslam.pipeline import PipelineHooks, run_slam  # noqa: E402
from mipslam.errors import MipslamError  # noqa: E402
from mipslam.rendering import render_view  # noqa: E402

log = logging.getLogger(__name__)

# Each variant: config overrides, and the loop stage's constants it replaces (PipelineHooks.constants).
VARIANTS = {
    "loop off": (["loop.enabled=false"], {}),
    "full LM": ([], {"loop.spectral_edge_weighting": False, "loop.low_frequency_correction": False}),
    "SA-PGO: spectral": ([], {"loop.spectral_edge_weighting": True, "loop.low_frequency_correction": False}),
    "SA-PGO: low-freq": ([], {"loop.spectral_edge_weighting": False, "loop.low_frequency_correction": True}),
    "SA-PGO: both": ([], {"loop.spectral_edge_weighting": True, "loop.low_frequency_correction": True}),
}

SETTINGS = {
    "full": dict(frames=241, width=64, height=48, bias=[0.0005, 0.0, 0.0, 0.0, 0.0008, 0.0], after_lap_frame=216,
                 overrides=["mapping.first_frame_iterations=60", "mapping.iterations=12", "tracking.iterations=1",
                            "keyframes.window_size=4", "keyframes.random_past=1", "mapping.densify_pixel_stride=2"],
                 constants={"loop.icp_pixel_stride": 1, "loop.icp_voxel_m": 0.04}),
    "quick": dict(frames=48, width=40, height=30, bias=[0.004, 0.0, 0.0, 0.0, 0.01, 0.0], after_lap_frame=22,
                  overrides=["mapping.first_frame_iterations=30", "mapping.iterations=8", "tracking.iterations=1",
                             "keyframes.window_size=3", "keyframes.random_past=1", "mapping.densify_pixel_stride=2"],
                  constants={"loop.min_keyframe_gap": 6, "loop.icp_pixel_stride": 1, "loop.icp_voxel_m": 0.05,
                             "loop.odometry_drift_ratio": 0.3}),
}




@dataclass(frozen=True)
class Options:
    size: str = "full"  # a key of SETTINGS: full (241 frames at 64x48) or quick (48 frames at 40x30)
    variants: tuple[str, ...] = tuple(VARIANTS)  # keys of VARIANTS
    threads: int = 1  # torch threads of each run (1 on a busy machine)
    frames: int = 0  # > 0: only this many frames of the setting's sequence (a smoke run)
    keep: bool = False  # keep the sequence and the runs in OUT/work (default: a temporary folder)


SMOKE = dict(size="quick", variants=("SA-PGO: both",))  # the quick circle: it closes its loop, about 5 s


def keyframe_indices(run_dir: Path) -> list[int]:
    frames = json.loads((run_dir / "frames.json").read_text())["frames"]
    return [f["index"] for f in frames if f["keyframe_id"] >= 0]


@torch.no_grad()
def map_psnr(run_dir: Path, sequence, config, indices: list[int], poses: torch.Tensor) -> float:
    """Mean PSNR (dB) of the run's final map rendered at ``poses`` [N, 4, 4] against frames ``indices``."""
    gmap = read_map_ply(run_dir / "map.ply")
    gaussians = gmap.activated()
    values = []
    for index, T_wc in zip(indices, poses):
        frame = sequence[index]
        out = render_view(gaussians, se3_inverse(T_wc.to(torch.float64)).to(torch.float32), frame.intrinsics, config.render)
        values.append(float(psnr(out.color.clamp(0, 1), frame.color)))
    return float(np.mean(values))


def run_variant(name: str, sequence_dir: Path, work: Path, setting: dict, threads: int) -> dict:
    # run.diagnostics: loops.json then holds the map's PSNR around each correction (renders only; the run is the same)
    overrides = [f"dataset.path={sequence_dir}", f"run.threads={threads}", "run.checkpoint_every=0",
                 "run.diagnostics=true", *setting["overrides"], *VARIANTS[name][0]]
    config = load_config(CONFIGS / "synthetic.yaml", overrides=overrides)
    sequence = make_sequence(config.dataset)
    odometer = import_test_helper("fault_injection").BiasedOdometer(sequence.gt_T_wc, torch.tensor(setting["bias"], dtype=torch.float64))
    run_dir = work / name.replace(" ", "_").replace(":", "")
    start = time.perf_counter()
    constants = {**setting["constants"], **VARIANTS[name][1]}
    summary = run_slam(config, run_dir, evaluate=False, hooks=PipelineHooks(after_tracking=odometer, constants=constants))
    seconds = time.perf_counter() - start
    metrics = evaluate_trajectory(read_tum_trajectory(run_dir / "traj_gt.txt"),
                                  read_tum_trajectory(run_dir / "traj_est.txt"), alignment="se3")
    loops = json.loads((run_dir / "loops.json").read_text())
    applied = [o for o in loops["optimisations"] if o["applied"]]
    keyframes = keyframe_indices(run_dir)
    est_keyframes = torch.tensor(np.array(read_tum_trajectory(run_dir / "keyframes.txt").T_wc))
    after_lap = [k for k, index in enumerate(keyframes) if index >= setting["after_lap_frame"]]
    result = {
        "variant": name,
        "ate_rmse_m": float(metrics.ate.rmse),
        "ate_max_m": float(metrics.ate.max),
        "keyframes": summary.keyframes,
        "gaussians": summary.gaussians,
        "candidates": loops["summary"]["candidates"],
        "verified": loops["summary"]["verified"],
        "optimisations": loops["summary"]["optimisations"],
        "applied": loops["summary"]["corrections_applied"],
        "pruned": loops["summary"]["pruned_loop_edges"],
        "pgo_seconds": loops["summary"]["pgo_seconds"],
        "run_seconds": seconds,
        "map_psnr_gt_poses_db": map_psnr(run_dir, sequence, config, keyframes, sequence.gt_T_wc[keyframes]),
        "map_psnr_est_poses_db": map_psnr(run_dir, sequence, config, keyframes, est_keyframes),
        "keyframes_after_lap": after_lap,
        "map_psnr_after_lap_db": map_psnr(run_dir, sequence, config, [keyframes[k] for k in after_lap],
                                          est_keyframes[after_lap]),
    }
    if applied:
        first = applied[0]
        result["first_correction"] = {
            "query_keyframe": first["query_keyframe"], "query_frame": first["query_frame"],
            "keyframes": first["psnr_keyframes"], "max_correction_m": first["max_correction_m"],
            "max_correction_deg": first["max_correction_deg"],
            "psnr_before_db": first["psnr_before_db"], "psnr_poses_only_db": first["psnr_poses_only_db"],
            "psnr_moved_db": first["psnr_moved_db"],
            "psnr_after_db": first["psnr_after_db"]}
    return result


def table(results: list[dict]) -> str:
    lines = ["| variant | ATE RMSE [cm] | ATE max [cm] | loops verified / applied / pruned | PGO [s] | "
             "lap closure: PSNR before / poses only / map moved / refined [dB] | final map PSNR: after the lap / all keyframes / "
             "at GT poses [dB] | run [s] |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        first = r.get("first_correction")
        lap = (f"{np.mean(first['psnr_before_db']):.2f} / {np.mean(first['psnr_poses_only_db']):.2f} / "
               f"{np.mean(first['psnr_moved_db']):.2f} / {np.mean(first['psnr_after_db']):.2f} "
               f"(kf {first['keyframes']})") if first else "-"
        lines.append(f"| {r['variant']} | {100 * r['ate_rmse_m']:.2f} | {100 * r['ate_max_m']:.2f} | "
                     f"{r['verified']} / {r['applied']} / {r['pruned']} | {r['pgo_seconds']:.2f} | {lap} | "
                     f"{r['map_psnr_after_lap_db']:.2f} / {r['map_psnr_est_poses_db']:.2f} / "
                     f"{r['map_psnr_gt_poses_db']:.2f} | {r['run_seconds']:.0f} |")
    return "\n".join(lines)


def run(options: Options, out_dir: Path) -> ScenarioResult:
    if options.size not in SETTINGS:
        raise MipslamError(f"loop_closure.size {options.size!r}: choose {' or '.join(SETTINGS)}")
    unknown = [v for v in options.variants if v not in VARIANTS]
    if unknown:
        raise MipslamError(f"loop_closure.variants: unknown {', '.join(unknown)}; choose from {', '.join(VARIANTS)}")
    setting = SETTINGS[options.size]
    if options.frames > 0:
        setting = {**setting, "frames": options.frames}
    work = out_dir / "work" if options.keep else Path(tempfile.mkdtemp(prefix="mipslam_loop_closure_"))
    try:
        sequence_dir = work / "sequence"
        data_synth.generate(sequence_dir, layout="replica", trajectory="loop", width=setting["width"],
                            height=setting["height"], frames=setting["frames"], seed=0, supersample=2)
        results = []
        for name in options.variants:
            results.append(run_variant(name, sequence_dir, work, setting, options.threads))
            r = results[-1]
            log.info("%s: ATE %.2f cm, %d loops verified, %d applied, %d pruned, %.0f s", name, 100 * r["ate_rmse_m"],
                     r["verified"], r["applied"], r["pruned"], r["run_seconds"])
    finally:
        if not options.keep:
            shutil.rmtree(work, ignore_errors=True)
    report = table(results)
    files = write_benchmark(out_dir, RECORD_NAME, {**parameters(options), "setting": setting}, results,
                            threads=options.threads, markdown=report)
    return ScenarioResult(files, report)
