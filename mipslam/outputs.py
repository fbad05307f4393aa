"""Writes a run's outputs (DESIGN.md "Outputs of a run"): trajectories, keyframes, per-frame tracking
record, map, timings and a description of the run. Every file is written atomically."""
from __future__ import annotations

import math
import statistics

import numpy as np
import torch

from mipslam import __version__
from mipslam.config import Config
from mipslam.datasets import RGBDSequence
from mipslam.io.ply import write_map_ply
from mipslam.io.run_folder import RunFolder, write_json_atomic
from mipslam.io.tum import write_tum_trajectory
from mipslam.state import SLAMState

RUN_INFO = "run.json"
FRAMES = "frames.json"


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def write_run_outputs(folder: RunFolder, state: SLAMState, sequence: RGBDSequence, config: Config) -> None:
    frames = state.frames
    timestamps = np.array([f.timestamp for f in frames], dtype=np.float64)
    write_tum_trajectory(folder.traj_est, timestamps, state.poses())
    if sequence.gt_T_wc is not None:
        with_gt = [i for i, f in enumerate(frames) if bool(sequence.gt_valid[f.index])]
        if with_gt:
            write_tum_trajectory(folder.traj_gt, timestamps[with_gt], sequence.gt_T_wc[[frames[i].index for i in with_gt]])
    keyframe_records = [frames[p] for p in state.keyframe_frames]
    if keyframe_records:
        write_tum_trajectory(folder.keyframes, np.array([f.timestamp for f in keyframe_records]),
                             torch.stack([f.T_wc for f in keyframe_records]))
    write_json_atomic(folder.root / FRAMES, {
        "columns": "per processed frame: sequence index, timestamp, tracking status, loss, iterations, keyframe id "
                   "(-1 = not a keyframe), Gaussians after the frame",
        "flagged": [f.index for f in frames if not f.tracked],
        "frames": [
            {"index": f.index, "timestamp": f.timestamp, "status": f.status,
             "tracking_loss": _finite_or_none(f.tracking_loss), "tracking_iterations": f.tracking_iterations,
             "keyframe_id": f.keyframe_id, "gaussians": count}
            for f, count in zip(frames, state.gaussian_counts)
        ],
    })
    write_map_ply(folder.map_ply, state.gaussian_map)
    write_json_atomic(folder.timings, timing_summary(state))
    intrinsics = sequence.intrinsics
    write_json_atomic(folder.root / RUN_INFO, {
        "mipslam_version": __version__,
        "dataset": {"kind": config.dataset.kind, "name": sequence.name, "root": str(sequence.root),
                    "timestamp_kind": sequence.timestamp_kind, "frames": len(sequence),
                    "intrinsics": {"fx": intrinsics.fx, "fy": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy,
                                   "width": intrinsics.width, "height": intrinsics.height},
                    "has_ground_truth": sequence.gt_T_wc is not None},
        "frames_processed": len(frames),
        "keyframes": len(state.keyframe_frames),
        "gaussians": len(state.gaussian_map),
        "device": str(state.gaussian_map.device),
        "torch_threads": torch.get_num_threads(),
    })


def timing_summary(state: SLAMState) -> dict:
    """Per stage: total seconds, median and mean milliseconds per frame, and the per-frame list."""
    stages = {}
    for stage, values in state.timings.items():
        stages[stage] = {
            "total_s": sum(values),
            "median_ms": 1000 * statistics.median(values) if values else 0.0,
            "mean_ms": 1000 * statistics.fmean(values) if values else 0.0,
            "per_frame_s": values,
        }
    total = sum(sum(v) for v in state.timings.values())
    frames = len(state.frames)
    return {
        "frames": frames,
        "total_s": total,
        "frames_per_second": frames / total if total > 0 else None,
        "note": "seconds of each stage per frame, summed over all sessions of the run (resume included)",
        "stages": stages,
    }
