"""Writes a run's outputs (docs/design.md "Outputs of a run"): trajectories, keyframes, per-frame tracking
record, map, timings, loop closures and a description of the run. Every file is written atomically."""
from __future__ import annotations

import math
from dataclasses import asdict

import numpy as np
import torch

from mipslam import __version__
from mipslam.config import Config
from mipslam.datasets import RGBDSequence
from mipslam.io.ply import write_map_ply
from mipslam.io.run_folder import RunFolder, write_json_atomic
from mipslam.io.tum import write_tum_trajectory
from mipslam.loop.closer import LoopOptions
from mipslam.render import available_backends
from mipslam.state import SLAMState

RUN_INFO = "run.json"
FRAMES = "frames.json"


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def write_run_outputs(folder: RunFolder, state: SLAMState, sequence: RGBDSequence, config: Config,
                      timings: dict) -> None:
    """Every output file of the run folder; ``timings`` is timings.json (:meth:`mipslam.observer.Observer.timing_summary`)."""
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
    write_json_atomic(folder.timings, timings)
    write_json_atomic(folder.loops, loop_summary(state, config))
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
        "render_backend": render_backend_summary(config, state.gaussian_map.device),
    })


def render_backend_summary(config: Config, device: torch.device) -> dict:
    """Which renderer backend the run asked for, which this machine has, and which ``auto`` resolves to
    (the compiled cpu backend for CPU tensors when it built; torch otherwise, e.g. on CUDA)."""
    available = available_backends()
    requested = config.render.backend
    if requested == "auto":
        used = "cpu" if device.type == "cpu" and "cpu" in available else "torch"
    else:
        used = requested
    return {"requested": requested, "available": list(available), "used": used}


def loop_summary(state: SLAMState, config: Config) -> dict:
    """loops.json: every loop candidate with its verification, every pose-graph optimisation, and totals."""
    log = state.loop_log
    optimisations = log["optimisations"]
    return {
        "enabled": config.loop.enabled,
        "settings": asdict(LoopOptions.from_config(config.loop, depth_noise_power=config.dataset.depth_noise_power)),
        "columns": {
            "loops": "every candidate pair (older keyframe i, query keyframe j) and its final status; accepted = "
                     "a loop edge of the final pose graph",
            "candidates": "query/candidate keyframe and frame, descriptor similarity, distance and view angle in the "
                          "current estimate, verification fitness and inlier RMSE (m), how far registration moved the "
                          "initial guess, accepted (became a loop edge) or the reason for the rejection, where the "
                          "registration passed its checks the relative pose T_i^-1 T_k it measured and the one the "
                          "estimate held then (row-major 4x4)",
            "optimisations": "per keyframe that added loop edges disagreeing with the current poses (edges within "
                             "LoopOptions.consistent_chi2 or min_correction_m/_deg join the graph without one): graph "
                             "size, cost before/after (robust, on the edges kept), LM iterations, pruned loop edges [i, j], final weight and chi2 of its new and pruned "
                             "loop edges, whether the correction was applied and why, largest keyframe correction, Gaussians "
                             "moved, refinement steps, with run.diagnostics the map PSNR at the loop's keyframes "
                             "before the correction, with only the poses corrected, after "
                             "the Gaussians moved with their anchors and after the refinement steps (dB), seconds",
        },
        "summary": {
            "keyframes": len(state.keyframe_frames),
            "candidates": len(log["candidates"]),
            "verified": sum(bool(c["accepted"]) for c in log["candidates"]),
            "optimisations": len(optimisations),
            "corrections_applied": sum(bool(o["applied"]) for o in optimisations),
            "pruned_loop_edges": sum(len(o["pruned_edges"]) for o in optimisations),
            "loop_edges_in_graph": int(state.loop.graph.edge_is_loop.sum()),
            "pgo_seconds": sum(o["time_s"] for o in optimisations),
        },
        "loops": loop_list(state),
        "candidates": log["candidates"],
        "optimisations": optimisations,
    }


def loop_list(state: SLAMState) -> list[dict]:
    """Every loop candidate with its final status: ``accepted`` when its edge is in the final pose graph;
    otherwise rejected by verification or pruned by the pose-graph optimisation."""
    graph = state.loop.graph
    in_graph = {tuple(pair) for pair in graph.edge_nodes[graph.edge_is_loop].tolist()}
    pruned = {tuple(pair) for o in state.loop_log["optimisations"] for pair in o["pruned_edges"]}
    rows = []
    for c in state.loop_log["candidates"]:
        pair = (c["candidate_keyframe"], c["query_keyframe"])
        if not c["accepted"]:
            status = "rejected by verification: " + c["reason"]
        elif pair in in_graph:
            status = "loop edge in the pose graph"
        elif pair in pruned:
            status = "pruned by the pose-graph optimisation (disagrees with the other edges)"
        else:
            status = "verified, not in the final graph"
        rows.append({"keyframe_i": pair[0], "keyframe_j": pair[1], "frame_i": c["candidate_frame"],
                     "frame_j": c["query_frame"], "accepted": pair in in_graph, "status": status})
    return rows
