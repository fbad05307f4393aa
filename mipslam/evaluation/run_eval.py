"""Evaluation of a run folder: trajectory metrics (ATE/RPE), render metrics and the visual report.

Reads ``traj_est.txt`` and ``traj_gt.txt`` (TUM format) and ``run.json`` (how the dataset stamps
its frames: Replica and its synthetic twin by frame index, TUM by time), evaluates with the run's
``eval`` config section (alignment, association tolerance, frame set, scales, modes) unless arguments
override it, renders the map for the render metrics (:mod:`mipslam.evaluation.render_eval`), writes
``RUN_DIR/report/`` (:mod:`mipslam.evaluation.report`) and returns the dict written to ``metrics.json``.
"""
from __future__ import annotations

import logging
from pathlib import Path

from mipslam.errors import DatasetError, EvaluationError
from mipslam.evaluation.trajectory import evaluate_trajectory
from mipslam.evaluation.run_files import read_run_config, read_run_json
from mipslam.io.run_folder import RunFolder
from mipslam.io.tum import read_tum_trajectory


logger = logging.getLogger(__name__)


def evaluate_run(run_dir: str | Path, *, alignment: str | None = None, association: str | None = None,
                 max_diff: float | None = None, render: bool = True, render_options=None,
                 report: bool = True) -> dict:
    """Metrics of a run folder (the dict for ``metrics.json``).

    render: also compute render metrics (``render_options``: a
    :class:`~mipslam.evaluation.render_eval.RenderEvalOptions`; None = the run's ``eval`` config:
    frames, scales, modes). When the dataset folder is gone the render section says why it is
    unavailable and the trajectory metrics are still returned. report: write ``RUN_DIR/report/``.
    """
    folder = RunFolder(run_dir)
    config = read_run_config(folder)
    info = read_run_json(folder.root / "run.json")
    if not folder.traj_gt.is_file():
        raise EvaluationError(f"{folder.traj_gt}: no ground truth for this run's sequence; nothing to compare with")
    frames = read_run_json(folder.root / "frames.json")
    by_index = info["dataset"]["timestamp_kind"] == "index"
    gt = read_tum_trajectory(folder.traj_gt, allow_duplicate_timestamps=True)
    est = read_tum_trajectory(folder.traj_est)
    options = dict(association=association or "timestamp",
                   max_diff=max_diff if max_diff is not None else (0.5 if by_index else config.eval.association_tolerance_s))
    requested = alignment or config.eval.alignment
    try:
        trajectory = evaluate_trajectory(gt, est, alignment=requested, **options).to_dict()
    except EvaluationError as exc:
        # A camera at rest or moving on a line leaves the alignment's rotation undetermined. Runs start
        # at the ground-truth pose of their first frame, so the unaligned error is meaningful there.
        if requested == "none" or "cannot align" not in str(exc):
            raise
        trajectory = evaluate_trajectory(gt, est, alignment="none", **options).to_dict()
        trajectory["protocol"]["alignment"]["fallback"] = (
            f"{requested} alignment impossible ({exc}); evaluated without alignment: the run's first pose is the "
            "ground-truth pose of its first frame")
    if by_index:
        trajectory["protocol"]["association"]["note"] = (
            "timestamps are frame indices (Replica layout): frames match by index")
    flagged = frames["flagged"]
    metrics = {
        "run_dir": str(folder.root),
        "dataset": info["dataset"],
        "frames_processed": info["frames_processed"],
        "keyframes": info["keyframes"],
        "gaussians": info["gaussians"],
        "tracking_failures": {"count": len(flagged), "frames": flagged,
                              "note": "flagged frames keep their motion-model pose and are included in the ATE"},
        "trajectory": trajectory,
    }
    evaluation = None
    if render:
        from mipslam.evaluation.render_eval import RenderEvalOptions, evaluate_render

        if render_options is None:
            render_options = RenderEvalOptions(frames=config.eval.frames, scales=tuple(config.eval.scales),
                                               modes=tuple(config.eval.modes))
        try:
            evaluation = evaluate_render(folder.root, render_options)
            metrics["render"] = evaluation.to_dict()
        except DatasetError as exc:
            logger.warning("render metrics unavailable: %s", exc)
            metrics["render"] = {"unavailable": f"the run's dataset cannot be read ({exc}); render metrics need it"}
    if report:
        from mipslam.evaluation.report import write_report

        written = write_report(folder.root, metrics, evaluation)
        metrics["report"] = str(written.html.relative_to(folder.root))
    return metrics
