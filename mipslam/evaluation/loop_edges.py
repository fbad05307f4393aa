"""How accurate a run's loop edges were: each verified registration of ``loops.json`` against the ground truth.

A loop candidate (keyframe i, query keyframe k) whose registration passed verification records the relative pose
it measured, ``Z = T_i^-1 T_k`` (``measured_T_ij``), and the one the estimate held then (``estimate_T_ij``). The
error of each is ``E = inv(Z_gt) Z`` with ``Z_gt`` from the ground truth of the two frames: the translation (cm)
and rotation angle (deg) of E. The estimate at verification is the yardstick: a loop edge can only improve the
estimate it corrects where it errs less than that. The run's final estimate of the two frames (``traj_est.txt``,
after every correction) is given as well. All are relative poses, so no alignment is involved.

Summaries are medians over the edges, all of them and by overlap (the verification's fitness, the fraction of the
query's points that found a correspondence), in the bins :data:`FITNESS_BINS`.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from mipslam.io.tum import Trajectory

FITNESS_BINS = (0.0, 0.5, 0.75, 1.0)


def _relative_error(Z_measured: np.ndarray, Z_true: np.ndarray) -> tuple[float, float]:
    """Translation (cm) and rotation (deg) of ``inv(Z_true) Z_measured``, both [4, 4]."""
    E = np.linalg.solve(Z_true, Z_measured)
    cos = float(np.clip((np.trace(E[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))
    return float(np.linalg.norm(E[:3, 3])) * 100.0, math.degrees(math.acos(cos))


def _median(values: list[float]) -> float | None:
    return float(np.median(values)) if values else None


# the trajectory files carry timestamps to the microsecond; frames.json to full precision
TIMESTAMP_TOLERANCE_S = 1e-5


def _pose_at(trajectory: Trajectory, timestamp: float) -> np.ndarray | None:
    """The pose [4, 4] of ``trajectory`` stamped ``timestamp`` (within :data:`TIMESTAMP_TOLERANCE_S`), else None."""
    times = trajectory.timestamps
    n = int(np.searchsorted(times, timestamp))
    for m in (n - 1, n):
        if 0 <= m < len(times) and abs(times[m] - timestamp) <= TIMESTAMP_TOLERANCE_S:
            return trajectory.T_wc[m]
    return None


def loop_edge_accuracy(candidates: list[dict[str, Any]], frame_timestamps: dict[int, float], ground_truth: Trajectory,
                       estimate: Trajectory) -> dict[str, Any] | None:
    """Errors of the verified loop edges against the ground truth.

    candidates: ``loops.json``'s candidate rows; frame_timestamps: sequence frame index -> timestamp of the run's
    frames (``frames.json``); ground_truth / estimate: ``traj_gt.txt`` / ``traj_est.txt``. Returns None when no
    row carries a measurement (loops off, none verified, or a run folder written before the measurements were
    recorded).

    -> {"edges": count, "used": count that became loop edges (``accepted``), "error_t_cm_median",
    "error_r_deg_median" (the edges), "estimate_then_error_*_median" (the estimate when each was verified),
    "final_estimate_error_*_median" (the final estimate), the same for the used edges ("used_*"), "by_fitness":
    per bin of :data:`FITNESS_BINS` its count and medians, "per_edge": rows}
    """
    rows = []
    for c in candidates:
        measured = c.get("measured_T_ij")
        if measured is None:
            continue
        t_query, t_candidate = frame_timestamps.get(c["query_frame"]), frame_timestamps.get(c["candidate_frame"])
        if t_query is None or t_candidate is None:
            continue
        gt_query, gt_candidate = _pose_at(ground_truth, t_query), _pose_at(ground_truth, t_candidate)
        if gt_query is None or gt_candidate is None:
            continue  # a frame without ground truth
        Z_true = np.linalg.solve(gt_candidate, gt_query)
        error_t, error_r = _relative_error(np.asarray(measured, dtype=np.float64).reshape(4, 4), Z_true)
        row = {"query_frame": c["query_frame"], "candidate_frame": c["candidate_frame"],
               "fitness": float(c["fitness"]), "used": bool(c["accepted"]), "error_t_cm": error_t, "error_r_deg": error_r}
        if c.get("estimate_T_ij") is not None:
            Z_then = np.asarray(c["estimate_T_ij"], dtype=np.float64).reshape(4, 4)
            row["estimate_then_error_t_cm"], row["estimate_then_error_r_deg"] = _relative_error(Z_then, Z_true)
        est_query, est_candidate = _pose_at(estimate, t_query), _pose_at(estimate, t_candidate)
        if est_query is not None and est_candidate is not None:
            Z_final = np.linalg.solve(est_candidate, est_query)
            row["final_estimate_error_t_cm"], row["final_estimate_error_r_deg"] = _relative_error(Z_final, Z_true)
        rows.append(row)
    if not rows:
        return None

    def medians(selected: list[dict], prefix: str = "") -> dict[str, float | None]:
        return {f"{prefix}{what}_median": _median([r[what] for r in selected if what in r])
                for what in ("error_t_cm", "error_r_deg", "estimate_then_error_t_cm", "estimate_then_error_r_deg",
                             "final_estimate_error_t_cm", "final_estimate_error_r_deg")}

    by_fitness = []
    for b, (low, high) in enumerate(zip(FITNESS_BINS[:-1], FITNESS_BINS[1:])):
        last = b == len(FITNESS_BINS) - 2
        inside = [r for r in rows if low <= r["fitness"] and (r["fitness"] <= high if last else r["fitness"] < high)]
        by_fitness.append({"fitness": [low, high], "edges": len(inside), **medians(inside)})
    used = [r for r in rows if r["used"]]
    return {"edges": len(rows), "used": len(used), **medians(rows), **medians(used, "used_"),
            "by_fitness": by_fitness, "per_edge": rows}


def _pair_text(values: dict[str, Any], prefix: str) -> str:
    t, r = values.get(f"{prefix}_t_cm_median"), values.get(f"{prefix}_r_deg_median")
    return "-" if t is None or r is None else f"{t:.2f} cm / {r:.2f} deg"


def summary_lines(accuracy: dict[str, Any]) -> list[str]:
    """Two lines of text for ``metrics.json``'s ``loop_edges`` (:func:`loop_edge_accuracy`): the medians of all and
    of the used edges, each beside the estimate they corrected, then the same by fitness."""
    return [
        f"{accuracy['edges']} verified edges err {_pair_text(accuracy, 'error')} (the estimate they corrected "
        f"{_pair_text(accuracy, 'estimate_then_error')}); the {accuracy['used']} used "
        f"{_pair_text(accuracy, 'used_error')} ({_pair_text(accuracy, 'used_estimate_then_error')})",
        "by fitness: " + ", ".join(
            f"{row['fitness'][0]:g}-{row['fitness'][1]:g}: {row['edges']} at {_pair_text(row, 'error')} "
            f"({_pair_text(row, 'estimate_then_error')})" for row in accuracy["by_fitness"]),
    ]
