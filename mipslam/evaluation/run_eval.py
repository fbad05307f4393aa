"""Evaluation of a run folder: trajectory metrics (ATE/RPE), render metrics and the visual report.

Reads ``traj_est.txt`` and ``traj_gt.txt`` (TUM format) and ``run.json`` (how the dataset stamps
its frames: Replica and its synthetic twin by frame index, TUM by time), evaluates with the run's
``eval`` config section (alignment, association tolerance, frame set, scales, modes) unless arguments
override it, renders the map for the render metrics (:mod:`mipslam.evaluation.render_eval`), writes
``RUN_DIR/report/`` (:mod:`mipslam.evaluation.report`) and returns the dict for the metrics file.

The run's own evaluation (its ``eval`` config, as ``mipslam run`` does at the end) is ``metrics.json``. Any other
request (other resolution, scales, modes, frame set, frame step, ground truth, alignment, association, no LPIPS, no
rendering) is named by what differs (:func:`evaluation_label`, e.g. ``multiscale`` or ``res-mapping_point-eaa``)
and belongs in ``metrics_<label>.json`` beside it, with its own section of the report, so it never replaces the
run's metrics; the same request made again replaces its own file. The dict's top-level ``"map"`` gives the final
map's size (:func:`map_size`).
"""
from __future__ import annotations

import logging
from pathlib import Path

from mipslam.errors import DatasetError, EvaluationError
from mipslam.evaluation.trajectory import evaluate_trajectory
from mipslam.evaluation.run_files import read_run_config, read_run_json, relative_name, run_file
from mipslam.io.run_folder import RunFolder
from mipslam.io.tum import read_tum_trajectory


logger = logging.getLogger(__name__)

DEFAULT_METRICS_FILE = "metrics.json"
# Seconds within which an estimated pose and a ground-truth pose are taken as the same instant (timestamped
# trajectories; by frame index otherwise).
TRAJECTORY_ASSOCIATION_S = 0.02


def metrics_file_name(label: str | None) -> str:
    """``metrics.json`` for the run's own evaluation, ``metrics_<label>.json`` for another."""
    return DEFAULT_METRICS_FILE if label is None else f"metrics_{label}.json"


def _scale_text(scale: float) -> str:
    return f"{scale:g}".replace(".", "p")


def evaluation_label(config, *, alignment: str | None = None, association: str | None = None,
                     max_diff: float | None = None, render: bool = True, render_options=None) -> str | None:
    """None when the request is the run's own evaluation (its ``eval`` config), else a file-name-safe name of
    what differs, parts joined by ``_``: ``res-mapping`` / ``res-native`` (the resolution), ``multiscale``
    (several scales) or ``scale0p5``, the modes (``point-eaa``), the frame set, ``every3``, ``gt-resampled``,
    ``nolpips``, ``trajectory`` (no rendering), ``align-sim3``, ``match-index`` and ``maxdiff0p1``."""
    cfg = config.eval
    parts: list[str] = []
    if not render:
        parts.append("trajectory")
    elif render_options is not None:
        if render_options.resolution != cfg.resolution:
            parts.append(f"res-{render_options.resolution}")
        scales = tuple(float(s) for s in render_options.scales)
        if sorted(set(scales)) != sorted(set(float(s) for s in cfg.scales)):
            parts.append("multiscale" if len(set(scales)) > 1 else f"scale{_scale_text(scales[0])}")
        run_modes = tuple(cfg.modes) or (config.render.mode,)
        modes = tuple(render_options.modes) or (config.render.mode,)
        if modes != run_modes:
            parts.append("-".join(modes))
        if render_options.frames != cfg.frames:
            parts.append(render_options.frames)
        if render_options.every is not None:
            parts.append(f"every{render_options.every}")
        if render_options.ground_truth != "auto":
            parts.append(f"gt-{render_options.ground_truth}")
        if not render_options.lpips:
            parts.append("nolpips")
    if alignment is not None and alignment != cfg.alignment:
        parts.append(f"align-{alignment}")
    if association is not None and association != "timestamp":
        parts.append(f"match-{association}")
    if max_diff is not None:
        parts.append(f"maxdiff{_scale_text(max_diff)}")
    return "_".join(parts) or None


def map_size(path: Path, name: str | None = None) -> dict:
    """The final map's size: Gaussian count (the PLY header's vertex count) and file size in MB (10^6 bytes);
    ``name``: how to name the file (default its file name)."""
    from mipslam.io.ply import ply_vertex_count

    name = name or path.name
    if not path.is_file():
        return {"file": name, "unavailable": f"{path} is missing"}
    return {"file": name, "gaussians": ply_vertex_count(path), "ply_mb": round(path.stat().st_size / 1e6, 3)}


def evaluate_run(run_dir: str | Path, *, alignment: str | None = None, association: str | None = None,
                 max_diff: float | None = None, render: bool = True, render_options=None,
                 report: bool = True, map_ply: str | Path | None = None, traj_est: str | Path | None = None) -> dict:
    """Metrics of a run folder (the dict for ``metrics.json``).

    render: also compute render metrics (``render_options``: a
    :class:`~mipslam.evaluation.render_eval.RenderEvalOptions`; None = the run's ``eval`` config:
    frames, resolution, scales, modes). When the dataset folder is gone the render section says why it is
    unavailable and the trajectory metrics are still returned. report: write ``RUN_DIR/report/`` (the run's own
    evaluation as the page's main part, any other as its own section; see the module docstring).

    ``map_ply`` / ``traj_est``: evaluate another map and trajectory of the run's frames than its own ``map.ply``
    and ``traj_est.txt`` (``mipslam refine``'s ``refined/map.ply`` and ``refined/traj_est.txt``; relative to the run
    folder), with the same protocol; the dict's ``"evaluation"`` names them. Such an evaluation belongs to its
    caller: it writes no report (``mipslam refine`` rebuilds the page with its own section) and names no metrics
    file (``metrics_file`` None).

    The dict's ``"evaluation"`` entry names the request (``label``: None for the run's own evaluation) and the
    file it belongs in (``metrics_file``: :func:`metrics_file_name`).
    """
    folder = RunFolder(run_dir)
    config = read_run_config(folder)
    info = read_run_json(folder.root / "run.json")
    if not folder.traj_gt.is_file():
        raise EvaluationError(f"{folder.traj_gt}: no ground truth for this run's sequence; nothing to compare with")
    frames = read_run_json(folder.root / "frames.json")
    by_index = info["dataset"]["timestamp_kind"] == "index"
    own_files = map_ply is None and traj_est is None
    map_path = run_file(folder, map_ply, folder.map_ply)
    traj_path = run_file(folder, traj_est, folder.traj_est)
    gt = read_tum_trajectory(folder.traj_gt, allow_duplicate_timestamps=True)
    est = read_tum_trajectory(traj_path)
    options = dict(association=association or "timestamp",
                   max_diff=max_diff if max_diff is not None else (0.5 if by_index else TRAJECTORY_ASSOCIATION_S))
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
    label = evaluation_label(config, alignment=alignment, association=association, max_diff=max_diff, render=render,
                             render_options=render_options)
    if own_files:
        evaluation_entry = {"label": label, "metrics_file": metrics_file_name(label),
                            "meaning": "the run's own evaluation (its eval config)" if label is None else
                                       "a request other than the run's eval config; metrics.json keeps the run's own"}
    else:
        evaluation_entry = {"label": label, "metrics_file": None,
                            "map": relative_name(folder, map_path), "trajectory": relative_name(folder, traj_path),
                            "meaning": f"{relative_name(folder, map_path)} rendered from "
                                       f"{relative_name(folder, traj_path)} "
                                       + ("with the run's own protocol (its eval config)" if label is None else
                                          "with a request other than the run's eval config")}
    metrics = {
        "run_dir": str(folder.root),
        "evaluation": evaluation_entry,
        "dataset": info["dataset"],
        "frames_processed": info["frames_processed"],
        "keyframes": info["keyframes"],
        "gaussians": info["gaussians"],
        "map": map_size(map_path, relative_name(folder, map_path)),
        "tracking_failures": {"count": len(flagged), "frames": flagged,
                              "note": "flagged frames keep their motion-model pose and are included in the ATE"},
        "trajectory": trajectory,
    }
    if folder.loops.is_file():
        from mipslam.evaluation.loop_edges import loop_edge_accuracy

        loops = read_run_json(folder.loops)
        timestamps = {int(f["index"]): float(f["timestamp"]) for f in frames["frames"]}
        accuracy = loop_edge_accuracy(loops.get("candidates", []), timestamps, gt, est)
        if accuracy is not None:
            metrics["loop_edges"] = accuracy
    evaluation = None
    if render:
        from mipslam.evaluation.render_eval import RenderEvalOptions, evaluate_render, load_render_context

        if render_options is None:
            render_options = RenderEvalOptions(frames=config.eval.frames, resolution=config.eval.resolution,
                                               scales=tuple(config.eval.scales), modes=tuple(config.eval.modes))
        try:
            source = folder.root if own_files else load_render_context(folder.root, map_ply=map_ply,
                                                                            traj_est=traj_est)
            evaluation = evaluate_render(source, render_options)
            metrics["render"] = evaluation.to_dict()
        except DatasetError as exc:
            logger.warning("render metrics unavailable: %s", exc)
            metrics["render"] = {"unavailable": f"the run's dataset cannot be read ({exc}); render metrics need it"}
    if report and own_files:
        from mipslam.evaluation.report import write_report

        written = write_report(folder.root, metrics, evaluation, label=label)
        metrics["report"] = str(written.html.relative_to(folder.root))
    return metrics
