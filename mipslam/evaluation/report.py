"""The visual report of a run: PNG plots and one ``report.html`` in ``RUN_DIR/report/``.

Written by ``mipslam eval`` (:func:`mipslam.evaluation.run_eval.evaluate_run`) from the run folder's files and the
metrics it just computed:

* ``trajectory.png``   top view (the two world axes with the largest ground-truth extent) of the ground truth and
  the estimate after the ATE alignment of ``metrics.json``, keyframes marked, loop closures (``loops.json``) drawn
  between their keyframes (accepted solid, rejected dotted);
* ``translation_error.png``  per-frame translational ATE (aligned) over time, keyframes marked, RMSE line;
* ``psnr_vs_scale.png``  PSNR against rendering scale per footprint mode (the multi-scale table; when only one
  scale was evaluated, the showcase frame's values at each showcase scale, labelled so);
* ``timing.png``       per-frame time of each stage (stacked) and the mean per stage;
* ``gaussians.png``    Gaussian count after each frame, keyframes marked;
* ``crops.png``        one frame at each scale, the same detailed region cut out, ground truth next to point / mip /
  eaa (nearest-neighbour display, so aliasing stays visible), with the full-image PSNR of each render;
* ``report.html``      the headline numbers (the novel-view row at scale 1 first, when there is one), the render
  table (one group of rows per evaluated view set) and the protocol in words, linking the images;
* ``refinement_psnr.png``  where ``mipslam refine`` ran (``RUN_DIR/refined/``): novel- and training-view PSNR
  against refinement time (``refined/progress.json``), in the page's "Refinement" section with the refined map's
  metrics (``refined/metrics.json``) beside the SLAM map's.

The page's main part is the run's own evaluation (``metrics.json``), followed by the Refinement section where
there is one (:func:`write_report_page` rebuilds the page from the run folder's files alone, as ``mipslam refine``
does). An evaluation with other scales, modes or
options (``metrics_<label>.json``, :func:`mipslam.evaluation.run_eval.evaluation_label`) gets its own section below
it, with its table and its ``psnr_vs_scale_<label>.png`` and ``crops_<label>.png``; the page lists a section for
every ``metrics_*.json`` in the run folder.

Curves that may coincide (footprint modes at the scales where they agree, the estimate on the ground truth) are
drawn widest first with nested markers, so each stays visible where they overlap.

Matplotlib draws through its Agg canvas on :class:`matplotlib.figure.Figure` objects (no pyplot, no global
backend change, nothing interactive); every file is written atomically.
"""
from __future__ import annotations

import html
import io
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mipslam.errors import EvaluationError
from mipslam.evaluation.loop_edges import summary_lines
from mipslam.io.run_folder import RunFolder, write_bytes_atomic, write_text_atomic
from mipslam.io.tum import read_tum_trajectory

logger = logging.getLogger(__name__)

__all__ = ["ReportFiles", "loop_closures", "loop_text", "overlap_styles", "plot_refinement", "selection_text",
           "top_view_axes", "write_report", "write_report_page"]

MODE_COLORS = {"point": "#d62728", "mip": "#1f77b4", "ewa": "#9467bd", "eaa": "#2ca02c", "exact": "#7f7f7f"}
STAGE_COLORS = ("#4c72b0", "#dd8452", "#55a868", "#c44e52", "#8172b3", "#937860", "#da8bc3", "#8c8c8c")
DPI = 110
SERIES_MARKERS = ("o", "s", "D", "^", "v", "P")


def overlap_styles(count: int) -> list[dict[str, Any]]:
    """Line and marker styles for ``count`` curves that may coincide: drawn in order, each thinner, with a
    smaller marker and above the one before, so a curve lying on another shows as a line inside a wider band and
    a marker inside a larger one (matplotlib keyword arguments)."""
    styles = []
    for k in range(count):
        wider = count - 1 - k  # how many curves come after (are drawn on top of) this one
        styles.append(dict(lw=1.4 + 1.6 * wider, ms=5.5 + 3.0 * wider, marker=SERIES_MARKERS[k % len(SERIES_MARKERS)],
                           mfc="white" if wider else None, mew=1.6, zorder=2 + k))
    return styles


@dataclass(frozen=True)
class ReportFiles:
    """What :func:`write_report` wrote: the folder, the HTML page and each image (name -> path)."""

    folder: Path
    html: Path
    images: dict[str, Path]


# ----------------------------------------------------------------------------- inputs

def _read_json_or_none(path: Path) -> Any:
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise EvaluationError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None


_LOOP_KEY_PAIRS = (("keyframe_i", "keyframe_j"), ("i", "j"), ("from", "to"), ("source", "target"),
                   ("query", "match"), ("kf_i", "kf_j"))


def loop_closures(data: Any) -> list[tuple[int, int, bool]]:
    """(keyframe id, keyframe id, accepted) of each loop closure listed in ``loops.json``.

    Accepts a list of objects, or an object with a ``"loops"`` list; each object names its two keyframes by one
    of the key pairs ``keyframe_i/keyframe_j``, ``i/j``, ``from/to``, ``source/target``, ``query/match``,
    ``kf_i/kf_j`` and may say ``"accepted": false``. Entries without a recognisable pair are skipped (logged).
    """
    if isinstance(data, dict):
        data = data.get("loops", data.get("closures", []))
    if not isinstance(data, list):
        return []
    out = []
    for entry in data:
        if not isinstance(entry, dict):
            continue
        for a, b in _LOOP_KEY_PAIRS:
            if isinstance(entry.get(a), int) and isinstance(entry.get(b), int):
                out.append((int(entry[a]), int(entry[b]), bool(entry.get("accepted", True))))
                break
        else:
            logger.debug("loops.json entry without keyframe ids skipped: %s", entry)
    return out


def top_view_axes(positions: np.ndarray) -> tuple[int, int]:  # [N, 3]
    """The two world axes with the largest extent of ``positions`` (the third, dropped, is taken as 'up')."""
    extent = np.ptp(positions, axis=0) if len(positions) else np.ones(3)
    first, second = sorted(np.argsort(extent)[-2:].tolist())
    return int(first), int(second)


def _align(points: np.ndarray, alignment: dict | None) -> np.ndarray:  # [N, 3] -> [N, 3]
    if not alignment:
        return points
    rotation = np.asarray(alignment["rotation"], dtype=np.float64)
    translation = np.asarray(alignment["translation_m"], dtype=np.float64)
    return (float(alignment.get("scale", 1.0)) * points) @ rotation.T + translation


def _figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _save(figure, path: Path) -> Path:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI)
    return write_bytes_atomic(path, buffer.getvalue(), error_type=EvaluationError)


# ----------------------------------------------------------------------------- plots

_AXIS_NAMES = "xyz"


def plot_trajectory(path: Path, gt: np.ndarray, est: np.ndarray, keyframes: np.ndarray,
                    loops: list[tuple[int, int, bool]], ate_rmse: float | None) -> Path:
    """Top view.  gt [N, 3], est [M, 3] (aligned), keyframes [K, 3] (aligned) positions in metres."""
    a, b = top_view_axes(gt if len(gt) else est)
    figure = _figure(6.4, 5.6)
    ax = figure.add_subplot()
    if len(gt):  # a wide light band under the estimate, which stays visible where the two coincide
        ax.plot(gt[:, a], gt[:, b], "-", color="#9a9a9a", lw=5.0, alpha=0.6, solid_capstyle="round",
                label="ground truth", zorder=2)
    ax.plot(est[:, a], est[:, b], "-", color="#1f77b4", lw=1.4, label="estimate (aligned)", zorder=3)
    if len(est):
        ax.plot(est[0, a], est[0, b], "o", color="#1f77b4", ms=8, mfc="white", label="start")
    if len(keyframes):
        ax.plot(keyframes[:, a], keyframes[:, b], "^", color="#ff7f0e", ms=7, mec="black", mew=0.5,
                label=f"keyframes ({len(keyframes)})")
    drawn = {True: False, False: False}
    for i, j, accepted in loops:
        if 0 <= i < len(keyframes) and 0 <= j < len(keyframes):
            label = None if drawn[accepted] else ("loop closure" if accepted else "rejected loop")
            drawn[accepted] = True
            ax.plot(keyframes[[i, j], a], keyframes[[i, j], b], "-" if accepted else ":", color="#d62728",
                    lw=1.8 if accepted else 1.0, alpha=1.0 if accepted else 0.5, label=label)
    ax.set_xlabel(f"world {_AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"world {_AXIS_NAMES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    title = "Trajectory, top view"
    if ate_rmse is not None:
        title += f" (ATE RMSE {ate_rmse * 100:.2f} cm)"
    ax.set_title(title)
    ax.legend(loc="best", fontsize=9)
    return _save(figure, path)


def plot_translation_error(path: Path, times: np.ndarray, errors: np.ndarray, keyframe_times: np.ndarray,
                           time_label: str) -> Path:
    """times [M], errors [M] metres, keyframe_times [K]."""
    figure = _figure(7.5, 3.6)
    ax = figure.add_subplot()
    ax.plot(times, errors * 100, "-", color="#1f77b4", lw=1.5, label="translation error")
    on_keyframes = np.isin(times, keyframe_times)
    if on_keyframes.any():
        ax.plot(times[on_keyframes], errors[on_keyframes] * 100, "^", color="#ff7f0e", ms=6, mec="black", mew=0.5,
                label="keyframes")
    if len(errors):
        rmse = float(np.sqrt(np.mean(errors**2)))
        ax.axhline(rmse * 100, color="#444444", ls="--", lw=1, label=f"RMSE {rmse * 100:.2f} cm")
    ax.set_xlabel(time_label)
    ax.set_ylabel("error after alignment [cm]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.set_title("Absolute translation error over time")
    ax.legend(loc="best", fontsize=9)
    return _save(figure, path)


def plot_psnr_vs_scale(path: Path, points: dict[str, list[tuple[float, float]]], subtitle: str,
                       reference: str = "mapping resolution") -> Path:
    """points: mode -> [(scale, PSNR dB)]; reference: what scale 1 is (the x axis label)."""
    figure = _figure(6.4, 4.4)
    ax = figure.add_subplot()
    scales = sorted({s for values in points.values() for s, _ in values})
    for (mode, values), style in zip(points.items(), overlap_styles(len(points))):
        values = sorted(values)
        ax.plot([s for s, _ in values], [p for _, p in values], "-", color=MODE_COLORS.get(mode), mec=MODE_COLORS.get(mode),
                label=mode, **style)
    ax.set_xscale("log", base=2)
    ax.set_xticks(scales)
    ax.set_xticklabels([_scale_label(s) for s in scales])
    ax.set_xlabel(f"rendering scale (x {reference})")
    ax.set_ylabel("PSNR [dB]")
    ax.grid(alpha=0.3, which="both")
    ax.set_title(f"PSNR against scale\n{subtitle}", fontsize=11)
    ax.legend(title="footprint", fontsize=9)
    return _save(figure, path)


def _scale_label(scale: float) -> str:
    if scale < 1 and abs(1 / scale - round(1 / scale)) < 1e-9:
        return f"1/{round(1 / scale)}"
    return f"{scale:g}"


def plot_timing(path: Path, timings: dict) -> Path:
    stages = {name: np.asarray(values.get("per_frame_s", []), dtype=np.float64)
              for name, values in timings.get("stages", {}).items()}
    from matplotlib.ticker import MaxNLocator

    figure = _figure(9.0, 3.8)
    left, right = figure.subplots(1, 2, width_ratios=(2.2, 1))
    frames = max((len(v) for v in stages.values()), default=0)
    per_frame_total = sum((np.pad(v, (0, frames - len(v))) for v in stages.values()), np.zeros(frames))
    unit, factor = ("s", 1.0) if frames and per_frame_total.max() > 10.0 else ("ms", 1000.0)
    bottom = np.zeros(frames)
    for k, (name, values) in enumerate(stages.items()):
        padded = np.zeros(frames)
        padded[:len(values)] = values
        left.bar(np.arange(frames), padded * factor, bottom=bottom, width=0.85,
                 color=STAGE_COLORS[k % len(STAGE_COLORS)], label=name)
        bottom += padded * factor
    left.xaxis.set_major_locator(MaxNLocator(integer=True))
    left.set_xlabel("frame")
    left.set_ylabel(f"time [{unit}]")
    left.set_title("Time per frame by stage")
    left.grid(alpha=0.3, axis="y")
    left.legend(fontsize=8)
    names = list(stages)
    means = [float(values.mean() * 1000) if len(values) else 0.0 for values in stages.values()]
    totals = [float(values.sum()) for values in stages.values()]
    right.barh(names, means, color=[STAGE_COLORS[k % len(STAGE_COLORS)] for k in range(len(names))])
    for y, (mean, total) in enumerate(zip(means, totals)):
        right.text(mean, y, f" {mean:.0f} ms ({total:.0f} s)", va="center", fontsize=8)
    right.set_xlim(0, max(means + [1.0]) * 1.6)
    right.invert_yaxis()
    right.set_xlabel("mean per frame [ms]")
    fps = timings.get("frames_per_second")
    right.set_title(f"Mean per stage ({fps:.2f} frames/s)" if fps else "Mean per stage")
    return _save(figure, path)


def plot_gaussians(path: Path, frame_indices: np.ndarray, counts: np.ndarray, keyframe_mask: np.ndarray) -> Path:
    """frame_indices [N], counts [N], keyframe_mask [N] bool."""
    figure = _figure(7.5, 3.4)
    ax = figure.add_subplot()
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.plot(frame_indices, counts, "-", color="#2ca02c", lw=1.8, label="Gaussians")
    if keyframe_mask.any():
        ax.plot(frame_indices[keyframe_mask], counts[keyframe_mask], "^", color="#ff7f0e", ms=6, mec="black",
                mew=0.5, label="keyframes")
    ax.set_xlabel("frame")
    ax.set_ylabel("Gaussians in the map")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.set_title(f"Map size over time (final: {int(counts[-1]) if len(counts) else 0})")
    ax.legend(loc="best", fontsize=9)
    return _save(figure, path)


def plot_refinement(path: Path, records: list[dict]) -> Path:
    """Novel- and training-view PSNR against refinement time (``refined/progress.json`` records), sessions
    marked where a later one continued."""
    figure = _figure(7.5, 3.8)
    ax = figure.add_subplot()
    seconds = np.asarray([r.get("seconds", 0.0) for r in records], dtype=np.float64)
    in_minutes = len(seconds) and seconds.max() > 300.0
    times = seconds / 60.0 if in_minutes else seconds
    for views, colour, marker in (("novel", "#1f77b4", "o"), ("training", "#ff7f0e", "s")):
        values = [r.get(f"{views}_psnr") for r in records]
        kept = [(t, v) for t, v in zip(times, values) if v is not None]
        if kept:
            frames = max((r.get(f"{views}_frames", 0) for r in records), default=0)
            ax.plot([t for t, _ in kept], [v for _, v in kept], "-", marker=marker, color=colour, ms=5,
                    label=f"{views} views ({frames} frames)")
    for k in range(1, len(records)):
        if records[k].get("session") != records[k - 1].get("session"):
            ax.axvline(times[k - 1], color="#888888", ls=":", lw=1)
    ax.set_xlabel("refinement time [min]" if in_minutes else "refinement time [s]")
    ax.set_ylabel("PSNR [dB] (native resolution)")
    ax.grid(alpha=0.3)
    steps = records[-1].get("steps", 0) if records else 0
    ax.set_title(f"PSNR during the refinement ({steps} steps; dotted: a later session continued)", fontsize=10)
    ax.legend(loc="best", fontsize=9)
    return _save(figure, path)


def _crop(image: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:  # [h, w, 3]
    height, width = image.shape[:2]
    x0, x1 = int(math.floor(box[0] * width)), max(int(math.floor(box[0] * width)) + 1, int(math.ceil(box[2] * width)))
    y0, y1 = int(math.floor(box[1] * height)), max(int(math.floor(box[1] * height)) + 1, int(math.ceil(box[3] * height)))
    return image[y0:min(y1, height), x0:min(x1, width)]


def plot_crops(path: Path, showcase) -> Path:
    """Crop grid of a :class:`~mipslam.evaluation.render_eval.Showcase` (rows: scales; columns: GT, modes)."""
    from mipslam.evaluation.image_metrics import psnr

    columns = ("ground truth", *showcase.modes)
    rows = showcase.scales
    largest = showcase.ground_truth[max(rows)]
    x0, y0, x1, y1 = showcase.crop_box
    aspect = ((y1 - y0) * largest.shape[0]) / max((x1 - x0) * largest.shape[1], 1e-9)  # crop height / width
    cell = 2.3
    figure = _figure(cell * len(columns) + 0.6, (cell * aspect + 0.25) * len(rows) + 0.6)
    axes = figure.subplots(len(rows), len(columns), squeeze=False)
    for r, scale in enumerate(rows):
        truth = showcase.ground_truth[scale]
        for c, name in enumerate(columns):
            ax = axes[r][c]
            image = truth if c == 0 else showcase.renders[(scale, name)]
            ax.imshow(_crop(image.numpy(), showcase.crop_box), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(name, fontsize=11, color=MODE_COLORS.get(name, "black"), fontweight="bold")
            if c == 0:
                ax.set_ylabel(f"x{_scale_label(scale)}\n{truth.shape[1]}x{truth.shape[0]} px", fontsize=10)
            else:
                value = float(psnr(image, truth))
                ax.text(0.02, 0.03, f"{value:.1f} dB", transform=ax.transAxes, fontsize=8, color="white",
                        bbox=dict(facecolor="black", alpha=0.6, pad=1.5, lw=0))
    box = showcase.crop_box
    figure.suptitle(f"Frame {showcase.frame_index}: region x {box[0]:.2f}-{box[2]:.2f}, y {box[1]:.2f}-{box[3]:.2f} "
                    "of the image at each scale (PSNR of the whole image)", fontsize=10)
    return _save(figure, path)


# ----------------------------------------------------------------------------- report

def _first_view_set(rows: list[dict]) -> tuple[str | None, list[dict]]:
    """The rows of the first evaluated view set (the novel views under ``split``): (its name, its rows)."""
    views = rows[0].get("views") if rows else None
    return views, [row for row in rows if row.get("views") == views]


def _reference_text(render: dict | None) -> str:
    """What scale 1 is, for labels: e.g. 'native resolution 640x480' (older metrics: the mapping resolution)."""
    reference = ((render or {}).get("protocol") or {}).get("scale_reference") or {}
    size = reference.get("size") or reference.get("mapping_resolution") or []
    name = reference.get("resolution", "mapping")
    return f"{name} resolution" + (f" {'x'.join(map(str, size))}" if size else "")


def selection_text(selection: dict) -> str:
    """One evaluated frame set of the render protocol (``render.protocol.frames.views[k]``) in words."""
    views, count, in_set = selection["views"], len(selection["evaluated"]), selection["in_set"]
    if views == "novel":
        return f"  novel views: {count} of {in_set} non-keyframes ({selection['rule']})"
    pool = {"training": "keyframes", "keyframes": "keyframes", "non_keyframes": "non-keyframes"}.get(views, "frames")
    name = "training views" if views == "training" else views
    return f"  {name}: {count} of {in_set} {pool}, every {selection['every']}"


def _psnr_points(render: dict | None, showcase) -> tuple[dict[str, list[tuple[float, float]]], str]:
    views, rows = _first_view_set((render or {}).get("rows", []))
    scales = {row["scale"] for row in rows}
    if len(scales) > 1:
        points: dict[str, list[tuple[float, float]]] = {}
        for row in rows:
            if row["psnr"] is not None:
                points.setdefault(row["mode"], []).append((row["scale"], row["psnr"]))
        return points, f"mean over {rows[0]['frames']} frames ({views or render['protocol']['frames']['set']})"
    if showcase is not None:
        from mipslam.evaluation.image_metrics import psnr

        points = {mode: [(s, float(psnr(showcase.renders[(s, mode)], showcase.ground_truth[s])))
                         for s in showcase.scales] for mode in showcase.modes}
        return points, f"frame {showcase.frame_index} only (run 'mipslam eval --scales' for the mean over frames)"
    return {}, ""


def write_report(run_dir: str | Path, metrics: dict, render_evaluation=None, *, label: str | None = None) -> ReportFiles:
    """Write the plots and ``report.html`` into ``RUN_DIR/report/`` (see the module docstring).

    ``metrics``: the dict of :func:`~mipslam.evaluation.run_eval.evaluate_run`; ``render_evaluation``: its
    :class:`~mipslam.evaluation.render_eval.RenderEvaluation` (for the crop grid), or None. ``label``: None for the
    run's own evaluation (the page's main part and its plots), else the name of another evaluation, which gets its
    own section and plots named ``<plot>_<label>.png``; the page is rebuilt from the run folder either way.
    """
    run = RunFolder(run_dir)
    folder = run.report
    folder.mkdir(parents=True, exist_ok=True)
    if label is None:
        images = main_images = _main_plots(run, metrics, render_evaluation)
        main = metrics
    else:
        images = _section_plots(folder, metrics, render_evaluation, label)
        main = _read_json_or_none(run.metrics)
        main_images = _existing_main_plots(folder)
    page = _write_page(run, main, main_images, _other_evaluations(run, label, metrics))
    return ReportFiles(folder, page, images)


def write_report_page(run_dir: str | Path) -> ReportFiles:
    """Rebuild ``report.html`` from the run folder's files without evaluating anything: the run's own
    ``metrics.json`` with the plots already in ``report/``, every ``metrics_<label>.json`` section and the
    Refinement section (its plot drawn again from ``refined/progress.json``). ``mipslam refine`` calls it."""
    run = RunFolder(run_dir)
    run.report.mkdir(parents=True, exist_ok=True)
    page = _write_page(run, _read_json_or_none(run.metrics), _existing_main_plots(run.report),
                       _other_evaluations(run, None, {}))
    return ReportFiles(run.report, page, {})


def _existing_main_plots(folder: Path) -> dict[str, Path]:
    return {name: folder / f"{name}.png" for name in MAIN_PLOTS if (folder / f"{name}.png").is_file()}


def _write_page(run: RunFolder, main: dict | None, main_images: dict[str, Path], sections: dict[str, dict]) -> Path:
    page = run.report / "report.html"
    refinement = _refinement_inputs(run)
    text = _html(run, main, _read_json_or_none(run.timings), _read_json_or_none(run.loops), main_images, sections,
                 refinement)
    write_text_atomic(page, text, error_type=EvaluationError)
    logger.info("report written to %s", page)
    return page


@dataclass(frozen=True)
class _Refinement:
    """What the report shows of ``RUN_DIR/refined/``."""

    progress: dict | None
    metrics: dict | None
    plot: Path | None


def _refinement_inputs(run: RunFolder) -> _Refinement | None:
    """The refinement's progress and metrics, with its plot drawn into ``report/`` (None: never refined)."""
    refined = run.refined
    if not refined.root.is_dir():
        return None
    progress = _read_json_or_none(refined.progress)
    metrics = _read_json_or_none(refined.metrics)
    if progress is None and metrics is None:
        return None
    plot = None
    records = (progress or {}).get("records") or []
    if any(r.get("novel_psnr") is not None or r.get("training_psnr") is not None for r in records):
        plot = plot_refinement(run.report / "refinement_psnr.png", records)
    return _Refinement(progress, metrics, plot)


MAIN_PLOTS = ("trajectory", "translation_error", "psnr_vs_scale", "crops", "timing", "gaussians")
SECTION_PLOTS = ("psnr_vs_scale", "crops")


def _main_plots(run: RunFolder, metrics: dict, render_evaluation) -> dict[str, Path]:
    folder = run.report
    images: dict[str, Path] = {}
    trajectory = metrics.get("trajectory", {})
    protocol = trajectory.get("protocol", {})
    alignment = protocol.get("alignment")
    frames_info = _read_json_or_none(run.root / "frames.json") or {"frames": []}
    records = frames_info.get("frames", [])
    timestamp_kind = metrics.get("dataset", {}).get("timestamp_kind", "time")
    time_label = "frame" if timestamp_kind == "index" else "time [s]"

    est = read_tum_trajectory(run.traj_est)
    gt = read_tum_trajectory(run.traj_gt, allow_duplicate_timestamps=True) if run.traj_gt.is_file() else None
    keyframes = read_tum_trajectory(run.keyframes) if run.keyframes.is_file() else None
    est_aligned = _align(est.positions, alignment)
    keyframes_aligned = _align(keyframes.positions, alignment) if keyframes is not None else np.zeros((0, 3))
    loops = loop_closures(_read_json_or_none(run.loops))
    ate = trajectory.get("ate", {}).get("rmse")
    images["trajectory"] = plot_trajectory(folder / "trajectory.png", gt.positions if gt is not None else np.zeros((0, 3)),
                                           est_aligned, keyframes_aligned, loops, ate)

    matched = protocol.get("frames", {})
    if gt is not None and matched.get("matched_est_indices"):
        est_idx = np.asarray(matched["matched_est_indices"], dtype=np.int64)
        gt_idx = np.asarray(matched["matched_gt_indices"], dtype=np.int64)
        errors = np.linalg.norm(gt.positions[gt_idx] - est_aligned[est_idx], axis=1)
        keyframe_times = keyframes.timestamps if keyframes is not None else np.zeros(0)
        images["translation_error"] = plot_translation_error(folder / "translation_error.png", est.timestamps[est_idx],
                                                             errors, keyframe_times, time_label)
    images.update(_section_plots(folder, metrics, render_evaluation, None))
    timings = _read_json_or_none(run.timings)
    if timings and timings.get("stages"):
        images["timing"] = plot_timing(folder / "timing.png", timings)
    if records:
        counts = np.asarray([r.get("gaussians", 0) for r in records], dtype=np.int64)
        indices = np.asarray([r["index"] for r in records], dtype=np.int64)
        is_keyframe = np.asarray([r.get("keyframe_id", -1) >= 0 for r in records], dtype=bool)
        images["gaussians"] = plot_gaussians(folder / "gaussians.png", indices, counts, is_keyframe)
    return images


def _section_plots(folder: Path, metrics: dict, render_evaluation, label: str | None) -> dict[str, Path]:
    """PSNR against scale and the crop grid of one evaluation (``<plot>.png``, or ``<plot>_<label>.png``)."""
    suffix = "" if label is None else f"_{label}"
    images: dict[str, Path] = {}
    render = metrics.get("render") if isinstance(metrics.get("render"), dict) else None
    showcase = getattr(render_evaluation, "showcase", None)
    points, subtitle = _psnr_points(render, showcase)
    if points:
        images["psnr_vs_scale"] = plot_psnr_vs_scale(folder / f"psnr_vs_scale{suffix}.png", points, subtitle,
                                                     _reference_text(render))
    if showcase is not None:
        images["crops"] = plot_crops(folder / f"crops{suffix}.png", showcase)
    return images


def _other_evaluations(run: RunFolder, label: str | None, metrics: dict) -> dict[str, dict]:
    """label -> metrics of every evaluation other than the run's own: ``metrics_<label>.json`` files in the run
    folder, and the one just made (which may not be written yet)."""
    sections: dict[str, dict] = {}
    for path in sorted(run.root.glob("metrics_*.json")):
        data = _read_json_or_none(path)
        if isinstance(data, dict):
            sections[path.stem[len("metrics_"):]] = data
    if label is not None:
        sections[label] = metrics
    return dict(sorted(sections.items()))


def _fmt(value, spec: str, unit: str = "", none: str = "-") -> str:
    return none if value is None else f"{value:{spec}}{unit}"


def loop_text(loops_data: Any) -> str:
    """The report's 'loop closures' line from the content of ``loops.json`` (None when the file is missing)."""
    if loops_data is None:
        return "not recorded (no loops.json)"
    loops = loop_closures(loops_data)
    accepted, rejected = sum(a for _, _, a in loops), sum(not a for _, _, a in loops)
    enabled = loops_data.get("enabled") if isinstance(loops_data, dict) else None
    text = f"{accepted} accepted, {rejected} rejected" if loops else "0 loop closures"
    if enabled is False:
        text += " (loop closure off)"
    return text


def _esc(value: Any) -> str:
    return html.escape(str(value))


def _render_table(render_rows: list[dict]) -> list[str]:
    parts = ["<table><tr><th>views</th><th>scale</th><th>size</th><th>mode</th><th>PSNR [dB]</th><th>SSIM</th>"
             "<th>LPIPS</th><th>depth L1 [cm]</th><th>frames</th></tr>"]
    for row in render_rows:
        parts.append(f"<tr><td class='l'>{_esc(row.get('views', '-'))}</td><td>{row['scale']:g}</td>"
                     f"<td>{row['width']}x{row['height']}</td><td class='l'>"
                     f"{_esc(row['mode'])}</td><td>{_fmt(row['psnr'], '.2f')}</td><td>{row['ssim']:.4f}</td>"
                     f"<td>{_fmt(row.get('lpips'), '.4f')}</td>"
                     f"<td>{_fmt(row.get('depth_l1') and row['depth_l1'] * 100, '.2f')}</td><td>{row['frames']}</td></tr>")
    parts.append("</table>")
    return parts


def _ate_text(trajectory: dict) -> str:
    ate = trajectory.get("ate", {})
    return (f"{_fmt(ate.get('rmse') and ate['rmse'] * 100, '.2f', ' cm')} over {ate.get('count', 0)} poses "
            f"({trajectory.get('protocol', {}).get('alignment', {}).get('method', '?')} alignment)")


def _protocol_items(metrics: dict) -> list[str]:
    """The evaluation protocol in a few sentences (the full record is in the metrics file)."""
    items = []
    trajectory = metrics.get("trajectory", {})
    protocol = trajectory.get("protocol", {})
    if protocol:
        association, alignment = protocol.get("association", {}), protocol.get("alignment", {})
        matched = f"{protocol.get('num_matched')} of {protocol.get('num_est_poses')} estimated poses matched"
        if association.get("note"):  # e.g. Replica: the timestamps are frame indices
            matched += f" ({association['note']})"
        elif association.get("method") == "timestamp":
            matched += f" by timestamp (within {association.get('max_diff_s')} s)"
        else:
            matched += " by index"
        items.append(f"Trajectory: {matched}; {alignment.get('description', alignment.get('method', '?'))}.")
        if alignment.get("fallback"):
            items.append(f"Alignment: {alignment['fallback']}.")
    render = metrics.get("render") if isinstance(metrics.get("render"), dict) else None
    if render and "protocol" in render:
        rp = render["protocol"]
        frames = rp.get("frames", {})
        scales = ", ".join(_scale_label(s) for s in rp.get("scales", []))
        reference = rp.get("scale_reference", {})
        other = "mapping" if reference.get("resolution") == "native" else "native"
        other_size = reference.get(f"{other}_resolution")
        items.append(f"Rendering: the map from the estimated poses, no exposure compensation, at scale {scales} of "
                     f"the {_reference_text(render)}"
                     + (f" ({other} resolution {'x'.join(map(str, other_size))})" if other_size else "")
                     + f", footprint {', '.join(rp.get('modes', []))}.")
        for selection in frames.get("views", []):
            items.append(f"{selection_text(selection).strip()}.")
        truth = rp.get("ground_truth", {})
        if truth:
            items.append(f"Ground truth: {truth.get('source', '?')}"
                         f"{'; colour: ' + truth['color'] if truth.get('color') else ''}.")
        lpips = render.get("lpips")
        if isinstance(lpips, str):
            items.append(f"LPIPS: {lpips}.")
    elif render and "unavailable" in render:
        items.append(f"Rendering: unavailable: {render['unavailable']}.")
    return items


def _html(run: RunFolder, main: dict | None, timings: dict | None, loops_data: Any, images: dict[str, Path],
          sections: dict[str, dict], refinement: _Refinement | None = None) -> str:
    esc = _esc
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>mipslam run report</title><style>",
        "body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
        "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}"
        "th{background:#f0f0f0}td.l{text-align:left}img{max-width:100%;border:1px solid #ddd;margin:0.4em 0}"
        "li{margin:0.2em 0}",
        "</style></head><body>",
        f"<h1>mipslam run report</h1><p>{esc(run.root)}</p>",
    ]
    if main is None:
        parts.append("<p>The run's own evaluation (metrics.json) is not there; 'mipslam eval RUN_DIR' writes it.</p>")
    else:
        parts.extend(_main_html(main, timings, loops_data, images))
    if refinement is not None:
        parts.extend(_refinement_html(run, refinement, main))
    for label, metrics in sections.items():
        parts.extend(_section_html(run, label, metrics))
    parts.append("</body></html>\n")
    return "\n".join(parts)


def _path_text(path: dict) -> str:
    """The estimate's path length against the ground truth's (metrics.json ``trajectory.path_length``)."""
    if path.get("ratio") is None:
        return "-"
    return f"{path['estimate'] * 100:.1f} cm against {path['ground_truth'] * 100:.1f} cm (x{path['ratio']:.2f})"


_VIEWS_TEXT = {"novel": "novel views", "training": "training views", "all": "all frames",
               "non_keyframes": "non-keyframes", "keyframes": "keyframes"}


def _render_headline(render: dict) -> list[tuple[str, str]]:
    """The headline's render lines: per view set (novel views first), the row nearest scale 1 in the run's mode."""
    rows = render["rows"]
    run_mode = render.get("protocol", {}).get("renderer", {}).get("run_mode", rows[0]["mode"])
    sets = list(dict.fromkeys(row.get("views") for row in rows))
    sets.sort(key=lambda views: views != "novel")
    lines = []
    for views in sets:
        main = min((r for r in rows if r.get("views") == views),
                   key=lambda r: (abs(math.log(r["scale"])), r["mode"] != run_mode))
        what = _VIEWS_TEXT.get(views, views or "evaluated frames")
        lines.append((f"render x{main['scale']:g} {main['width']}x{main['height']} ({main['mode']}, {what})",
                      f"PSNR {_fmt(main['psnr'], '.2f', ' dB')}, SSIM {main['ssim']:.4f}, "
                      f"LPIPS {_fmt(main.get('lpips'), '.4f')}, depth L1 "
                      f"{_fmt(main.get('depth_l1') and main['depth_l1'] * 100, '.2f', ' cm')} over {main['frames']} "
                      "frames"))
    return lines


def _main_html(metrics: dict, timings: dict | None, loops_data: Any, images: dict[str, Path]) -> list[str]:
    esc = _esc
    trajectory = metrics.get("trajectory", {})
    rpe_t, rpe_r = trajectory.get("rpe_translation", {}), trajectory.get("rpe_rotation", {})
    dataset = metrics.get("dataset", {})
    k = dataset.get("intrinsics", {})
    fps = (timings or {}).get("frames_per_second")
    size = metrics.get("map") or {}
    headline = [
        ("sequence", f"{dataset.get('name', '?')} ({dataset.get('kind', '?')}), {metrics.get('frames_processed')} frames "
                     f"mapped at {k.get('width')}x{k.get('height')}"),
        ("ATE RMSE", _ate_text(trajectory)),
        ("RPE per frame", f"{_fmt(rpe_t.get('rmse') and rpe_t['rmse'] * 100, '.2f', ' cm')}, "
                          f"{_fmt(rpe_r.get('rmse'), '.3f', ' deg')}"),
        ("path length", _path_text(trajectory.get("path_length") or {})),
        ("keyframes / Gaussians", f"{metrics.get('keyframes')} / {metrics.get('gaussians')}"),
        *([("map size", f"{size['gaussians']} Gaussians, {size['ply_mb']:.2f} MB (map.ply)")]
          if "gaussians" in size else []),
        ("tracking failures", str(metrics.get("tracking_failures", {}).get("count", 0))),
        ("loop closures", loop_text(loops_data)),
        *([("loop edges against ground truth (medians)", " ".join(summary_lines(metrics["loop_edges"])))]
          if metrics.get("loop_edges") else []),
        ("speed", f"{fps:.2f} frames/s ({timings.get('total_s', 0):.0f} s in total)" if fps else "-"),
    ]
    render = metrics.get("render") if isinstance(metrics.get("render"), dict) else None
    render_rows = (render or {}).get("rows", [])
    if render_rows:
        headline.extend(_render_headline(render))
    elif render and "unavailable" in render:
        headline.append(("render metrics", f"unavailable: {render['unavailable']}"))
    parts = ["<h2>Headline</h2><table>",
             *[f"<tr><th style='text-align:left'>{esc(name)}</th><td class='l'>{esc(value)}</td></tr>"
               for name, value in headline],
             "</table>"]
    if render_rows:
        parts.append("<h2>Rendering (mean over the evaluated frames)</h2>")
        parts.extend(_render_table(render_rows))
    captions = {
        "trajectory": "Trajectory (top view)", "translation_error": "Translation error over time",
        "psnr_vs_scale": "PSNR against rendering scale", "crops": "One frame at each scale: ground truth and footprints",
        "timing": "Timing per stage", "gaussians": "Gaussian count over time",
    }
    for name, caption in captions.items():
        if name in images:
            parts.append(f"<h2>{esc(caption)}</h2><img src='{esc(images[name].name)}' alt='{esc(caption)}'>")
    items = _protocol_items(metrics)
    if items:
        parts.append("<h2>Protocol</h2><ul>" + "".join(f"<li>{esc(item)}</li>" for item in items) +
                     "<li>The complete record is in metrics.json.</li></ul>")
    return parts


def _headline_row(metrics: dict | None, views: str) -> dict | None:
    """The row of ``views`` nearest scale 1 in the run's mode of a metrics dict's render table."""
    render = (metrics or {}).get("render")
    rows = [r for r in (render or {}).get("rows", []) if r.get("views") == views] if isinstance(render, dict) else []
    if not rows:
        return None
    run_mode = render.get("protocol", {}).get("renderer", {}).get("run_mode", rows[0]["mode"])
    return min(rows, key=lambda r: (abs(math.log(r["scale"])), r["mode"] != run_mode))


def _refinement_html(run: RunFolder, refinement: _Refinement, main: dict | None) -> list[str]:
    """The Refinement section: what ran, the SLAM map against the refined one, the refined table, the plot."""
    esc = _esc
    progress, metrics = refinement.progress or {}, refinement.metrics
    sessions = progress.get("sessions") or []
    parts = ["<h2 id='refinement'>Refinement (refined/)</h2>"]
    if progress:
        size = progress.get("image_size") or []
        poses = (metrics or {}).get("refinement", {}).get("poses_refined")
        parts.append(f"<p>mipslam refine: {progress.get('steps', 0)} steps, {progress.get('seconds', 0.0):.1f} s of "
                     f"refinement in {len(sessions)} session(s), over {progress.get('keyframes', '?')} keyframes at "
                     f"{esc(progress.get('resolution', '?'))} resolution "
                     f"{esc('x'.join(map(str, size)))}{'; keyframe poses refined' if poses else ''}. The refined map "
                     "is refined/map.ply (the run's map.ply is unchanged).</p>")
    if metrics is None:
        parts.append(f"<p>The refined map is not evaluated (no refined/metrics.json): 'mipslam refine {esc(run.root)}' "
                     "evaluates it at the end of a session ('--iterations 0': without refining further).</p>")
    else:
        steps = metrics.get("refinement", {}).get("steps")
        parts.append("<table><tr><th>views</th><th>size</th><th>PSNR [dB] SLAM map</th><th>refined</th>"
                     "<th>SSIM SLAM map</th><th>refined</th><th>LPIPS SLAM map</th><th>refined</th><th>frames</th></tr>")
        for views in ("novel", "training", "all", "keyframes", "non_keyframes"):
            after = _headline_row(metrics, views)
            if after is None:
                continue
            before = _headline_row(main, views) or {}
            parts.append(f"<tr><td class='l'>{esc(_VIEWS_TEXT.get(views, views))}</td>"
                         f"<td>{after['width']}x{after['height']}</td><td>{_fmt(before.get('psnr'), '.2f')}</td>"
                         f"<td>{_fmt(after.get('psnr'), '.2f')}</td><td>{_fmt(before.get('ssim'), '.4f')}</td>"
                         f"<td>{_fmt(after.get('ssim'), '.4f')}</td><td>{_fmt(before.get('lpips'), '.4f')}</td>"
                         f"<td>{_fmt(after.get('lpips'), '.4f')}</td><td>{after['frames']}</td></tr>")
        parts.append("</table>")
        parts.append(f"<p>The refined map after step {esc(steps)}, evaluated with the run's own protocol "
                     f"(refined/metrics.json); ATE RMSE of its poses {esc(_ate_text(metrics.get('trajectory', {})))}."
                     "</p>")
        render = metrics.get("render") if isinstance(metrics.get("render"), dict) else None
        if render and render.get("rows"):
            parts.extend(_render_table(render["rows"]))
    if refinement.plot is not None:
        caption = "PSNR against refinement time (a fixed subset of frames, native resolution)"
        parts.append(f"<h3>{esc(caption)}</h3><img src='{esc(refinement.plot.name)}' alt='{esc(caption)}'>")
    return parts


def _section_html(run: RunFolder, label: str, metrics: dict) -> list[str]:
    esc = _esc
    file_name = f"metrics_{label}.json"
    parts = [f"<h2 id='{esc(label)}'>Evaluation '{esc(label)}' ({esc(file_name)})</h2>",
             f"<p>ATE RMSE {esc(_ate_text(metrics.get('trajectory', {})))}.</p>"]
    render = metrics.get("render") if isinstance(metrics.get("render"), dict) else None
    if render and render.get("rows"):
        parts.extend(_render_table(render["rows"]))
    elif render and "unavailable" in render:
        parts.append(f"<p>Render metrics unavailable: {esc(render['unavailable'])}</p>")
    for name, caption in (("psnr_vs_scale", "PSNR against rendering scale"),
                          ("crops", "One frame at each scale: ground truth and footprints")):
        image = run.report / f"{name}_{label}.png"
        if image.is_file():
            parts.append(f"<h3>{esc(caption)}</h3><img src='{esc(image.name)}' alt='{esc(caption)}'>")
    items = _protocol_items(metrics)
    if items:
        parts.append("<ul>" + "".join(f"<li>{esc(item)}</li>" for item in items) +
                     f"<li>The complete record is in {esc(file_name)}.</li></ul>")
    return parts
