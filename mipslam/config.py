"""Typed, frozen configuration: one dataclass per stage, loaded from YAML.

* The built-in configs ship inside the package (``mipslam/configs/*.yaml``, :data:`CONFIG_DIR`): the dataset
  configs (``base``, ``replica``, ``tum``, ``synthetic``) and the presets (:data:`PRESETS`). Wherever a config
  file is asked for (``mipslam run CONFIG``, :func:`load_config`, ``inherit_from``), a name that is not an
  existing file but a built-in's name (``tum``) means that built-in (:func:`resolve_config_source`).
* A YAML file may name ``inherit_from: other.yaml`` (or a list); paths are relative to the file.
  Parents are merged first, the child overrides them key by key (deeply); cycles are an error.
* ``--preset NAME`` overlays the built-in ``NAME`` after the file; ``--set a.b=value`` overrides
  come last (values parsed as YAML scalars/lists).
* Unknown keys are rejected with the nearest valid key; values are type-checked and range-checked.
* YAML is always read with ``yaml.safe_load``.

The config holds only the user-facing keys. Each stage owns an options dataclass beside its code
(``TrackingOptions`` in mipslam/tracking.py, ...) with its internal constants, built from its own section (and,
where a sensor property is shared, the dataset's ``depth_noise_power``) by :func:`section_options`; this module
imports no stage. Keys that became constants or were renamed are errors that say so (:func:`retired_key_message`).
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Mapping

import yaml

from mipslam.errors import ConfigError

# The built-in configs: package data (pyproject.toml), so an installed wheel has them as a checkout does.
CONFIG_DIR = Path(__file__).resolve().parent / "configs"
PRESETS = ("fast", "balanced", "accurate")


def _quoted(text: str) -> str:
    """``'text'`` for a message, escaped (``repr``) when it holds a line break or another unprintable character."""
    return f"'{text}'" if text.isprintable() else repr(text)


def _check(cond: bool, key: str, message: str) -> None:
    if not cond:
        raise ConfigError(f"config key '{key}': {message}")


@dataclass(frozen=True)
class RunConfig:
    """Process-level settings."""

    seed: int = 0  # seeds every random choice of the run (keyframe sampling, RANSAC, initial noise)
    device: Literal["auto", "cpu", "cuda"] = "auto"  # auto: CUDA when torch sees it
    threads: int = 0  # torch intra-op threads; 0 keeps torch's default (the count changes results at float level)
    checkpoint_every: int = 50  # frames between checkpoints; 0 = only at the end
    evaluate_at_end: bool = True  # write metrics.json after the last frame (mipslam eval RUN_DIR does it later)
    # Measurements that cost time and change no result (the map's PSNR at the loop's keyframes around each loop
    # correction, in loops.json); off, a run renders nothing it does not need.
    diagnostics: bool = False

    def __post_init__(self):
        _check(self.threads >= 0, "run.threads", "must be >= 0 (0 = torch default)")
        _check(self.checkpoint_every >= 0, "run.checkpoint_every", "must be >= 0")


@dataclass(frozen=True)
class DatasetConfig:
    """Which sequence to read and how, and what the sensor is (intrinsics default to the dataset's own files)."""

    kind: Literal["replica", "tum", "synthetic", "realsense", "realsense_bag"] = "synthetic"
    path: str = ""  # the sequence folder (or .bag file); relative: to the YAML file, or to the working directory
    stride: int = 1  # every n-th frame (>= 1)
    first_frame: int = 0  # index of the first frame read (>= 0)
    max_frames: int = 0  # 0 = all frames
    downscale: int = 1  # integer factor: colour area-averaged, depth without mixing surfaces
    camera: str = ""  # TUM preset: freiburg1 | freiburg2 | freiburg3 (empty = from fx..cy or the folder)
    fx: float | None = None  # pixels, at the images' resolution on disk (unset: the dataset's own)
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    width: int | None = None  # pixels (unset: the images')
    height: int | None = None
    depth_scale: float | None = None  # stored value / depth_scale = metres (Replica 6553.5, TUM 5000)
    # Lens distortion of the images on disk, OpenCV order (k1, k2, p1, p2[, k3]); frames (colour bilinear,
    # depth nearest) are undistorted at the dataset boundary with the same fx..cy. Unset or [] = none.
    distortion: tuple[float, ...] | None = None
    association_tolerance_s: float = 0.02  # seconds; TUM rgb-depth-groundtruth association
    # Depth not registered to colour (a raw Kinect's): the depth camera's fx, fy, cx, cy at its images' resolution,
    # and its pose in the colour camera's frame, [tx, ty, tz] metres or [tx, ty, tz, rx, ry, rz] with a rotation
    # vector in radians. Depth is moved into the colour camera as it is read (mipslam/datasets/images.py
    # DepthRegistration). Unset or [] = registered (the depth camera is the colour camera).
    depth_intrinsics: tuple[float, ...] | None = None
    depth_extrinsics: tuple[float, ...] | None = None
    # Seconds a rolling-shutter colour camera takes to read its rows, top to bottom, in [0, 0.1] (0 = a global
    # shutter); each row is moved to the frame's instant with the tracked motion (docs/tracking.md).
    rolling_shutter_readout_s: float = 0.0
    realtime: bool = False  # realsense_bag: play at the recorded rate, dropping frames (false: every frame)
    # The sensor's depth noise grows as z^p: tracking's direct alignment and loop verification weigh depth
    # residuals in units of z^p (0: metres, for noise-free renders; 2: an active sensor, Kinect, RealSense).
    depth_noise_power: float = 0.0

    def __post_init__(self):
        _check(self.stride >= 1, "dataset.stride", "must be >= 1")
        _check(self.first_frame >= 0, "dataset.first_frame", "must be >= 0")
        _check(self.max_frames >= 0, "dataset.max_frames", "must be >= 0 (0 = all frames)")
        _check(self.downscale >= 1, "dataset.downscale", "must be an integer >= 1")
        for key in ("fx", "fy", "depth_scale"):
            value = getattr(self, key)
            _check(value is None or value > 0, f"dataset.{key}", "must be positive")
        for key in ("width", "height"):
            value = getattr(self, key)
            _check(value is None or value >= 1, f"dataset.{key}", "must be >= 1")
        _check(self.association_tolerance_s > 0, "dataset.association_tolerance_s", "must be positive")
        _check(0 <= self.rolling_shutter_readout_s <= 0.1, "dataset.rolling_shutter_readout_s",
               "must be in [0, 0.1] seconds (0 = a global shutter)")
        _check(self.distortion is None or len(self.distortion) in (0, 4, 5), "dataset.distortion",
               "must be [] or OpenCV's [k1, k2, p1, p2] or [k1, k2, p1, p2, k3]")
        _check(self.distortion is None or all(math.isfinite(v) for v in self.distortion), "dataset.distortion",
               "must be finite numbers")
        _check(self.depth_noise_power >= 0, "dataset.depth_noise_power", "must be >= 0 (0 = metres)")
        _check(self.depth_intrinsics is None or len(self.depth_intrinsics) in (0, 4), "dataset.depth_intrinsics",
               "must be [] or the depth camera's [fx, fy, cx, cy] in pixels")
        _check(self.depth_intrinsics is None or len(self.depth_intrinsics) == 0
               or (all(math.isfinite(v) for v in self.depth_intrinsics) and min(self.depth_intrinsics[:2]) > 0),
               "dataset.depth_intrinsics", "must be finite, with fx and fy positive")
        _check(self.depth_extrinsics is None or len(self.depth_extrinsics) in (0, 3, 6), "dataset.depth_extrinsics",
               "must be [] or the depth camera's pose in the colour camera's frame: [tx, ty, tz] metres or "
               "[tx, ty, tz, rx, ry, rz] (rotation vector, radians)")
        _check(self.depth_extrinsics is None or all(math.isfinite(v) for v in self.depth_extrinsics),
               "dataset.depth_extrinsics", "must be finite numbers")
        _check(not (self.kind.startswith("realsense") and (self.depth_intrinsics or self.depth_extrinsics)),
               "dataset.depth_intrinsics", "does not apply to a RealSense camera or recording: librealsense registers "
               "its depth to colour; unset dataset.depth_intrinsics and dataset.depth_extrinsics")


@dataclass(frozen=True)
class RenderConfig:
    """Renderer settings (docs/design.md, renderer contract and EAA); the renderer's constants are
    :class:`mipslam.render.RenderOptions`' and :mod:`mipslam.rendering`'s."""

    mode: Literal["point", "mip", "ewa", "eaa", "exact"] = "eaa"  # footprint of every render (docs/renderer.md)
    backend: Literal["auto", "torch", "cpu"] = "auto"  # auto: the compiled CPU backend where it loads
    eaa_max_nodes: int = 4  # EAA node cap n_max, >= 1: the speed/accuracy knob (1 = one node everywhere)
    filter_3d: bool = False  # Mip-Splatting 3D smoothing filter (sized by the map's sampling rates)

    def __post_init__(self):
        _check(int(self.eaa_max_nodes) == self.eaa_max_nodes and self.eaa_max_nodes >= 1, "render.eaa_max_nodes",
               "must be an integer >= 1 (1 = one node everywhere)")


@dataclass(frozen=True)
class TrackingConfig:
    """One frame's pose against the frozen map (mipslam/tracking.py; the rest is ``TrackingOptions`` there)."""

    iterations: int = 40  # gradient steps on the render loss per frame (>= 1)
    # Gauss-Newton steps per pyramid level of the direct RGB-D alignment against the map's render, before the
    # gradient steps (0 = off)
    direct_iterations: int = 0
    resolution_scale: float = 1.0  # scale of the tracked image against the frame, in (0, 1] (never below 160 px wide)
    # The first this many gradient steps render in mip's cheaper footprint, the rest in render.mode (0 = none)
    coarse_mode_iterations: int = 0
    use_exposure: bool = False  # an affine exposure per frame (a real camera's auto-exposure)
    # Pixels the map renders below this opacity, in (0, 1], stay out of the tracking loss (the map's thin border
    # reads depth short); a map trained for a few steps only is less opaque and needs a lower one
    opacity_threshold: float = 0.95
    # A frame whose loss stays above this times the running level is aligned to the previous frame by RGB-D
    # odometry and tracked again from there (a jump, a bump, dropped frames); 0 = off, else > 1.
    relocalise_loss_ratio: float = 1.3

    def __post_init__(self):
        _check(self.iterations >= 1, "tracking.iterations", "must be >= 1")
        _check(self.direct_iterations >= 0, "tracking.direct_iterations", "must be >= 0 (0 = off)")
        _check(0 < self.resolution_scale <= 1, "tracking.resolution_scale", "must be in (0, 1]")
        _check(self.coarse_mode_iterations >= 0, "tracking.coarse_mode_iterations", "must be >= 0 (0 = none)")
        _check(0 < self.opacity_threshold <= 1, "tracking.opacity_threshold", "must be in (0, 1]")
        _check(self.relocalise_loss_ratio == 0 or self.relocalise_loss_ratio > 1, "tracking.relocalise_loss_ratio",
               "must be 0 (off) or > 1")


@dataclass(frozen=True)
class FrontendConfig:
    """Wide-basin start of tracking (mipslam/frontend.py): ORB features with depth, PnP RANSAC."""

    method: Literal["none", "orb_pnp"] = "orb_pnp"  # none: tracking starts from the motion model alone


@dataclass(frozen=True)
class KeyframeConfig:
    """Keyframe decision and window (mipslam/keyframes.py)."""

    covisibility_threshold: float = 0.9  # in (0, 1]: a new keyframe when the overlap with the last drops below
    window_size: int = 8  # keyframes mapping trains on together (>= 1)
    random_past: int = 2  # random older keyframes added to each mapping step (>= 0)
    # ... or when the map renders less than this fraction of the frame's valid depth, in [0, 1] (0 = off)
    min_map_coverage: float = 0.0

    def __post_init__(self):
        _check(0 < self.covisibility_threshold <= 1, "keyframes.covisibility_threshold", "must be in (0, 1]")
        _check(0 <= self.min_map_coverage <= 1, "keyframes.min_map_coverage", "must be in [0, 1] (0 = off)")
        _check(self.window_size >= 1, "keyframes.window_size", "must be >= 1")
        _check(self.random_past >= 0, "keyframes.random_past", "must be >= 0")


@dataclass(frozen=True)
class MappingConfig:
    """Densify, optimise, prune over the keyframe window (mipslam/mapping.py; the rest is ``MappingOptions``)."""

    iterations: int = 60  # optimisation steps per keyframe (>= 0)
    first_frame_iterations: int = 200  # ... for the first keyframe, the map every later frame tracks against
    densify_pixel_stride: int = 1  # one new Gaussian per stride x stride pixels (>= 1)
    max_gaussians: int = 200_000  # the map's size cap
    initial_scale_factor: float = 1.0  # a new Gaussian's std-dev in units of its cell (stride px at its depth), > 0
    initial_opacity: float = 0.5  # a new Gaussian's opacity, in (0, 1)
    # A new Gaussian is not added within this many of its std-devs of an existing centre (0 = off)
    add_min_distance_ratio: float = 1.0
    lr_poses: float = 1e-4  # Adam rate of the window's keyframe poses (m, rad per step; 0 = fixed)
    lambda_freq: float = 0.0  # weight of the frequency-domain loss (0 = off; the presets use 1000)
    # What the frequency loss may move while frames are tracked: "always" the geometry and poses too; "final"
    # the colours alone (a real camera's detail is not all geometry). The final refinement has no frequency term.
    freq_moves_geometry: Literal["final", "always"] = "always"

    def __post_init__(self):
        _check(self.iterations >= 0, "mapping.iterations", "must be >= 0")
        _check(self.first_frame_iterations >= 0, "mapping.first_frame_iterations", "must be >= 0")
        _check(self.max_gaussians >= 1, "mapping.max_gaussians", "must be >= 1")
        _check(self.lambda_freq >= 0, "mapping.lambda_freq", "must be >= 0")
        _check(self.densify_pixel_stride >= 1, "mapping.densify_pixel_stride", "must be >= 1")
        _check(0 < self.initial_opacity < 1, "mapping.initial_opacity", "must be in (0, 1)")
        _check(self.add_min_distance_ratio >= 0, "mapping.add_min_distance_ratio", "must be >= 0 (0 = off)")
        _check(self.initial_scale_factor > 0, "mapping.initial_scale_factor", "must be positive")
        _check(self.lr_poses >= 0, "mapping.lr_poses", "must be >= 0 (0 = poses fixed)")


@dataclass(frozen=True)
class LocalBAConfig:
    """Local bundle adjustment of the keyframe window by its features before mapping (mipslam/local_ba.py; the
    rest is ``LocalBAOptions``). Its features are ORB, as the front-end's."""

    # On in the tum config (a real camera's keyframes) and the fast preset (a coarse map); off by default and for
    # rendered data, whose exact depth the features cannot improve on (docs/mapping.md, "Local bundle adjustment")
    enabled: bool = False


@dataclass(frozen=True)
class RefineConfig:
    """The final refinement of the map over every keyframe after the last frame, and the keyframe poses that
    ``mipslam refine`` moves (mipslam/refinement.py; docs/mapping.md, "The final refinement")."""

    # passes over every keyframe after the last frame, in a random order (a pass at least 10 steps); 0 = none
    passes: int = 0
    # Adam rate of the keyframe poses in the refinement (m, rad); 0 keeps them fixed. It fits the poses to the
    # images as recorded, and a rolling shutter's image fits the pose of its middle row, not its time stamp's
    lr_poses: float = 0.0

    def __post_init__(self):
        _check(self.passes >= 0, "refine.passes", "must be >= 0 (0 = no final refinement)")
        _check(self.lr_poses >= 0, "refine.lr_poses", "must be >= 0 (0 = poses fixed)")


@dataclass(frozen=True)
class LoopConfig:
    """Loop closure and SA-PGO (docs/pgo.md; the rest is ``LoopOptions`` in mipslam/loop/closer.py)."""

    enabled: bool = True  # false: no loop stage at all (the run is exactly the one without it)
    # A loop edge is verified when at least this fraction, in [0, 1], of the candidate's points find a
    # correspondence after registration (their shared view)
    fitness_threshold: float = 0.3

    def __post_init__(self):
        _check(0 <= self.fitness_threshold <= 1, "loop.fitness_threshold", "must be in [0, 1]")


@dataclass(frozen=True)
class EvalConfig:
    """The run's own evaluation (``mipslam eval RUN_DIR`` and the end of ``mipslam run``; docs/evaluation.md)."""

    alignment: Literal["se3", "sim3", "none"] = "se3"  # of the estimated trajectory to the ground truth
    # split: two rows, novel views (MonoGS: frames.json positions 0, 5, 10, ... that are not keyframes) and
    # training views (the keyframes); all | keyframes | non_keyframes: one row of that set
    frames: Literal["split", "all", "keyframes", "non_keyframes"] = "split"
    # what scale 1 means: native = the camera's own images (the dataset read with downscale 1, original
    # intrinsics); mapping = the frames the run mapped (after dataset.downscale)
    resolution: Literal["native", "mapping"] = "native"
    scales: tuple[float, ...] = (1.0,)  # of the `resolution` reference, each > 0
    modes: tuple[str, ...] = ()  # footprint modes to render the metrics in; empty = the run's render mode

    def __post_init__(self):
        _check(all(s > 0 for s in self.scales), "eval.scales", "must all be positive")


@dataclass(frozen=True)
class Config:
    run: RunConfig = field(default_factory=RunConfig)
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    local_ba: LocalBAConfig = field(default_factory=LocalBAConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)


def section_options(options_type: type, section: Any, **extra: Any) -> Any:
    """A stage's options (``options_type``: a frozen dataclass beside the stage's code) built from its config
    section: each key of the section sets the option of the same name, ``extra`` sets options that another
    section holds (the sensor's depth noise), and every other option keeps the stage's constant. The one way a
    config becomes a stage's options (each stage's ``Options.from_config`` calls it)."""
    names = {f.name for f in dataclasses.fields(options_type)}
    values = {f.name: getattr(section, f.name) for f in dataclasses.fields(section)}
    unknown = sorted((set(values) | set(extra)) - names)
    if unknown:  # a programming error: every key must reach its stage
        raise TypeError(f"{options_type.__name__} has no option(s) {unknown}")
    return options_type(**values, **extra)


# ----------------------------------------------------------------------------- dict <-> dataclass

def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Check ``value`` against the annotation ``tp`` and convert where lossless (int -> float, list -> tuple)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"config key '{key}': expected {_type_name(tp)}, got {value!r}")
    if origin is Literal:
        if value not in args:
            near = difflib.get_close_matches(str(value), [str(a) for a in args], n=1)
            hint = f" (did you mean '{near[0]}'?)" if near else ""
            raise ConfigError(f"config key '{key}': {value!r} is not one of {', '.join(map(str, args))}{hint}")
        return value
    if origin is tuple:
        if isinstance(value, (int, float, str)) and not isinstance(value, bool):
            value = [value]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"config key '{key}': expected a list, got {value!r}")
        item_tp = args[0] if args else Any
        return tuple(_coerce(v, item_tp, f"{key}[{i}]") for i, v in enumerate(value))
    if tp is Any:
        return value
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"config key '{key}': expected true or false, got {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ConfigError(f"config key '{key}': expected an integer, got {value!r}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            try:
                number = float(value)
            except OverflowError:  # an integer beyond float range
                number = math.inf
            if math.isfinite(number):
                return number
            raise ConfigError(f"config key '{key}': expected a finite number, got {value!r}")
        if isinstance(value, str):
            # YAML 1.1 reads "5e-4" (no dot in the mantissa) as a string; users mean the number.
            try:
                number = float(value)
            except ValueError:
                number = None
            if number is not None and math.isfinite(number):
                return number
        raise ConfigError(f"config key '{key}': expected a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return str(value)
        raise ConfigError(f"config key '{key}': expected a string, got {value!r}")
    raise ConfigError(f"config key '{key}': unsupported type {_type_name(tp)}")


# Keys that existed once, with what replaced them (a clearer error than a near-miss suggestion).
RETIRED_KEYS = {
    "render.eaa_point_area": "retired: EAA's 1-node threshold is now an internal constant of the renderer "
                             "(mipslam/render/__init__.py, RenderOptions.eaa_single_node_sigma); delete the line",
    "mapping.final_iterations": "retired: the final refinement is now 'refine.passes' (passes over every keyframe, "
                                "a pass at least 10 steps; docs/mapping.md); delete the line or set the new key",
    "loop.icp_fitness_threshold": "renamed 'loop.fitness_threshold' (the default registration is direct, not ICP); "
                                  "set the new key",
    "tracking.direct_depth_noise_power": "merged into 'dataset.depth_noise_power' (a property of the sensor, used by "
                                         "tracking and loop verification alike); set the new key",
    "loop.registration_depth_noise_power": "merged into 'dataset.depth_noise_power' (a property of the sensor, used "
                                           "by tracking and loop verification alike); set the new key",
    "run.mmap_threshold_kib": "removed: it was off in every shipped config (docs/robustness.md, \"Long runs\"); "
                              "delete the line",
    "tracking.gradient_mask_percentile": "removed: it was off (0) in every shipped config; delete the line",
    "tracking.lr_final_ratio": "removed: it was off (1, a constant rate) in every shipped config; delete the line",
}

# Keys that became a stage's internal constants: section -> (the module that defines them, the option object),
# and the keys. Setting one is an error that says where the constant lives, never silently ignored.
INTERNAL_KEYS = {
    "run": ("mipslam/run_control.py and mipslam/pipeline.py", "KEEP_CHECKPOINTS, RELEASE_MEMORY_EVERY, KEYFRAME_CACHE_MIB", (
        "keep_checkpoints", "keyframe_cache_mib", "release_memory_every")),
    "render": ("mipslam/render/__init__.py and mipslam/rendering.py", "RenderOptions, FILTER_3D_SCALE, FRUSTUM_MARGIN", (
        "eaa_eta", "eaa_gamma", "eaa_k_sigma", "eaa_single_node_sigma", "eaa_tau", "filter_3d_scale", "frustum_margin",
        "near_plane")),
    "tracking": ("mipslam/tracking.py", "TrackingOptions", (
        "align_depth_time", "alpha_color", "coarse_render_mode", "coarse_share", "coarse_to_fine",
        "convergence_threshold", "coverage_opacity", "dense_start", "depth_alpha_floor", "depth_normalise",
        "depth_outlier_ratio", "direct_alpha_color", "direct_convergence", "direct_levels", "direct_renders",
        "failure_loss_ratio", "lr_rotation", "lr_translation",
        "max_depth", "min_valid_fraction", "min_width", "optimizer", "relocalise_max_deg",
        "relocalise_max_m", "render_mode", "rprop_max_step_ratio", "running_loss_momentum", "start_margin")),
    "frontend": ("mipslam/frontend.py", "FeatureOptions", (
        "fast_threshold", "guided_radius", "max_hamming", "min_inlier_ratio", "min_inliers", "num_features",
        "pyramid_levels", "ransac_iterations", "ransac_reprojection_px", "ratio_test", "relocalise_keyframes")),
    "keyframes": ("mipslam/keyframes.py", "KeyframeOptions", (
        "covisibility_depth_tolerance", "covisibility_pixel_stride", "rotation_deg", "translation_ratio",
        "window_min_overlap")),
    "mapping": ("mipslam/mapping.py", "MappingOptions", (
        "add_depth_error_ratio", "add_opacity_threshold", "alpha_color", "depth_alpha_floor", "depth_normalise",
        "freq_alpha", "freq_patch", "isotropy_weight", "keyframe_cache", "lr_colors", "lr_means", "lr_opacities",
        "lr_quats", "lr_scales", "max_depth", "opacity_weight", "prune_max_sigma_px", "prune_opacity")),
    "loop": ("mipslam/loop/closer.py", "LoopOptions", (
        "confirm_keyframes", "confirm_relative", "confirm_tolerance_deg", "confirm_tolerance_m", "consistent_chi2",
        "full_iterations", "icp_pixel_stride", "icp_rmse_threshold", "icp_voxel_m", "loop_sigma_deg", "loop_sigma_m",
        "low_frequency_correction", "max_correction_psnr_drop_db", "max_drift_sigmas", "min_correction_deg",
        "min_correction_m", "min_keyframe_gap", "num_eigenvectors", "odometry_drift_ratio", "odometry_sigma_deg",
        "odometry_sigma_m", "pgo_window_keyframes", "refine_iterations", "registration", "spectral_edge_weighting")),
    "eval": ("mipslam/evaluation/run_eval.py", "TRAJECTORY_ASSOCIATION_S", ("association_tolerance_s",)),
}


def retired_key_message(key: str) -> str | None:
    """Why ``key`` (``section.name``) is no longer a config key and what to do instead; None when it never was."""
    if key in RETIRED_KEYS:
        return RETIRED_KEYS[key]
    section, _, name = key.partition(".")
    module, where, names = INTERNAL_KEYS.get(section, ("", "", ()))
    if name in names:
        return (f"no longer a config key: it is an internal constant of {module} ({where}); delete the line "
                "(mipslam config NAME prints the config keys)")
    return None


def _build(cls: type, data: Mapping[str, Any], prefix: str) -> Any:
    if not isinstance(data, Mapping):
        raise ConfigError(f"config key '{prefix.rstrip('.') or '<root>'}': expected a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    for key in data:
        if key not in names:
            retired = retired_key_message(f"{prefix}{key}")
            if retired is not None:
                raise ConfigError(f"config key '{prefix}{key}': {retired}")
            near = difflib.get_close_matches(str(key), names, n=1, cutoff=0.5)
            hint = f"; did you mean '{prefix}{near[0]}'?" if near else f"; valid keys: {', '.join(names)}"
            raise ConfigError(f"unknown config key {_quoted(f'{prefix}{key}')}{hint}")
    kwargs = {}
    for name in names:
        if name not in data:
            continue
        tp = hints[name]
        if dataclasses.is_dataclass(tp):
            kwargs[name] = _build(tp, data[name] or {}, f"{prefix}{name}.")
        else:
            kwargs[name] = _coerce(data[name], tp, f"{prefix}{name}")
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"config section '{prefix.rstrip('.')}': {exc}") from exc


def config_from_dict(data: Mapping[str, Any]) -> Config:
    """Validate a nested mapping and build the frozen :class:`Config` (defaults for missing keys)."""
    return _build(Config, data, "")


def config_to_dict(config: Any) -> dict[str, Any]:
    """Plain nested dict (tuples as lists) suitable for YAML/JSON."""

    def plain(value: Any) -> Any:
        if dataclasses.is_dataclass(value):
            return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
        if isinstance(value, tuple):
            return [plain(v) for v in value]
        return value

    return plain(config)


# ----------------------------------------------------------------------------- YAML, inheritance, overrides

def _deep_merge(base: dict[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = _deep_merge(dict(out[key]), value)
        else:
            out[key] = value
    return out


def _shown(path: Path) -> str:
    """A path for a one-line message (escaped when its name holds a line break or another unprintable character)."""
    text = str(path)
    return text if text.isprintable() else repr(text)


def _missing_file_message(path: Path) -> str:
    """'config file not found', with the nearest YAML file of that folder when there is a likely one."""
    folder = path.parent
    builtin = path.stem if path.suffix.lower() in (".yaml", ".yml") and path.stem in builtin_config_names() else None
    hint = f"; for the built-in config give its name: {builtin}" if builtin else ""
    if not folder.is_dir():
        return f"{_shown(path)}: config file not found (folder {_shown(folder)} does not exist){hint}"
    if builtin:  # configs/tum.yaml of an older checkout, tum.yaml: the built-in is the likely meaning
        return f"{_shown(path)}: config file not found{hint}"
    try:
        names = sorted(p.name for p in folder.iterdir() if p.suffix.lower() in (".yaml", ".yml") and p.is_file())
    except OSError:
        names = []
    near = difflib.get_close_matches(path.name, names, n=1, cutoff=0.6)
    if near:
        return f"{_shown(path)}: config file not found; did you mean {_shown(folder / near[0])}?"
    listing = f" (YAML files there: {', '.join(map(_shown, names[:6]))})" if names else ""
    return f"{_shown(path)}: config file not found{listing}"


def _yaml_error_message(path: Path, exc: Exception) -> str:
    """One line naming the file, the line and column (1-based) where PyYAML gives them, and the problem."""
    if isinstance(exc, RecursionError):
        return f"{_shown(path)}: invalid YAML (nested too deeply)"
    if isinstance(exc, yaml.MarkedYAMLError):
        mark = exc.problem_mark or exc.context_mark
        where = f":{mark.line + 1}:{mark.column + 1}" if mark is not None else ""
        problem = " ".join("; ".join(str(part) for part in (exc.context, exc.problem) if part).split())
        return f"{_shown(path)}{where}: invalid YAML ({problem or type(exc).__name__})"
    # a value PyYAML recognised but could not build (e.g. the date 2001-13-45), or another YAMLError
    detail = " ".join(str(exc).split()) or type(exc).__name__
    return f"{_shown(path)}: invalid YAML ({detail})"


def _read_yaml(path: Path) -> dict[str, Any]:
    if path.is_dir():
        hint = f"; the run's config is {_shown(path / 'config.yaml')}" if (path / "config.yaml").is_file() else ""
        raise ConfigError(f"{_shown(path)}: is a folder, not a YAML config file{hint}")
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(_missing_file_message(path)) from None
    except OSError as exc:
        raise ConfigError(f"{_shown(path)}: cannot read config file ({exc.strerror or exc})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{_shown(path)}: not a YAML text file (byte 0x{raw[exc.start]:02x} at offset {exc.start} "
                          "is not UTF-8); give a YAML config file or a built-in config's name, e.g. replica") from None
    if "\x00" in text:
        raise ConfigError(f"{_shown(path)}: not a YAML text file (it contains NUL bytes); give a YAML config file or a "
                          "built-in config's name, e.g. replica")
    try:
        data = yaml.safe_load(text)
    except (yaml.YAMLError, ValueError, TypeError, OverflowError, RecursionError) as exc:
        raise ConfigError(_yaml_error_message(path, exc)) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{_shown(path)}: the top level must be a mapping of sections, got {type(data).__name__}")
    return data


# Keys holding file-system paths: a relative path in a YAML file is relative to that file, so a
# config works from any working directory; one given with --set is relative to the working directory.
# After loading, every such path is absolute (and normalised), so a resolved config written out
# (a run's config.yaml) means the same wherever it is read, and one folder is one value.
_PATH_KEYS = (("dataset", "path"),)


def _absolute_path(value: str, base: Path) -> str:
    """``value`` (``~`` expanded) made absolute against ``base`` and normalised (``.``, ``..``, links)."""
    path = Path(value).expanduser()
    try:
        return str((path if path.is_absolute() else base / path).resolve())
    except (OSError, RuntimeError, ValueError) as exc:  # a NUL byte, a symlink loop
        raise ConfigError(f"config path {value!r}: not a usable path ({exc})") from None


def _resolve_paths(data: Mapping[str, Any], base: Path) -> None:
    """Make the path keys of ``data`` (nested dict, changed in place) absolute against ``base``."""
    for section, key in _PATH_KEYS:
        block = data.get(section)
        if isinstance(block, dict) and isinstance(block.get(key), str) and block[key]:
            block[key] = _absolute_path(block[key], base)


def with_absolute_paths(data: Mapping[str, Any], base: str | Path | None = None) -> dict[str, Any]:
    """A copy of a plain config dict whose path keys are absolute (relative ones against ``base``,
    default the working directory). Used to write and to compare resolved configs."""
    out = {key: dict(value) if isinstance(value, Mapping) else value for key, value in data.items()}
    _resolve_paths(out, Path.cwd() if base is None else Path(base))
    return out


def load_yaml_tree(path: str | Path, _stack: tuple[Path, ...] = ()) -> dict[str, Any]:
    """Read a YAML config and everything it inherits from, merged (parents first).

    Relative paths under ``dataset.path`` are resolved against the directory of the file that names them.
    An ``inherit_from`` entry is a file relative to this one or, where no such file exists, a built-in config's name.
    """
    try:
        path = Path(path).resolve()
    except (OSError, RuntimeError, ValueError) as exc:  # a NUL byte in the name, a symlink loop
        raise ConfigError(f"config file {str(path)!r}: not a usable path ({exc})") from None
    if path in _stack:
        cycle = " -> ".join(_shown(p) for p in (*_stack, path))
        raise ConfigError(f"{_shown(path)}: cyclic inherit_from ({cycle}); remove one of the links")
    data = _read_yaml(path)
    _resolve_paths(data, path.parent)
    parents = data.pop("inherit_from", None)
    if parents is None:
        return data
    if isinstance(parents, str):
        parents = [parents]
    if not isinstance(parents, list) or not all(isinstance(p, str) for p in parents):
        raise ConfigError(f"{_shown(path)}: inherit_from must be a file name, a built-in config's name or a list of "
                          "them")
    merged: dict[str, Any] = {}
    for parent in parents:
        try:
            source = resolve_config_source(parent, base=path.parent)
        except ConfigError as exc:
            raise ConfigError(f"{_shown(path)}: inherit_from: {exc}") from None
        merged = _deep_merge(merged, load_yaml_tree(source, (*_stack, path)))
    return _deep_merge(merged, data)


def parse_override(text: str) -> tuple[list[str], Any]:
    """``'tracking.iterations=30'`` -> (['tracking', 'iterations'], 30); the value is read as YAML."""
    if "=" not in text:
        raise ConfigError(f"override {_quoted(text)} must look like section.key=value")
    key, raw = text.split("=", 1)
    parts = [p for p in key.strip().split(".")]
    if len(parts) < 2 or not all(parts):
        raise ConfigError(f"override {_quoted(text)}: the key must name a section and a key, e.g. "
                          "tracking.iterations=30")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except (yaml.YAMLError, ValueError, TypeError, OverflowError, RecursionError):
        value = raw  # not a YAML value: the text itself (the type check then names the key)
    return parts, value


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    for text in overrides:
        parts, value = parse_override(text)
        nested: Any = value
        for part in reversed(parts):
            nested = {part: nested}
        data = _deep_merge(data, nested)
    return data


@dataclass(frozen=True)
class BuiltinConfig:
    """A config shipped in the package (``mipslam/configs/NAME.yaml``)."""

    name: str
    path: Path
    description: str  # the file's first comment line
    preset: bool  # an overlay for --preset NAME (else a config to run or inherit from)


def builtin_config_names() -> tuple[str, ...]:
    """The built-in configs' names: the dataset configs (sorted), then the presets in :data:`PRESETS` order."""
    try:
        names = {p.stem for p in CONFIG_DIR.glob("*.yaml") if p.is_file()}
    except OSError:
        names = set()
    return (*sorted(names - set(PRESETS)), *(name for name in PRESETS if name in names))


def _first_comment_line(path: Path) -> str:
    """The file's first comment line, up to the end of its first sentence."""
    try:
        with path.open(encoding="utf-8") as f:
            for line in f:
                if line.lstrip().startswith("#"):
                    text = line.strip().lstrip("#").strip()
                    return text.split(". ", 1)[0] + "." if ". " in text else text
                if line.strip():
                    break  # the comment must come before the first key
    except (OSError, UnicodeDecodeError):
        pass
    return ""


def builtin_configs() -> tuple[BuiltinConfig, ...]:
    """Every built-in config with its description (``mipslam config --list``), in :func:`builtin_config_names` order."""
    return tuple(BuiltinConfig(name, CONFIG_DIR / f"{name}.yaml", _first_comment_line(CONFIG_DIR / f"{name}.yaml"),
                               name in PRESETS) for name in builtin_config_names())


def _available_configs() -> str:
    names = builtin_config_names()
    configs = [n for n in names if n not in PRESETS]
    presets = [n for n in names if n in PRESETS]
    text = f"built-in configs: {', '.join(configs) or 'none (the package is incomplete; reinstall mipslam)'}"
    return f"{text} (presets: {', '.join(presets)})" if presets else text


def builtin_config_path(name: str) -> Path:
    """The file of the built-in config ``name`` (``tum`` -> ``mipslam/configs/tum.yaml``); a ConfigError that
    names the nearest built-in and lists them all otherwise."""
    names = builtin_config_names()
    if name in names:
        return CONFIG_DIR / f"{name}.yaml"
    near = difflib.get_close_matches(name, names, n=1)
    hint = f" (did you mean '{near[0]}'?)" if near else ""
    raise ConfigError(f"unknown config {_quoted(name)}{hint}; {_available_configs()}; or give a YAML file")


def _looks_like_a_name(text: str) -> bool:
    """``tum`` (a built-in's name, perhaps misspelt), not ``my.yaml`` or ``dir/file`` (a file path)."""
    return bool(text) and "/" not in text and "\\" not in text and not Path(text).suffix and text not in (".", "..")


def resolve_config_source(source: str | Path, base: str | Path | None = None) -> Path:
    """The file a config argument names: ``source`` (relative to ``base``, default the working directory) when it
    is an existing file, else the built-in config of that name (``tum``), else ``source`` as a path (reading it
    then reports the missing file). A bare name that is neither (``tmu``) is a ConfigError that lists the
    built-ins."""
    text = str(source)
    path = Path(source) if base is None else Path(base) / source
    try:
        is_file = path.is_file()
    except (OSError, ValueError):  # a NUL byte, a name too long: reading it reports the problem
        return path
    if is_file:
        return path
    if text in builtin_config_names():
        return CONFIG_DIR / f"{text}.yaml"
    if _looks_like_a_name(text) and not path.exists():
        files = [path.with_name(path.name + suffix) for suffix in (".yaml", ".yml")]
        sibling = next((file for file in files if file.is_file()), None)
        if sibling is not None:  # `inherit_from: parent` beside parent.yaml
            raise ConfigError(f"unknown config {_quoted(text)} (did you mean {_shown(sibling)}?); "
                              f"{_available_configs()}; or give a YAML file")
        builtin_config_path(text)  # raises: unknown config, with the nearest built-in
    return path


def preset_path(name: str) -> Path:
    if name not in PRESETS:
        near = difflib.get_close_matches(name, PRESETS, n=1)
        hint = f" (did you mean '{near[0]}'?)" if near else ""
        raise ConfigError(f"unknown preset '{name}'{hint}; choose one of {', '.join(PRESETS)}")
    path = CONFIG_DIR / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"{path}: preset file missing; the installed package is incomplete, reinstall mipslam")
    return path


def load_config(path: str | Path | None = None, *, preset: str | None = None, overrides: list[str] | None = None) -> Config:
    """Resolve a config: file (with inherit_from) -> preset overlay -> ``--set`` overrides.

    ``path`` is a YAML file or a built-in config's name (``"tum"``: :func:`resolve_config_source`); None starts
    from the defaults. Path keys come out absolute: relative to the YAML file that names them, or to the working
    directory for ``--set``. Every problem is a ConfigError naming the file (line and column for YAML syntax).
    """
    data: dict[str, Any] = load_yaml_tree(resolve_config_source(path)) if path is not None else {}
    if preset:
        data = _deep_merge(data, load_yaml_tree(preset_path(preset)))
    data = apply_overrides(data, list(overrides or []))
    _resolve_paths(data, Path.cwd())
    return config_from_dict(data)


def config_to_yaml(config: Config) -> str:
    """The resolved config as YAML, path keys absolute (so the text means the same wherever it is read)."""
    return yaml.safe_dump(with_absolute_paths(config_to_dict(config)), sort_keys=False)


def save_config(config: Config, path: str | Path) -> None:
    Path(path).write_text(config_to_yaml(config), encoding="utf-8")
