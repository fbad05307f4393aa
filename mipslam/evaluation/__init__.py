"""Evaluation: trajectory accuracy (ATE/RPE); render metrics and reports live beside it."""
from mipslam.evaluation.trajectory import (
    Alignment,
    Association,
    ErrorStatistics,
    TrajectoryMetrics,
    associate_by_index,
    associate_by_timestamp,
    evaluate_trajectory,
    umeyama_alignment,
)

__all__ = [
    "Alignment", "Association", "ErrorStatistics", "TrajectoryMetrics",
    "associate_by_index", "associate_by_timestamp", "evaluate_trajectory", "umeyama_alignment",
]
