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

from typing import Any

import numpy as np

from mipslam.evaluation.trajectory import pose_errors, poses_at_stamps
from mipslam.io.tum import Trajectory

FITNESS_BINS = (0.0, 0.5, 0.75, 1.0)

# the trajectory files carry timestamps to the microsecond; frames.json to full precision
TIMESTAMP_TOLERANCE_S = 1e-5

_MEDIANS = ("error_t_cm", "error_r_deg", "estimate_then_error_t_cm", "estimate_then_error_r_deg",
            "final_estimate_error_t_cm", "final_estimate_error_r_deg")


def fitness_bins(fitness: list[float], edges: tuple[float, ...]) -> list[list[int]]:
    """Indices of ``fitness`` in each bin ``[edges[b], edges[b + 1])``, the last bin closed; values outside
    every bin are in none."""
    last = len(edges) - 2
    return [[n for n, f in enumerate(fitness) if low <= f and (f <= high if b == last else f < high)]
            for b, (low, high) in enumerate(zip(edges[:-1], edges[1:]))]


def _median(values: list[float]) -> float | None:
    return float(np.median(values)) if values else None


def _error_cm_deg(Z_true: np.ndarray, Z: list[float] | np.ndarray) -> tuple[float, float]:
    """:func:`pose_errors` of one relative pose ``Z`` (4x4, or 16 numbers row-major) against ``Z_true`` [4, 4]:
    translation in centimetres, rotation in degrees."""
    t, r = pose_errors(Z_true[None], np.asarray(Z, dtype=np.float64).reshape(1, 4, 4))
    return float(t[0]) * 100.0, float(r[0])


def _relative_pose(trajectory: Trajectory, t_candidate: float, t_query: float) -> np.ndarray | None:
    """``T_i^-1 T_k`` [4, 4] of ``trajectory`` between the frames stamped ``t_candidate`` (i) and ``t_query`` (k),
    or None where either has no pose."""
    found, T_wc = poses_at_stamps(trajectory, np.array([t_candidate, t_query]), TIMESTAMP_TOLERANCE_S)
    return np.linalg.solve(T_wc[0], T_wc[1]) if found.all() else None


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
        if c.get("measured_T_ij") is None or c["query_frame"] not in frame_timestamps \
                or c["candidate_frame"] not in frame_timestamps:
            continue
        stamps = frame_timestamps[c["candidate_frame"]], frame_timestamps[c["query_frame"]]
        Z_true = _relative_pose(ground_truth, *stamps)
        if Z_true is None:
            continue  # a frame without ground truth
        row = {"query_frame": c["query_frame"], "candidate_frame": c["candidate_frame"], "fitness": float(c["fitness"]),
               "used": bool(c["accepted"])}
        row["error_t_cm"], row["error_r_deg"] = _error_cm_deg(Z_true, c["measured_T_ij"])
        if c.get("estimate_T_ij") is not None:
            row["estimate_then_error_t_cm"], row["estimate_then_error_r_deg"] = _error_cm_deg(Z_true, c["estimate_T_ij"])
        Z_final = _relative_pose(estimate, *stamps)
        if Z_final is not None:
            row["final_estimate_error_t_cm"], row["final_estimate_error_r_deg"] = _error_cm_deg(Z_true, Z_final)
        rows.append(row)
    if not rows:
        return None

    def medians(selected: list[dict], prefix: str = "") -> dict[str, float | None]:
        return {f"{prefix}{what}_median": _median([r[what] for r in selected if what in r]) for what in _MEDIANS}

    by_fitness = [{"fitness": [low, high], "edges": len(members), **medians([rows[n] for n in members])}
                  for (low, high), members in zip(zip(FITNESS_BINS[:-1], FITNESS_BINS[1:]),
                                                  fitness_bins([r["fitness"] for r in rows], FITNESS_BINS))]
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
