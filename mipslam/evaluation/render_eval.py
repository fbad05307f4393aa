"""Rendering evaluation of a run folder: PSNR, SSIM, depth L1 and LPIPS, at several scales and footprint modes.

Protocol (written into ``metrics.json`` under ``"render"`` by :meth:`RenderEvaluation.to_dict`):

* **Map and pose.** The map is ``map.ply`` (the final map of the run; ``refined/map.ply`` for the map of
  ``mipslam refine``, with its ``refined/traj_est.txt``). Every evaluated frame is rendered from its
  *estimated* pose ``T_wc`` (``traj_est.txt``, the map's own frame; no trajectory alignment is applied, since the map
  and the estimate share a frame), with the run's render config (backend, EAA constants, 3D filter) and the
  footprint mode of the table cell (``point | mip | ewa | eaa | exact``). No exposure compensation: the rendered
  colour is compared as it is.
* **Frames** (``frames``; one group of table rows per evaluated set, named by the rows' ``views``):

  - ``split`` (default): two sets. ``novel`` = MonoGS's ``eval_rendering`` frames: the frames whose position in
    ``frames.json`` is a multiple of ``every`` (default :data:`NOVEL_EVERY`) and that are not keyframes.
    ``training`` = the keyframes, every ``k``-th of them with the automatic step below. A set without frames
    has no rows.
  - ``all``, ``keyframes`` (training views) or ``non_keyframes`` (novel views): one set, then every ``k``-th frame
    of it (``every``).

  The automatic step ``k`` evaluates at most :data:`AUTO_FRAME_LIMIT_SINGLE` frames of a set for a one-cell table
  and :data:`AUTO_FRAME_LIMIT_MULTI` for a multi-scale / multi-mode table, which keeps the cost bounded. The
  evaluated frame indices of each set are listed.
* **Resolution and scales.** ``resolution`` says what scale 1 is. ``native`` (default): the camera's own images,
  i.e. the dataset read with ``downscale = 1`` (whole images, original intrinsics). ``mapping``: the frames the run
  mapped (``run.json``, after ``dataset.downscale``, which crops to a multiple of the factor). Scale ``s`` renders
  at ``reference_intrinsics.scaled(s)`` (pixel-centre convention, :meth:`mipslam.types.Intrinsics.scaled`:
  ``f' = s f``, ``c' = s (c + 0.5) - 0.5``, size ``round(s W)``).
* **Ground truth at scale s.**

  - data_synth sequences (``dataset.kind = synthetic``): the exact footprint-averaged image of the procedural scene
    rendered by :func:`data_synth.render_view` at the scaled reference intrinsics from the frame's exact
    ground-truth pose (:func:`data_synth.ground_truth_poses`), with ``S(s) = clamp(ceil(S0 / s), S0, 16)``
    stratified rays per pixel side (``S0`` = the supersampling the sequence was generated with, so the ray density
    per original pixel never drops below the sequence's own), colour rounded to 8 bits like the sequence's PNGs;
    depth is the exact pixel-centre depth. Sensor effects of the sequence (depth noise, holes, exposure jitter)
    are absent.
  - real data: the original (full-resolution, not downscaled) image, resampled by exact area averaging
    (:func:`resize_area`; never bilinear sampling, which would alias the ground truth itself): native resolution,
    the whole image with factor ``s``; mapping resolution, the image cropped like the dataset reader crops for
    ``dataset.downscale = d``, factor ``s / d``. Above the original resolution area resampling replicates pixels
    (no detail is invented). Depth: the area average of the valid (> 0) depths of each output pixel, 0 where it
    covers none.
* **Metrics** (per frame, then the mean over the frames of a set per (scale, mode)): PSNR over all pixels and
  channels, SSIM with the 11x11 Gaussian window of sigma 1.5 in the 3DGS zero-padding convention, depth L1 in metres
  of the rendered depth ``sum T alpha z`` (what mapping fits) over pixels with valid ground-truth depth, LPIPS-alex
  v0.1 (:mod:`mipslam.evaluation.lpips`) where its weights are installed and the image is at least 31 px on each
  side.
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
from mipslam.evaluation.run_files import read_run_config, read_run_json, relative_name, run_file
from mipslam.io.run_folder import RunFolder
from mipslam.io.tum import read_tum_trajectory
from mipslam.render import MODES, RenderOptions, RenderOutput
from mipslam.rendering import FILTER_3D_SCALE, render_view
from mipslam.types import Intrinsics

logger = logging.getLogger(__name__)

__all__ = [
    "AUTO_FRAME_LIMIT_MULTI", "AUTO_FRAME_LIMIT_SINGLE", "DEFAULT_SHOWCASE_MODES", "DEFAULT_SHOWCASE_SCALES",
    "FRAME_SETS", "NOVEL_EVERY", "RESOLUTIONS", "FrameSelection", "GroundTruth", "GroundTruthView",
    "RenderEvalOptions", "RenderEvaluation", "RunRenderContext", "ScaleModeRow", "Showcase", "SyntheticGroundTruth",
    "AreaResampledGroundTruth", "ViewMetrics", "auto_frame_step", "evaluate_render", "frame_selections",
    "load_render_context", "novel_view_frames", "pick_detail_crop", "render_frame", "select_frames",
    "synth_supersample",
]

FRAME_SETS = ("split", "all", "keyframes", "non_keyframes")
SINGLE_SETS = ("all", "keyframes", "non_keyframes")
RESOLUTIONS = ("native", "mapping")
NOVEL_EVERY = 5  # MonoGS eval_rendering: every 5th frame of the sequence that is not a keyframe
AUTO_FRAME_LIMIT_SINGLE = 50  # frames of a set evaluated by default when the table has one (scale, mode) cell
AUTO_FRAME_LIMIT_MULTI = 8  # ... and when it has several
DEFAULT_SHOWCASE_SCALES = (0.125, 0.25, 0.5, 1.0, 2.0)
DEFAULT_SHOWCASE_MODES = ("point", "mip", "eaa")
LPIPS_MIN_SIDE = 31
SYNTH_MAX_SUPERSAMPLE = 16

FRAME_SET_MEANING = {
    "split": "two row groups: novel views (every 5th frame that is not a keyframe, as MonoGS) and training views "
             "(the keyframes)",
    "all": "every processed frame",
    "keyframes": "keyframes only (training views)",
    "non_keyframes": "non-keyframes only (novel views)",
}
RESOLUTION_MEANING = {
    "native": "scale 1 = the camera's own images: the dataset read with downscale 1, whole images, original intrinsics",
    "mapping": "scale 1 = the frames the run mapped (run.json intrinsics, after dataset.downscale and its crop)",
}


# ----------------------------------------------------------------------------- options and results

@dataclass(frozen=True)
class RenderEvalOptions:
    """What to evaluate. ``modes`` empty = the run's render mode.

    frames: ``split`` (novel and training views as separate rows), ``all``, ``keyframes`` or ``non_keyframes``
    (module docstring). every: ``split``: the novel views' position step in frames.json (None = :data:`NOVEL_EVERY`;
    the training views always take the automatic step); a single set: every k-th frame of it (None = automatic).
    resolution: what ``scales`` are relative to: ``native`` (the camera's own images) or ``mapping`` (the frames
    the run mapped, after ``dataset.downscale``).
    ground_truth: "auto" (exact data_synth ground truth for ``dataset.kind = synthetic``, area resampling of the
    original images otherwise), "exact" or "resampled" (force one). showcase: also render one frame at
    ``showcase_scales`` (default: the evaluated scales when there are several, else
    :data:`DEFAULT_SHOWCASE_SCALES`) in ``showcase_modes`` for the report's crop grid. max_frames: at most this
    many frames of each evaluated set, evenly spaced (every k-th of the set's frames, k = ceil(count / max_frames));
    None = no cap (``mipslam refine``'s progress records use 8).
    """

    frames: Literal["split", "all", "keyframes", "non_keyframes"] = "split"
    resolution: Literal["native", "mapping"] = "native"
    every: int | None = None
    scales: tuple[float, ...] = (1.0,)
    modes: tuple[str, ...] = ()
    lpips: bool = True
    ground_truth: Literal["auto", "exact", "resampled"] = "auto"
    showcase: bool = True
    showcase_scales: tuple[float, ...] | None = None
    showcase_modes: tuple[str, ...] = DEFAULT_SHOWCASE_MODES
    max_frames: int | None = None

    def __post_init__(self):
        if self.frames not in FRAME_SETS:
            raise ConfigError(f"render evaluation: frame set {self.frames!r} is not one of {', '.join(FRAME_SETS)}")
        if self.resolution not in RESOLUTIONS:
            raise ConfigError(f"render evaluation: resolution {self.resolution!r} is not one of "
                              f"{', '.join(RESOLUTIONS)}")
        if self.every is not None and (isinstance(self.every, bool) or int(self.every) != self.every or self.every < 1):
            raise ConfigError(f"render evaluation: 'every' must be a whole number >= 1, got {self.every!r}")
        if self.max_frames is not None and (isinstance(self.max_frames, bool) or int(self.max_frames) != self.max_frames
                                            or self.max_frames < 1):
            raise ConfigError(f"render evaluation: 'max_frames' must be a whole number >= 1, got {self.max_frames!r}")
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
    views: str = "all"  # the evaluated set the frame belongs to: novel | training | all | keyframes | non_keyframes


@dataclass(frozen=True)
class ScaleModeRow:
    """One cell of the table: the mean over the evaluated frames of one set (``views``) at (scale, mode)."""

    views: str  # novel | training (frames = split), else the set's name
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
        return {"views": self.views, "scale": self.scale, "mode": self.mode, "width": self.width,
                "height": self.height, "frames": self.frames, "psnr": _finite(self.psnr), "ssim": self.ssim,
                "depth_l1": self.depth_l1, "lpips": self.lpips}


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

    @property
    def view_sets(self) -> tuple[str, ...]:
        """The evaluated sets that have rows, in row order (e.g. ("novel", "training"))."""
        return tuple(dict.fromkeys(row.views for row in self.rows))

    def row(self, scale: float, mode: str, views: str | None = None) -> ScaleModeRow:
        """The row at (scale, mode) of ``views`` (novel | training | the single set's name); None = the first
        set with rows (the novel views under ``split``, else the one set)."""
        wanted = views if views is not None else next(iter(self.view_sets), None)
        for row in self.rows:
            if row.views == wanted and row.mode == mode and math.isclose(row.scale, scale):
                return row
        raise KeyError(f"no row for scale {scale}, mode {mode!r} and views {wanted!r}")

    def to_dict(self) -> dict[str, Any]:
        """The ``"render"`` section of metrics.json: protocol, the table and the per-frame values."""
        return {
            "protocol": self.protocol,
            "lpips": self.lpips_status,
            "rows": [row.to_dict() for row in self.rows],
            "per_frame": [
                {"frame": v.frame_index, "views": v.views, "keyframe": v.is_keyframe, "scale": v.scale,
                 "mode": v.mode, "psnr": _finite(v.psnr), "ssim": v.ssim, "depth_l1": v.depth_l1, "lpips": v.lpips}
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
    """Ground truth of the run's frames at any scale of a reference resolution (native or mapping)."""

    def view(self, frame_index: int, scale: float) -> GroundTruthView:
        raise NotImplementedError

    def describe(self) -> dict[str, Any]:
        raise NotImplementedError


def synth_supersample(base: int, scale: float) -> int:
    """Rays per pixel side for exact ground truth at ``scale``: ``clamp(ceil(base / scale), base, 16)``."""
    return int(min(SYNTH_MAX_SUPERSAMPLE, max(base, math.ceil(base / scale - 1e-9))))


class SyntheticGroundTruth(GroundTruth):
    """Exact ground truth of a data_synth folder at ``reference_intrinsics.scaled(scale)`` (module docstring)."""

    def __init__(self, root: Path, reference_intrinsics: Intrinsics, source_indices: np.ndarray):
        import data_synth

        self._render = data_synth.render_view
        self.root = Path(root)
        self.scene = data_synth.load_scene(self.root)
        info = data_synth.read_synth_json(self.root)
        self.base_supersample = int(info.get("render", {}).get("supersample", 4))
        self.poses_T_wc = data_synth.ground_truth_poses(self.root)  # [frames, 4, 4] float64
        self.intrinsics = reference_intrinsics
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
        k = self.intrinsics
        return {
            "source": "exact: data_synth.render_view of the procedural scene in synth.json",
            "sequence": str(self.root),
            "pose": "exact ground-truth pose of the frame (data_synth.ground_truth_poses)",
            "color": f"rendered at the {k.width}x{k.height} reference intrinsics .scaled(scale); mean of S x S "
                     "stratified rays over each pixel's unit square, S = clamp(ceil(S0 / scale), S0, 16), "
                     f"S0 = {self.base_supersample}; rounded to 8 bits",
            "depth": "exact camera-frame z of the pixel-centre ray's hit (no sensor noise or holes)",
            "resampling": "none: rendered directly at each scale's intrinsics",
        }


class AreaResampledGroundTruth(GroundTruth):
    """The dataset's original images resampled by exact area averaging to each scale (see the module docstring).

    resolution "native": scale s of the whole original image (factor s); "mapping": scale s of the run's mapping
    resolution, i.e. of the original cropped to a multiple of ``downscale`` (factor s / downscale)."""

    def __init__(self, full_sequence, downscale: int, mapping_intrinsics: Intrinsics,
                 resolution: Literal["native", "mapping"] = "mapping"):
        self.sequence = full_sequence  # RGBDSequence read with downscale = 1
        self.downscale = int(downscale)
        self.resolution = resolution
        full = full_sequence.intrinsics
        cropped = (full.width - full.width % self.downscale, full.height - full.height % self.downscale)
        expected = full.with_size(*cropped)
        expected = expected.scaled(1.0 / self.downscale) if self.downscale > 1 else expected
        if (expected.width, expected.height) != (mapping_intrinsics.width, mapping_intrinsics.height) or not all(
                math.isclose(getattr(expected, k), getattr(mapping_intrinsics, k), rel_tol=1e-6, abs_tol=1e-6)
                for k in ("fx", "fy", "cx", "cy")):
            raise EvaluationError(
                f"{full_sequence.root}: the original images ({full.width}x{full.height}, downscale {self.downscale}) "
                f"do not give the run's mapping intrinsics {mapping_intrinsics}; was the dataset changed since the run?")
        # native: the whole image (the crop only serves the mapping resolution's pixel grid)
        self.used_size = (full.width, full.height) if resolution == "native" else cropped
        self.factor_per_scale = 1.0 if resolution == "native" else 1.0 / self.downscale
        self.intrinsics = full if resolution == "native" else mapping_intrinsics
        self._cache: tuple[int, torch.Tensor, torch.Tensor] | None = None

    def _original(self, frame_index: int) -> tuple[torch.Tensor, torch.Tensor]:
        if self._cache is None or self._cache[0] != frame_index:
            frame = self.sequence[frame_index]
            width, height = self.used_size
            self._cache = (frame_index, frame.color[:height, :width].to(torch.float64),
                           frame.depth[:height, :width].to(torch.float64))
        return self._cache[1], self._cache[2]

    def view(self, frame_index: int, scale: float) -> GroundTruthView:
        color, depth = self._original(frame_index)  # [H, W, 3], [H, W]
        factor = scale * self.factor_per_scale
        if factor == 1.0:
            return GroundTruthView(color.to(torch.float32), depth.to(torch.float32))
        color_s = resize_area(color, factor)
        depth_s = resize_area(depth, factor, valid=depth > 0)
        return GroundTruthView(color_s.to(torch.float32).clamp(0.0, 1.0), depth_s.to(torch.float32))

    def describe(self) -> dict[str, Any]:
        width, height = self.used_size
        if self.resolution == "native":
            image = (f"original {width}x{height} image (whole) resampled by exact area averaging (resize_area) "
                     "with factor scale")
        else:
            image = (f"original {width}x{height} image (cropped to a multiple of downscale {self.downscale}) "
                     "resampled by exact area averaging (resize_area) with factor scale / downscale")
        return {
            "source": "dataset images",
            "sequence": str(self.sequence.root),
            "pose": "the frame's own image (captured at the ground-truth pose)",
            "color": f"{image}; never bilinear; above the original resolution pixels are replicated",
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
    """What rendering evaluation needs from a run folder, loaded once (the dataset only when first needed)."""

    run_dir: Path
    config: Config
    info: dict[str, Any]
    intrinsics: Intrinsics  # mapping resolution
    gaussians: ActivatedGaussians
    frames: list[FrameInfo]
    T_wc_est: torch.Tensor  # [N, 4, 4] float64, row k = frames[k]
    sequence_root: Path
    _ground_truth: dict[tuple[str, str], GroundTruth] = field(default_factory=dict)
    _full_sequence: Any = None  # the run's dataset read with downscale 1
    map_file: str = "map.ply"  # what ``gaussians`` and ``T_wc_est`` were read from, relative to the run folder
    trajectory_file: str = "traj_est.txt"

    def full_sequence(self):
        """The run's dataset read with ``downscale = 1`` (the camera's own images); DatasetError when it is gone."""
        if self._full_sequence is None:
            from mipslam.datasets import make_sequence

            if not self.sequence_root.is_dir():
                raise DatasetError(self.sequence_root, "the run's dataset folder (run.json dataset.root) is not "
                                                       "there; render metrics need its images")
            self._full_sequence = make_sequence(replace(self.config.dataset, path=str(self.sequence_root), downscale=1))
        return self._full_sequence

    def native_intrinsics(self) -> Intrinsics:
        """The camera's own image size and intrinsics (the images on disk, before ``dataset.downscale``)."""
        return self.full_sequence().intrinsics

    def reference_intrinsics(self, resolution: str) -> Intrinsics:
        """What scale 1 renders at: the native intrinsics, or the mapping intrinsics of run.json."""
        if resolution not in RESOLUTIONS:
            raise EvaluationError(f"resolution {resolution!r} is not one of {', '.join(RESOLUTIONS)}")
        return self.native_intrinsics() if resolution == "native" else self.intrinsics

    def ground_truth(self, kind: Literal["auto", "exact", "resampled"] = "auto",
                     resolution: Literal["native", "mapping"] = "native") -> GroundTruth:
        if kind == "auto":
            kind = "exact" if self.config.dataset.kind == "synthetic" else "resampled"
        if (kind, resolution) not in self._ground_truth:
            self._ground_truth[kind, resolution] = self._build_ground_truth(kind, resolution)
        return self._ground_truth[kind, resolution]

    def _build_ground_truth(self, kind: str, resolution: str) -> GroundTruth:
        full = self.full_sequence()
        if kind == "exact":
            if not (self.sequence_root / "synth.json").is_file():
                raise DatasetError(self.sequence_root / "synth.json",
                                   "exact ground truth needs a data_synth folder; use ground_truth='resampled'")
            return SyntheticGroundTruth(self.sequence_root, self.reference_intrinsics(resolution), full.source_indices)
        return AreaResampledGroundTruth(full, self.config.dataset.downscale, self.intrinsics, resolution)


def load_render_context(run_dir: str | Path, *, device: torch.device | str = "cpu", map_ply: str | Path | None = None,
                        traj_est: str | Path | None = None) -> RunRenderContext:
    """Read config.yaml, run.json, frames.json, traj_est.txt and map.ply of a run folder.

    ``map_ply`` / ``traj_est``: render another map from other poses of the same frames instead of the run's own
    (e.g. ``refined/map.ply`` and ``refined/traj_est.txt`` of ``mipslam refine``; relative paths are relative to
    the run folder); None = the run's own file."""
    folder = RunFolder(run_dir)
    config = read_run_config(folder)
    info = read_run_json(folder.root / "run.json")
    records = read_run_json(folder.root / "frames.json").get("frames", [])
    frames = [FrameInfo(k, int(r["index"]), float(r["timestamp"]), int(r["keyframe_id"])) for k, r in enumerate(records)]
    map_path = run_file(folder, map_ply, folder.map_ply)
    traj_path = run_file(folder, traj_est, folder.traj_est)
    est = read_tum_trajectory(traj_path)
    if len(est) != len(frames):
        raise EvaluationError(f"{traj_path}: {len(est)} poses but frames.json lists {len(frames)} frames; "
                              "the run folder is inconsistent (rerun or resume the run)")
    for frame, stamp in zip(frames, est.timestamps):
        if abs(frame.timestamp - float(stamp)) > 1e-4 * max(1.0, abs(frame.timestamp)):
            raise EvaluationError(f"{traj_path}: pose at t={stamp} does not match frames.json frame "
                                  f"{frame.index} (t={frame.timestamp}); the run folder is inconsistent")
    k = info["dataset"]["intrinsics"]
    intrinsics = Intrinsics(fx=float(k["fx"]), fy=float(k["fy"]), cx=float(k["cx"]), cy=float(k["cy"]),
                            width=int(k["width"]), height=int(k["height"]))
    gaussian_map = read_map_ply(map_path, device=device)
    with torch.no_grad():
        gaussians = gaussian_map.activated().detached()
    return RunRenderContext(folder.root, config, info, intrinsics, gaussians, frames,
                            torch.from_numpy(np.array(est.T_wc)), Path(info["dataset"]["root"]),
                            map_file=relative_name(folder, map_path), trajectory_file=relative_name(folder, traj_path))


def select_frames(frames: Sequence[FrameInfo], which: str, every: int) -> list[FrameInfo]:
    """A single set (all / keyframes / non_keyframes), then every ``every``-th frame of it (the first included)."""
    if which not in SINGLE_SETS:
        raise EvaluationError(f"frame set {which!r} is not one of {', '.join(SINGLE_SETS)}")
    chosen = [f for f in frames if which == "all" or (f.keyframe_id >= 0) == (which == "keyframes")]
    return chosen[::every]


def novel_view_frames(frames: Sequence[FrameInfo], every: int = NOVEL_EVERY) -> list[FrameInfo]:
    """MonoGS's ``eval_rendering`` frames: ``for idx in range(0, n, every): if idx in kf_indices: continue``, with
    ``idx`` the frame's position in frames.json."""
    return [f for f in frames if f.position % every == 0 and f.keyframe_id < 0]


def auto_frame_step(count: int, cells: int) -> int:
    """Default ``every``: at most 50 frames for a one-cell table, 8 for a multi-scale / multi-mode table."""
    limit = AUTO_FRAME_LIMIT_SINGLE if cells <= 1 else AUTO_FRAME_LIMIT_MULTI
    return max(1, math.ceil(count / limit))


@dataclass(frozen=True)
class FrameSelection:
    """One evaluated set of frames (one group of table rows, named by ``views``)."""

    views: str  # novel | training | all | keyframes | non_keyframes
    rule: str  # how the frames were chosen, in words
    in_set: int  # frames the rule chose from: non-keyframes (novel), keyframes (training), the set (single)
    every: int  # novel: step of the frames.json positions; else: every k-th frame of the set
    every_rule: str
    frames: tuple[FrameInfo, ...]

    def to_dict(self) -> dict[str, Any]:
        return {"views": self.views, "rule": self.rule, "in_set": self.in_set, "every": self.every,
                "every_rule": self.every_rule, "evaluated": [f.index for f in self.frames],
                "positions": [f.position for f in self.frames],
                "keyframes_among_evaluated": sum(f.keyframe_id >= 0 for f in self.frames)}


def _automatic_rule() -> str:
    return (f"automatic: at most {AUTO_FRAME_LIMIT_SINGLE} frames for one (scale, mode) cell, "
            f"{AUTO_FRAME_LIMIT_MULTI} for several")


def frame_selections(frames: Sequence[FrameInfo], which: str, every: int | None, cells: int,
                     max_frames: int | None = None) -> tuple[FrameSelection, ...]:
    """The evaluated sets of ``which`` (module docstring): ``split`` -> (novel, training), else the one set.
    ``every`` None = the default step; ``cells`` = (scale, mode) cells of the table, for the automatic step;
    ``max_frames``: then at most that many frames of each set, every k-th (:func:`capped_selection`)."""
    selections = _frame_selections(frames, which, every, cells)
    return selections if max_frames is None else tuple(capped_selection(s, max_frames) for s in selections)


def capped_selection(selection: FrameSelection, max_frames: int) -> FrameSelection:
    """``selection`` with at most ``max_frames`` of its frames: every k-th, k = ceil(count / max_frames), the first
    included (a fixed subset: the same frames every time)."""
    count = len(selection.frames)
    if count <= max_frames:
        return selection
    k = math.ceil(count / max_frames)
    # novel views: ``every`` is the step of frames.json positions, which the cap does not multiply
    every = selection.every if selection.views == "novel" else selection.every * k
    return replace(selection, frames=selection.frames[::k], every=every,
                   every_rule=f"{selection.every_rule}; then every {k}-th of those, at most {max_frames} frames")


def _frame_selections(frames: Sequence[FrameInfo], which: str, every: int | None, cells: int
                      ) -> tuple[FrameSelection, ...]:
    if which == "split":
        step = every or NOVEL_EVERY
        keyframes = select_frames(frames, "keyframes", 1)
        non_keyframes = len(frames) - len(keyframes)
        k = auto_frame_step(len(keyframes), cells)
        return (
            FrameSelection("novel", f"MonoGS eval_rendering: frames.json positions 0, {step}, {2 * step}, ... that "
                                    "are not keyframes", non_keyframes, step,
                           "given by the caller" if every else f"default {NOVEL_EVERY} (MonoGS)",
                           tuple(novel_view_frames(frames, step))),
            FrameSelection("training", "keyframes, every k-th", len(keyframes), k, _automatic_rule(),
                           tuple(keyframes[::k])),
        )
    in_set = select_frames(frames, which, 1)
    k = every or auto_frame_step(len(in_set), cells)
    return (FrameSelection(which, f"{FRAME_SET_MEANING[which]}, every k-th", len(in_set), k,
                           "given by the caller" if every else _automatic_rule(), tuple(in_set[::k])),)


def render_frame(context: RunRenderContext, frame: FrameInfo, scale: float, mode: str,
                 resolution: Literal["native", "mapping"] = "native") -> RenderOutput:
    """Render the map from ``frame``'s estimated pose at ``scale`` of the ``resolution`` reference in ``mode``."""
    T_cw = se3_inverse(context.T_wc_est[frame.position]).to(torch.float32)  # [4, 4]
    intrinsics = context.reference_intrinsics(resolution).scaled(scale)
    with torch.no_grad():
        return render_view(context.gaussians, T_cw, intrinsics, context.config.render, mode=mode)


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
    """Render metrics of a run folder (or a loaded :class:`RunRenderContext`) per (evaluated set, scale, mode); see
    the module docstring for the protocol. Raises EvaluationError (run folder problems), DatasetError (dataset
    moved)."""
    options = options or RenderEvalOptions()
    context = run if isinstance(run, RunRenderContext) else load_render_context(run)
    modes = tuple(options.modes) or (context.config.render.mode,)
    scales = tuple(float(s) for s in options.scales)
    cells = [(s, m) for s in scales for m in modes]
    selections = frame_selections(context.frames, options.frames, options.every, len(cells), options.max_frames)
    evaluated = [s for s in selections if s.frames]
    if not evaluated:
        raise EvaluationError(f"{context.run_dir}: the frame set '{options.frames}' is empty "
                              f"({len(context.frames)} frames processed); choose another set")
    ground_truth = context.ground_truth(options.ground_truth, options.resolution)
    device = context.gaussians.means.device
    lpips_model, lpips_status = _load_lpips(options.lpips, device)

    views: list[ViewMetrics] = []
    sizes: dict[float, tuple[int, int]] = {}
    for selection in evaluated:
        for frame in selection.frames:
            for scale in scales:
                truth = ground_truth.view(frame.index, scale)
                sizes[scale] = (truth.color.shape[1], truth.color.shape[0])
                for mode in modes:
                    views.append(_view_metrics(context, frame, selection.views, scale, mode, options.resolution,
                                               truth, lpips_model))
            logger.debug("render evaluation: frame %d (%s) done", frame.index, selection.views)
    rows = tuple(_aggregate(views, selection.views, scale, mode, sizes[scale])
                 for selection in evaluated for scale, mode in cells)
    showcase = (_showcase(context, list(evaluated[0].frames), ground_truth, options, scales)
                if options.showcase else None)
    protocol = _protocol(context, options, modes, scales, selections, ground_truth, lpips_status, showcase)
    return RenderEvaluation(rows, tuple(views), protocol, lpips_status, showcase)


def _view_metrics(context: RunRenderContext, frame: FrameInfo, views_name: str, scale: float, mode: str,
                  resolution: str, truth: GroundTruthView, lpips_model) -> ViewMetrics:
    out = render_frame(context, frame, scale, mode, resolution)
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
                       value_psnr, value_ssim, value_depth, value_lpips, views_name)


def _mean(values: list[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return float(np.mean(present)) if present else None


def _aggregate(views: list[ViewMetrics], views_name: str, scale: float, mode: str,
               size: tuple[int, int]) -> ScaleModeRow:
    cell = [v for v in views if v.views == views_name and v.mode == mode and v.scale == scale]
    return ScaleModeRow(views_name, scale, mode, size[0], size[1], len(cell), float(np.mean([v.psnr for v in cell])),
                        float(np.mean([v.ssim for v in cell])), _mean([v.depth_l1 for v in cell]),
                        _mean([v.lpips for v in cell]))


def _showcase(context: RunRenderContext, chosen: list[FrameInfo], ground_truth: GroundTruth,
              options: RenderEvalOptions, scales: tuple[float, ...]) -> Showcase:
    frame = chosen[len(chosen) // 2]
    showcase_scales = tuple(options.showcase_scales or (scales if len(scales) > 1 else DEFAULT_SHOWCASE_SCALES))
    truths = {s: ground_truth.view(frame.index, s).color for s in showcase_scales}
    reference = truths[min(showcase_scales, key=lambda s: abs(s - 1.0))]
    renders = {(s, m): render_frame(context, frame, s, m, options.resolution).color.clamp(0.0, 1.0).detach().cpu()
               .to(torch.float32) for s in showcase_scales for m in options.showcase_modes}
    return Showcase(frame.index, showcase_scales, tuple(options.showcase_modes), pick_detail_crop(reference), truths,
                    renders)


def _intrinsics_dict(k: Intrinsics) -> dict[str, Any]:
    return {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy, "width": k.width, "height": k.height}


def _protocol(context: RunRenderContext, options: RenderEvalOptions, modes, scales,
              selections: tuple[FrameSelection, ...], ground_truth: GroundTruth, lpips_status: str,
              showcase: Showcase | None) -> dict[str, Any]:
    render_cfg = context.config.render
    mapping, native = context.intrinsics, context.native_intrinsics()
    reference = context.reference_intrinsics(options.resolution)
    evaluated = sorted({f.position: f for s in selections for f in s.frames}.values(), key=lambda f: f.position)
    return {
        "map": {"file": context.map_file, "gaussians": int(context.gaussians.means.shape[0])},
        "pose": f"estimated T_wc of each frame ({context.trajectory_file}, the map's frame); no alignment; the map is "
                "rendered from it",
        "exposure": "no exposure compensation: the rendered colour is compared as it is (no per-frame exposure or "
                    "colour correction, neither the one tracking fits nor one fitted to the ground truth)",
        "frames": {
            "set": options.frames,
            "meaning": FRAME_SET_MEANING[options.frames],
            "views": [s.to_dict() for s in selections],
            "evaluated": [f.index for f in evaluated],
            "keyframes_among_evaluated": sum(f.keyframe_id >= 0 for f in evaluated),
        },
        "resolution": options.resolution,
        "scales": list(scales),
        "scale_reference": {
            "resolution": options.resolution,
            "meaning": RESOLUTION_MEANING[options.resolution],
            "size": [reference.width, reference.height],
            "native_resolution": [native.width, native.height],
            "mapping_resolution": [mapping.width, mapping.height],
            "dataset_downscale": context.config.dataset.downscale,
            "intrinsics": _intrinsics_dict(reference),
            "scaling": "reference intrinsics .scaled(scale): f' = s f, c' = s (c + 0.5) - 0.5, "
                       "size round(s W) x round(s H)",
        },
        "modes": list(modes),
        "renderer": {"run_mode": render_cfg.mode, "backend": render_cfg.backend, "filter_3d": render_cfg.filter_3d,
                     **({"filter_3d_variance": f"{FILTER_3D_SCALE} / nu^2 per Gaussian, nu = its highest "
                                               "sampling rate (f / z) among the keyframes that trained it "
                                               "(map.ply max_sampling_rate), the same at every scale"}
                        if render_cfg.filter_3d else {}),
                     "eaa_max_nodes": render_cfg.eaa_max_nodes, "eaa_gamma": RenderOptions.eaa_gamma,
                     "eaa_eta": RenderOptions.eaa_eta, "eaa_tau": RenderOptions.eaa_tau,
                     "eaa_k_sigma": RenderOptions.k_sigma, "near_plane": RenderOptions.near_plane},
        "ground_truth": ground_truth.describe(),
        "metrics": {
            "psnr": "10 log10(1 / MSE) over all pixels and channels of the rendered colour (clamped to [0, 1]); "
                    "mean over the frames of a set",
            "ssim": "11x11 Gaussian window, sigma 1.5, zero padding as 3DGS utils/loss_utils.ssim; mean over the "
                    "frames of a set",
            "depth_l1": "mean |D - D_gt| in metres, D = rendered sum T alpha z, over pixels with valid ground-truth depth",
            "lpips": lpips_status,
        },
        "showcase": None if showcase is None else {
            "frame": showcase.frame_index, "scales": list(showcase.scales), "modes": list(showcase.modes),
            "crop_box_fraction": list(showcase.crop_box),
        },
    }
