"""Rendering evaluation of a run folder: PSNR, SSIM, depth L1 and LPIPS, at several scales and footprint modes.

Protocol (written into ``metrics.json`` under ``"render"`` by :meth:`RenderEvaluation.to_dict`):

* **Map and pose.** The map is ``map.ply`` (the final map of the run). Every evaluated frame is rendered from its
  *estimated* pose ``T_wc`` (``traj_est.txt``, the map's own frame; no trajectory alignment is applied, since the map
  and the estimate share a frame), with the run's render config (backend, EAA constants, 3D filter) and the
  footprint mode of the table cell (``point | mip | ewa | eaa | exact``).
* **Frames.** ``all`` processed frames, ``keyframes`` (training views) or ``non_keyframes`` (novel views), from
  ``frames.json``; then every ``k``-th frame of that set (``every``; by default ``k`` is chosen so that at most
  :data:`AUTO_FRAME_LIMIT_SINGLE` frames are evaluated for a one-cell table and :data:`AUTO_FRAME_LIMIT_MULTI` for
  a multi-scale / multi-mode table, which keeps the cost bounded). The evaluated frame indices are listed.
* **Scales.** Scale ``s`` renders at ``mapping_intrinsics.scaled(s)`` (pixel-centre convention,
  :meth:`mipslam.types.Intrinsics.scaled`: ``f' = s f``, ``c' = s (c + 0.5) - 0.5``, size ``round(s W)``), where the
  mapping intrinsics are those of the frames the run mapped (``run.json``, after ``dataset.downscale``).
* **Ground truth at scale s.**

  - data_synth sequences (``dataset.kind = synthetic``): the exact footprint-averaged image of the procedural scene
    rendered by :func:`data_synth.render_view` at the scaled intrinsics from the frame's exact ground-truth pose
    (:func:`data_synth.ground_truth_poses`), with ``S(s) = clamp(ceil(S0 / s), S0, 16)`` stratified rays per pixel
    side (``S0`` = the supersampling the sequence was generated with, so the ray density per original pixel never
    drops below the sequence's own), colour rounded to 8 bits like the sequence's PNGs; depth is the exact
    pixel-centre depth. Sensor effects of the sequence (depth noise, holes, exposure jitter) are absent.
  - real data: the original (full-resolution, not downscaled) image, cropped like the dataset reader crops for
    ``dataset.downscale = d``, resampled by exact area averaging (:func:`resize_area`, factor ``s / d``; never
    bilinear sampling, which would alias the ground truth itself). Above the original resolution area resampling
    replicates pixels (no detail is invented). Depth: the area average of the valid (> 0) depths of each output
    pixel, 0 where it covers none.
* **Metrics** (per frame, then the mean over frames per (scale, mode)): PSNR over all pixels and channels, SSIM
  with the 11x11 Gaussian window of sigma 1.5 in the 3DGS zero-padding convention, depth L1 in metres of the
  rendered depth ``sum T alpha z`` (what mapping fits) over pixels with valid ground-truth depth, LPIPS-alex v0.1
  (:mod:`mipslam.evaluation.lpips`) where its weights are installed and the image is at least 31 px on each side.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np
import torch

from mipslam.config import Config
from mipslam.errors import ConfigError, DatasetError, EvaluationError
from mipslam.evaluation.image_metrics import depth_l1, psnr, resize_area, ssim
from mipslam.gaussians import ActivatedGaussians
from mipslam.geometry import se3_inverse
from mipslam.io.ply import read_map_ply
from mipslam.evaluation.run_files import read_run_config, read_run_json
from mipslam.io.run_folder import RunFolder
from mipslam.io.tum import read_tum_trajectory
from mipslam.render import MODES, RenderOutput
from mipslam.rendering import render_view
from mipslam.types import Intrinsics

logger = logging.getLogger(__name__)

__all__ = [
    "AUTO_FRAME_LIMIT_MULTI", "AUTO_FRAME_LIMIT_SINGLE", "DEFAULT_SHOWCASE_MODES", "DEFAULT_SHOWCASE_SCALES",
    "FRAME_SETS", "GroundTruth", "GroundTruthView", "RenderEvalOptions", "RenderEvaluation", "RunRenderContext",
    "ScaleModeRow", "Showcase", "SyntheticGroundTruth", "AreaResampledGroundTruth", "ViewMetrics",
    "auto_frame_step", "evaluate_render", "load_render_context", "pick_detail_crop", "render_frame",
    "select_frames", "synth_supersample",
]

FRAME_SETS = ("all", "keyframes", "non_keyframes")
AUTO_FRAME_LIMIT_SINGLE = 50  # frames evaluated by default when the table has one (scale, mode) cell
AUTO_FRAME_LIMIT_MULTI = 8  # ... and when it has several
DEFAULT_SHOWCASE_SCALES = (0.125, 0.25, 0.5, 1.0, 2.0)
DEFAULT_SHOWCASE_MODES = ("point", "mip", "eaa")
LPIPS_MIN_SIDE = 31
SYNTH_MAX_SUPERSAMPLE = 16


# ----------------------------------------------------------------------------- options and results

@dataclass(frozen=True)
class RenderEvalOptions:
    """What to evaluate. ``modes`` empty = the run's render mode; ``every`` None = automatic (module docstring).

    ground_truth: "auto" (exact data_synth ground truth for ``dataset.kind = synthetic``, area resampling of the
    original images otherwise), "exact" or "resampled" (force one). showcase: also render one frame at
    ``showcase_scales`` (default: the evaluated scales when there are several, else
    :data:`DEFAULT_SHOWCASE_SCALES`) in ``showcase_modes`` for the report's crop grid.
    """

    frames: Literal["all", "keyframes", "non_keyframes"] = "all"
    every: int | None = None
    scales: tuple[float, ...] = (1.0,)
    modes: tuple[str, ...] = ()
    lpips: bool = True
    ground_truth: Literal["auto", "exact", "resampled"] = "auto"
    showcase: bool = True
    showcase_scales: tuple[float, ...] | None = None
    showcase_modes: tuple[str, ...] = DEFAULT_SHOWCASE_MODES

    def __post_init__(self):
        if self.frames not in FRAME_SETS:
            raise ConfigError(f"render evaluation: frame set {self.frames!r} is not one of {', '.join(FRAME_SETS)}")
        if self.every is not None and (isinstance(self.every, bool) or int(self.every) != self.every or self.every < 1):
            raise ConfigError(f"render evaluation: 'every' must be a whole number >= 1, got {self.every!r}")
        if not self.scales or not all(isinstance(s, (int, float)) and math.isfinite(s) and s > 0 for s in self.scales):
            raise ConfigError(f"render evaluation: scales must be positive numbers, got {self.scales!r}")
        for mode in (*self.modes, *self.showcase_modes):
            if mode not in MODES:
                raise ConfigError(f"render evaluation: unknown footprint mode {mode!r}; choose from {', '.join(MODES)}")
        if self.ground_truth not in ("auto", "exact", "resampled"):
            raise ConfigError(f"render evaluation: ground_truth must be auto, exact or resampled, got {self.ground_truth!r}")


@dataclass(frozen=True)
class ViewMetrics:
    """Metrics of one frame rendered at one scale in one mode (plain floats; None = not computed)."""

    frame_index: int  # index in the run's sequence (frames.json "index")
    is_keyframe: bool
    scale: float
    mode: str
    width: int
    height: int
    psnr: float  # dB
    ssim: float
    depth_l1: float | None  # metres
    lpips: float | None


@dataclass(frozen=True)
class ScaleModeRow:
    """One cell of the table: the mean over the evaluated frames of each metric at (scale, mode)."""

    scale: float
    mode: str
    width: int
    height: int
    frames: int
    psnr: float
    ssim: float
    depth_l1: float | None
    lpips: float | None

    def to_dict(self) -> dict[str, Any]:
        return {"scale": self.scale, "mode": self.mode, "width": self.width, "height": self.height,
                "frames": self.frames, "psnr": _finite(self.psnr), "ssim": self.ssim, "depth_l1": self.depth_l1,
                "lpips": self.lpips}


@dataclass(frozen=True)
class Showcase:
    """One frame at several scales and modes, for the report's crop grid (CPU float32 images in [0, 1]).

    ground_truth[scale]        # [h, w, 3]
    renders[(scale, mode)]     # [h, w, 3]
    crop_box: (x0, y0, x1, y1) as fractions of the image width/height (the same world region at every scale)
    """

    frame_index: int
    scales: tuple[float, ...]
    modes: tuple[str, ...]
    crop_box: tuple[float, float, float, float]
    ground_truth: dict[float, torch.Tensor]
    renders: dict[tuple[float, str], torch.Tensor]


@dataclass(frozen=True)
class RenderEvaluation:
    rows: tuple[ScaleModeRow, ...]
    views: tuple[ViewMetrics, ...]
    protocol: dict[str, Any]
    lpips_status: str  # "computed ..." or "unavailable: why"
    showcase: Showcase | None = None

    def row(self, scale: float, mode: str) -> ScaleModeRow:
        for row in self.rows:
            if row.mode == mode and math.isclose(row.scale, scale):
                return row
        raise KeyError(f"no row for scale {scale} and mode {mode!r}")

    def to_dict(self) -> dict[str, Any]:
        """The ``"render"`` section of metrics.json: protocol, the table and the per-frame values."""
        return {
            "protocol": self.protocol,
            "lpips": self.lpips_status,
            "rows": [row.to_dict() for row in self.rows],
            "per_frame": [
                {"frame": v.frame_index, "keyframe": v.is_keyframe, "scale": v.scale, "mode": v.mode,
                 "psnr": _finite(v.psnr), "ssim": v.ssim, "depth_l1": v.depth_l1, "lpips": v.lpips}
                for v in self.views
            ],
        }


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


# ----------------------------------------------------------------------------- ground truth

@dataclass(frozen=True)
class GroundTruthView:
    color: torch.Tensor  # [h, w, 3] float32 in [0, 1]
    depth: torch.Tensor  # [h, w] float32 metres, 0 = none


class GroundTruth:
    """Ground truth of the run's frames at any scale of the mapping resolution."""

    def view(self, frame_index: int, scale: float) -> GroundTruthView:
        raise NotImplementedError

    def describe(self) -> dict[str, Any]:
        raise NotImplementedError


def synth_supersample(base: int, scale: float) -> int:
    """Rays per pixel side for exact ground truth at ``scale``: ``clamp(ceil(base / scale), base, 16)``."""
    return int(min(SYNTH_MAX_SUPERSAMPLE, max(base, math.ceil(base / scale - 1e-9))))


class SyntheticGroundTruth(GroundTruth):
    """Exact ground truth of a data_synth folder (see the module docstring)."""

    def __init__(self, root: Path, mapping_intrinsics: Intrinsics, source_indices: np.ndarray):
        import data_synth

        self._render = data_synth.render_view
        self.root = Path(root)
        self.scene = data_synth.load_scene(self.root)
        info = data_synth.read_synth_json(self.root)
        self.base_supersample = int(info.get("render", {}).get("supersample", 4))
        self.poses_T_wc = data_synth.ground_truth_poses(self.root)  # [frames, 4, 4] float64
        self.intrinsics = mapping_intrinsics
        self.source_indices = np.asarray(source_indices, dtype=np.int64)
        if self.source_indices.size and int(self.source_indices.max()) >= len(self.poses_T_wc):
            raise DatasetError(self.root / "synth.json", f"the run's frames reach source frame "
                               f"{int(self.source_indices.max())} but the sequence has {len(self.poses_T_wc)} frames")

    def view(self, frame_index: int, scale: float) -> GroundTruthView:
        T_wc = self.poses_T_wc[int(self.source_indices[frame_index])]
        color, depth = self._render(self.scene, T_wc, self.intrinsics.scaled(scale),
                                    supersample=synth_supersample(self.base_supersample, scale))
        color = np.round(color * 255.0) / 255.0  # like the sequence's 8-bit PNGs
        return GroundTruthView(torch.from_numpy(color.astype(np.float32)), torch.from_numpy(depth))

    def describe(self) -> dict[str, Any]:
        return {
            "source": "exact: data_synth.render_view of the procedural scene in synth.json",
            "sequence": str(self.root),
            "pose": "exact ground-truth pose of the frame (data_synth.ground_truth_poses)",
            "color": "mean of S x S stratified rays over each pixel's unit square, S = clamp(ceil(S0 / scale), S0, 16), "
                     f"S0 = {self.base_supersample}; rounded to 8 bits",
            "depth": "exact camera-frame z of the pixel-centre ray's hit (no sensor noise or holes)",
            "resampling": "none: rendered directly at each scale's intrinsics",
        }


class AreaResampledGroundTruth(GroundTruth):
    """The dataset's original images resampled by exact area averaging to each scale (see the module docstring)."""

    def __init__(self, full_sequence, downscale: int, mapping_intrinsics: Intrinsics):
        self.sequence = full_sequence  # RGBDSequence read with downscale = 1
        self.downscale = int(downscale)
        full = full_sequence.intrinsics
        self.cropped_size = (full.width - full.width % self.downscale, full.height - full.height % self.downscale)
        expected = full.with_size(*self.cropped_size)
        expected = expected.scaled(1.0 / self.downscale) if self.downscale > 1 else expected
        if (expected.width, expected.height) != (mapping_intrinsics.width, mapping_intrinsics.height) or not all(
                math.isclose(getattr(expected, k), getattr(mapping_intrinsics, k), rel_tol=1e-6, abs_tol=1e-6)
                for k in ("fx", "fy", "cx", "cy")):
            raise EvaluationError(
                f"{full_sequence.root}: the original images ({full.width}x{full.height}, downscale {self.downscale}) "
                f"do not give the run's mapping intrinsics {mapping_intrinsics}; was the dataset changed since the run?")
        self._cache: tuple[int, torch.Tensor, torch.Tensor] | None = None

    def _original(self, frame_index: int) -> tuple[torch.Tensor, torch.Tensor]:
        if self._cache is None or self._cache[0] != frame_index:
            frame = self.sequence[frame_index]
            width, height = self.cropped_size
            self._cache = (frame_index, frame.color[:height, :width].to(torch.float64),
                           frame.depth[:height, :width].to(torch.float64))
        return self._cache[1], self._cache[2]

    def view(self, frame_index: int, scale: float) -> GroundTruthView:
        color, depth = self._original(frame_index)  # [H, W, 3], [H, W]
        factor = scale / self.downscale
        if factor == 1.0:
            return GroundTruthView(color.to(torch.float32), depth.to(torch.float32))
        color_s = resize_area(color, factor)
        depth_s = resize_area(depth, factor, valid=depth > 0)
        return GroundTruthView(color_s.to(torch.float32).clamp(0.0, 1.0), depth_s.to(torch.float32))

    def describe(self) -> dict[str, Any]:
        width, height = self.cropped_size
        return {
            "source": "dataset images",
            "sequence": str(self.sequence.root),
            "pose": "the frame's own image (captured at the ground-truth pose)",
            "color": f"original {width}x{height} image (cropped to a multiple of downscale {self.downscale}) resampled "
                     "by exact area averaging (resize_area) with factor scale / downscale; never bilinear; above "
                     "the original resolution pixels are replicated",
            "depth": "area average of the valid (> 0) original depths under each output pixel, 0 where none",
            "resampling": "area",
        }


# ----------------------------------------------------------------------------- the run

@dataclass(frozen=True)
class FrameInfo:
    position: int  # row in frames.json / traj_est.txt
    index: int  # index in the run's sequence
    timestamp: float
    keyframe_id: int


@dataclass
class RunRenderContext:
    """What rendering evaluation needs from a run folder, loaded once."""

    run_dir: Path
    config: Config
    info: dict[str, Any]
    intrinsics: Intrinsics  # mapping resolution
    gaussians: ActivatedGaussians
    frames: list[FrameInfo]
    T_wc_est: torch.Tensor  # [N, 4, 4] float64, row k = frames[k]
    sequence_root: Path
    _ground_truth: dict[str, GroundTruth] = field(default_factory=dict)

    def ground_truth(self, kind: Literal["auto", "exact", "resampled"] = "auto") -> GroundTruth:
        if kind == "auto":
            kind = "exact" if self.config.dataset.kind == "synthetic" else "resampled"
        if kind not in self._ground_truth:
            self._ground_truth[kind] = self._build_ground_truth(kind)
        return self._ground_truth[kind]

    def _build_ground_truth(self, kind: str) -> GroundTruth:
        from mipslam.datasets import make_sequence

        dataset_cfg = replace(self.config.dataset, path=str(self.sequence_root))
        if not self.sequence_root.is_dir():
            raise DatasetError(self.sequence_root, "the run's dataset folder (run.json dataset.root) is not there; "
                                                   "render metrics need its images")
        if kind == "exact":
            if not (self.sequence_root / "synth.json").is_file():
                raise DatasetError(self.sequence_root / "synth.json",
                                   "exact ground truth needs a data_synth folder; use ground_truth='resampled'")
            sequence = make_sequence(dataset_cfg)
            return SyntheticGroundTruth(self.sequence_root, self.intrinsics, sequence.source_indices)
        full = make_sequence(replace(dataset_cfg, downscale=1))
        return AreaResampledGroundTruth(full, self.config.dataset.downscale, self.intrinsics)


def load_render_context(run_dir: str | Path, *, device: torch.device | str = "cpu") -> RunRenderContext:
    """Read config.yaml, run.json, frames.json, traj_est.txt and map.ply of a run folder."""
    folder = RunFolder(run_dir)
    config = read_run_config(folder)
    info = read_run_json(folder.root / "run.json")
    records = read_run_json(folder.root / "frames.json").get("frames", [])
    frames = [FrameInfo(k, int(r["index"]), float(r["timestamp"]), int(r["keyframe_id"])) for k, r in enumerate(records)]
    est = read_tum_trajectory(folder.traj_est)
    if len(est) != len(frames):
        raise EvaluationError(f"{folder.traj_est}: {len(est)} poses but frames.json lists {len(frames)} frames; "
                              "the run folder is inconsistent (rerun or resume the run)")
    for frame, stamp in zip(frames, est.timestamps):
        if abs(frame.timestamp - float(stamp)) > 1e-4 * max(1.0, abs(frame.timestamp)):
            raise EvaluationError(f"{folder.traj_est}: pose at t={stamp} does not match frames.json frame "
                                  f"{frame.index} (t={frame.timestamp}); the run folder is inconsistent")
    k = info["dataset"]["intrinsics"]
    intrinsics = Intrinsics(fx=float(k["fx"]), fy=float(k["fy"]), cx=float(k["cx"]), cy=float(k["cy"]),
                            width=int(k["width"]), height=int(k["height"]))
    gaussian_map = read_map_ply(folder.map_ply, device=device)
    with torch.no_grad():
        gaussians = gaussian_map.activated().detached()
    return RunRenderContext(folder.root, config, info, intrinsics, gaussians, frames,
                            torch.from_numpy(np.array(est.T_wc)), Path(info["dataset"]["root"]))


def select_frames(frames: Sequence[FrameInfo], which: str, every: int) -> list[FrameInfo]:
    """The frame set (all / keyframes / non_keyframes), then every ``every``-th frame of it (the first included)."""
    if which not in FRAME_SETS:
        raise EvaluationError(f"frame set {which!r} is not one of {', '.join(FRAME_SETS)}")
    chosen = [f for f in frames if which == "all" or (f.keyframe_id >= 0) == (which == "keyframes")]
    return chosen[::every]


def auto_frame_step(count: int, cells: int) -> int:
    """Default ``every``: at most 50 frames for a one-cell table, 8 for a multi-scale / multi-mode table."""
    limit = AUTO_FRAME_LIMIT_SINGLE if cells <= 1 else AUTO_FRAME_LIMIT_MULTI
    return max(1, math.ceil(count / limit))


def render_frame(context: RunRenderContext, frame: FrameInfo, scale: float, mode: str) -> RenderOutput:
    """Render the map from ``frame``'s estimated pose at ``scale`` of the mapping resolution in ``mode``."""
    T_cw = se3_inverse(context.T_wc_est[frame.position]).to(torch.float32)  # [4, 4]
    with torch.no_grad():
        return render_view(context.gaussians, T_cw, context.intrinsics.scaled(scale), context.config.render, mode=mode)


def pick_detail_crop(color: torch.Tensor, fraction: float = 0.4) -> tuple[float, float, float, float]:  # [H, W, 3]
    """The ``fraction``-sized window (fractions of width/height) with the most image-gradient energy.

    Returns (x0, y0, x1, y1) as fractions of the width and height, so the same region can be cut at any scale.
    """
    gray = color.to(torch.float64).mean(dim=-1)  # [H, W]
    height, width = gray.shape
    energy = torch.zeros_like(gray)
    energy[:, 1:] += (gray[:, 1:] - gray[:, :-1]).abs()
    energy[1:, :] += (gray[1:, :] - gray[:-1, :]).abs()
    win_h, win_w = max(1, round(fraction * height)), max(1, round(fraction * width))
    integral = torch.nn.functional.pad(energy.cumsum(0).cumsum(1), (1, 0, 1, 0))  # [H+1, W+1]
    sums = (integral[win_h:, win_w:] - integral[:-win_h, win_w:] - integral[win_h:, :-win_w]
            + integral[:-win_h, :-win_w])  # [H-win_h+1, W-win_w+1]
    best = int(torch.argmax(sums))
    y0, x0 = divmod(best, sums.shape[1])
    return (x0 / width, y0 / height, (x0 + win_w) / width, (y0 + win_h) / height)


# ----------------------------------------------------------------------------- evaluation

def _load_lpips(enabled: bool, device: torch.device):
    if not enabled:
        return None, "unavailable: disabled by the caller (--no-lpips)"
    from mipslam.evaluation.lpips import LPIPSUnavailableError, load_lpips_alex

    try:
        model = load_lpips_alex(device=device)
    except LPIPSUnavailableError as error:
        logger.warning("LPIPS unavailable: %s", error)
        return None, f"unavailable: {error}"
    return model, f"computed: LPIPS-alex v0.1 from {model.source}, images of at least {LPIPS_MIN_SIDE} px per side"


def evaluate_render(run: str | Path | RunRenderContext, options: RenderEvalOptions | None = None) -> RenderEvaluation:
    """Render metrics of a run folder (or a loaded :class:`RunRenderContext`) per (scale, mode); see the module
    docstring for the protocol. Raises EvaluationError (run folder problems), DatasetError (dataset moved)."""
    options = options or RenderEvalOptions()
    context = run if isinstance(run, RunRenderContext) else load_render_context(run)
    modes = tuple(options.modes) or (context.config.render.mode,)
    scales = tuple(float(s) for s in options.scales)
    cells = [(s, m) for s in scales for m in modes]
    in_set = select_frames(context.frames, options.frames, 1)
    if not in_set:
        raise EvaluationError(f"{context.run_dir}: the frame set '{options.frames}' is empty "
                              f"({len(context.frames)} frames processed); choose another set")
    every = options.every or auto_frame_step(len(in_set), len(cells))
    chosen = in_set[::every]
    ground_truth = context.ground_truth(options.ground_truth)
    device = context.gaussians.means.device
    lpips_model, lpips_status = _load_lpips(options.lpips, device)

    views: list[ViewMetrics] = []
    sizes: dict[float, tuple[int, int]] = {}
    for frame in chosen:
        for scale in scales:
            truth = ground_truth.view(frame.index, scale)
            sizes[scale] = (truth.color.shape[1], truth.color.shape[0])
            for mode in modes:
                views.append(_view_metrics(context, frame, scale, mode, truth, lpips_model))
        logger.debug("render evaluation: frame %d done", frame.index)
    rows = tuple(_aggregate(views, scale, mode, sizes[scale]) for scale, mode in cells)
    showcase = _showcase(context, chosen, ground_truth, options, scales) if options.showcase else None
    protocol = _protocol(context, options, modes, scales, in_set, chosen, every, ground_truth, lpips_status, showcase)
    return RenderEvaluation(rows, tuple(views), protocol, lpips_status, showcase)


def _view_metrics(context: RunRenderContext, frame: FrameInfo, scale: float, mode: str, truth: GroundTruthView,
                  lpips_model) -> ViewMetrics:
    out = render_frame(context, frame, scale, mode)
    color = out.color.clamp(0.0, 1.0).to(torch.float32)  # [h, w, 3]
    gt_color = truth.color.to(color.device)
    gt_depth = truth.depth.to(color.device)
    if color.shape != gt_color.shape:
        raise EvaluationError(f"frame {frame.index} at scale {scale}: rendered {tuple(color.shape)} but ground truth "
                              f"{tuple(gt_color.shape)}; the intrinsics of run.json and the dataset disagree")
    with torch.no_grad():
        value_psnr = float(psnr(color, gt_color))
        value_ssim = float(ssim(color, gt_color))
        has_depth = bool(((gt_depth > 0) & torch.isfinite(gt_depth)).any())
        value_depth = float(depth_l1(out.depth.to(torch.float32), gt_depth)) if has_depth else None
        value_lpips = None
        if lpips_model is not None and min(color.shape[0], color.shape[1]) >= LPIPS_MIN_SIDE:
            value_lpips = float(lpips_model(color, gt_color))
    return ViewMetrics(frame.index, frame.keyframe_id >= 0, scale, mode, color.shape[1], color.shape[0],
                       value_psnr, value_ssim, value_depth, value_lpips)


def _mean(values: list[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return float(np.mean(present)) if present else None


def _aggregate(views: list[ViewMetrics], scale: float, mode: str, size: tuple[int, int]) -> ScaleModeRow:
    cell = [v for v in views if v.mode == mode and v.scale == scale]
    return ScaleModeRow(scale, mode, size[0], size[1], len(cell), float(np.mean([v.psnr for v in cell])),
                        float(np.mean([v.ssim for v in cell])), _mean([v.depth_l1 for v in cell]),
                        _mean([v.lpips for v in cell]))


def _showcase(context: RunRenderContext, chosen: list[FrameInfo], ground_truth: GroundTruth,
              options: RenderEvalOptions, scales: tuple[float, ...]) -> Showcase:
    frame = chosen[len(chosen) // 2]
    showcase_scales = tuple(options.showcase_scales or (scales if len(scales) > 1 else DEFAULT_SHOWCASE_SCALES))
    truths = {s: ground_truth.view(frame.index, s).color for s in showcase_scales}
    reference = truths[min(showcase_scales, key=lambda s: abs(s - 1.0))]
    renders = {(s, m): render_frame(context, frame, s, m).color.clamp(0.0, 1.0).detach().cpu().to(torch.float32)
               for s in showcase_scales for m in options.showcase_modes}
    return Showcase(frame.index, showcase_scales, tuple(options.showcase_modes), pick_detail_crop(reference), truths,
                    renders)


def _protocol(context: RunRenderContext, options: RenderEvalOptions, modes, scales, in_set, chosen, every,
              ground_truth: GroundTruth, lpips_status: str, showcase: Showcase | None) -> dict[str, Any]:
    render_cfg = context.config.render
    k = context.intrinsics
    return {
        "map": {"file": "map.ply", "gaussians": int(context.gaussians.means.shape[0])},
        "pose": "estimated T_wc of each frame (traj_est.txt, the map's frame); no alignment; the map is rendered from it",
        "frames": {
            "set": options.frames,
            "meaning": {"all": "every processed frame", "keyframes": "keyframes only (training views)",
                        "non_keyframes": "non-keyframes only (novel views)"}[options.frames],
            "in_set": len(in_set),
            "every": every,
            "every_rule": "given by the caller" if options.every else (
                f"automatic: at most {AUTO_FRAME_LIMIT_SINGLE} frames for one (scale, mode) cell, "
                f"{AUTO_FRAME_LIMIT_MULTI} for several"),
            "evaluated": [f.index for f in chosen],
            "keyframes_among_evaluated": sum(f.keyframe_id >= 0 for f in chosen),
        },
        "scales": list(scales),
        "scale_reference": {
            "mapping_resolution": [k.width, k.height],
            "intrinsics": "mapping intrinsics .scaled(scale): f' = s f, c' = s (c + 0.5) - 0.5, size round(s W) x round(s H)",
        },
        "modes": list(modes),
        "renderer": {"run_mode": render_cfg.mode, "backend": render_cfg.backend, "filter_3d": render_cfg.filter_3d,
                     **({"filter_3d_variance": f"{render_cfg.filter_3d_scale} / nu^2 per Gaussian, nu = its highest "
                                               "sampling rate (f / z) among the keyframes that trained it "
                                               "(map.ply max_sampling_rate), the same at every scale"}
                        if render_cfg.filter_3d else {}),
                     "eaa_max_nodes": render_cfg.eaa_max_nodes, "eaa_gamma": render_cfg.eaa_gamma,
                     "eaa_eta": render_cfg.eaa_eta, "eaa_tau": render_cfg.eaa_tau,
                     "eaa_k_sigma": render_cfg.eaa_k_sigma, "near_plane": render_cfg.near_plane},
        "ground_truth": ground_truth.describe(),
        "metrics": {
            "psnr": "10 log10(1 / MSE) over all pixels and channels of the rendered colour (clamped to [0, 1]); "
                    "mean over frames",
            "ssim": "11x11 Gaussian window, sigma 1.5, zero padding as 3DGS utils/loss_utils.ssim; mean over frames",
            "depth_l1": "mean |D - D_gt| in metres, D = rendered sum T alpha z, over pixels with valid ground-truth depth",
            "lpips": lpips_status,
        },
        "showcase": None if showcase is None else {
            "frame": showcase.frame_index, "scales": list(showcase.scales), "modes": list(showcase.modes),
            "crop_box_fraction": list(showcase.crop_box),
        },
    }
