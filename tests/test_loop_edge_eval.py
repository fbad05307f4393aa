"""The loop edges of a run against the ground truth (mipslam.evaluation.loop_edges)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mipslam.evaluation.loop_edges import loop_edge_accuracy, summary_lines
from mipslam.io.tum import Trajectory


def pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    """Camera-to-world pose [4, 4]: at (x, 0, 0), turned by ``yaw_deg`` about z."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3] = x
    return T


def candidate(query: int, old: int, measured: np.ndarray | None, fitness: float, accepted: bool,
              estimate: np.ndarray | None = None) -> dict:
    return {"query_frame": query, "candidate_frame": old, "fitness": fitness, "accepted": accepted,
            "measured_T_ij": None if measured is None else measured.reshape(-1).tolist(),
            "estimate_T_ij": None if estimate is None else estimate.reshape(-1).tolist()}


def test_each_verified_edge_is_compared_with_the_relative_ground_truth_pose():
    times = np.array([0.0, 0.1, 0.2, 0.3])
    truth = Trajectory(times, np.stack([pose(0.0), pose(0.1, 10), pose(0.2, 20), pose(0.3, 30)]))
    # the estimate: frame 3 is 1 cm further along x than the truth says, in the world frame
    estimate = Trajectory(times, np.stack([pose(0.0), pose(0.1, 10), pose(0.2, 20), pose(0.31, 30)]))
    Z_true = np.linalg.solve(truth.T_wc[0], truth.T_wc[3])  # T_0^-1 T_3
    off_by_2cm = Z_true.copy()
    off_by_2cm[1, 3] += 0.02  # 2 cm in the old camera's y
    estimate_then = Z_true.copy()
    estimate_then[2, 3] += 0.03  # when it was verified the estimate was 3 cm off in the old camera's z
    candidates = [
        candidate(3, 0, off_by_2cm, fitness=0.9, accepted=True, estimate=estimate_then),
        candidate(3, 1, np.linalg.solve(truth.T_wc[1], truth.T_wc[3]) @ pose(0.0, 1.0), fitness=0.4, accepted=False),
        candidate(2, 0, None, fitness=0.2, accepted=False),  # rejected by verification: nothing measured
    ]
    frames = {index: float(t) for index, t in enumerate(times)}
    result = loop_edge_accuracy(candidates, frames, truth, estimate)
    assert result["edges"] == 2 and result["used"] == 1
    first, second = result["per_edge"]
    assert first["error_t_cm"] == pytest.approx(2.0) and first["error_r_deg"] == pytest.approx(0.0, abs=1e-6)
    assert second["error_t_cm"] == pytest.approx(0.0, abs=1e-9) and second["error_r_deg"] == pytest.approx(1.0)
    assert first["estimate_then_error_t_cm"] == pytest.approx(3.0) and "estimate_then_error_t_cm" not in second
    # the final estimate's relative pose between frames 0 and 3 is 1 cm off (along the old camera's x)
    assert first["final_estimate_error_t_cm"] == pytest.approx(1.0)
    assert result["used_estimate_then_error_t_cm_median"] == pytest.approx(3.0)
    assert result["used_error_t_cm_median"] == pytest.approx(2.0)
    assert result["error_t_cm_median"] == pytest.approx(1.0)  # median of 2.0 and 0.0
    bins = {tuple(row["fitness"]): row["edges"] for row in result["by_fitness"]}
    assert bins == {(0.0, 0.5): 1, (0.5, 0.75): 0, (0.75, 1.0): 1}
    # what `mipslam eval` prints and the report shows: the used edge beside the estimate it corrected
    first, by_fitness = summary_lines(result)
    assert first.startswith("2 verified edges err 1.00 cm / 0.50 deg") and "the 1 used 2.00 cm / 0.00 deg (3.00 cm" in first
    assert "0.5-0.75: 0 at - (-)" in by_fitness and "0.75-1: 1 at 2.00 cm / 0.00 deg (3.00 cm / 0.00 deg)" in by_fitness


def test_frames_without_ground_truth_and_runs_without_measurements_are_left_out():
    times = np.array([0.0, 0.1])
    truth = Trajectory(times, np.stack([pose(0.0), pose(0.1)]))
    measured = np.linalg.solve(truth.T_wc[0], truth.T_wc[1])
    frames = {0: 0.0, 1: 0.1, 2: 0.2}  # frame 2 has no ground-truth pose
    rows = [candidate(2, 0, measured, 0.9, True), candidate(1, 0, measured, 0.9, True)]
    result = loop_edge_accuracy(rows, frames, truth, truth)
    assert result["edges"] == 1 and result["error_t_cm_median"] == pytest.approx(0.0, abs=1e-9)
    assert loop_edge_accuracy([candidate(1, 0, None, 0.9, False)], frames, truth, truth) is None
    # a loops.json written before the measurements were recorded has no such column
    assert loop_edge_accuracy([{"query_frame": 1, "candidate_frame": 0, "fitness": 0.9, "accepted": True}], frames,
                              truth, truth) is None
