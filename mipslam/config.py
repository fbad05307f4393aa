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

Each stage's factory receives only its own section (kiss-icp style), never the whole config.
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
from mipslam.loop.descriptors import CandidateOptions
from mipslam.loop.registration import RegistrationOptions
from mipslam.loop.solver import PGOOptions
from mipslam.render import RenderOptions, render_option_problems

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

    seed: int = 0
    device: Literal["auto", "cpu", "cuda"] = "auto"
    threads: int = 0  # torch intra-op threads; 0 keeps torch's default
    checkpoint_every: int = 50  # frames between checkpoints; 0 = only at the end
    keep_checkpoints: int = 2  # how many complete checkpoints stay on disk
    evaluate_at_end: bool = True
    # frames between returns of freed heap memory to the OS (glibc malloc_trim; 0 = never). Without it
    # fragmentation grows RSS by about 3 MiB per 100 frames on long runs (docs/robustness.md).
    release_memory_every: int = 50
    # allocations of at least this many KiB come from mmap and go back to the OS when freed (glibc
    # mallopt M_MMAP_THRESHOLD, fixed); 0 keeps glibc's dynamic threshold. 64 halves the RSS creep of
    # a 2000-frame run (+31 -> +17 MiB) but costs 11 % frames/s (docs/robustness.md, "Long runs").
    mmap_threshold_kib: int = 0
    # Measurements that cost time and change no result (the map's PSNR at the loop's keyframes around each loop
    # correction, in loops.json); off, a run renders nothing it does not need.
    diagnostics: bool = False
    # keyframes' images kept in memory for mapping and loop verification (MiB; 0 = read them again from the
    # sequence each time): a 320x240 keyframe takes 1.2 MiB
    keyframe_cache_mib: int = 256

    def __post_init__(self):
        _check(self.threads >= 0, "run.threads", "must be >= 0 (0 = torch default)")
        _check(self.checkpoint_every >= 0, "run.checkpoint_every", "must be >= 0")
        _check(self.keep_checkpoints >= 1, "run.keep_checkpoints", "must be >= 1")
        _check(self.release_memory_every >= 0, "run.release_memory_every", "must be >= 0 (0 = never)")
        _check(self.keyframe_cache_mib >= 0, "run.keyframe_cache_mib", "must be >= 0 (0 = no keyframe cache)")
        _check(0 <= self.mmap_threshold_kib <= 32768, "run.mmap_threshold_kib",
               "must be in [0, 32768] KiB (0 = the C library's default)")


@dataclass(frozen=True)
class DatasetConfig:
    """Which sequence to read and how (intrinsics default to the dataset's own files/presets)."""

    kind: Literal["replica", "tum", "synthetic", "realsense", "realsense_bag"] = "synthetic"
    path: str = ""
    stride: int = 1
    first_frame: int = 0
    max_frames: int = 0  # 0 = all frames
    downscale: int = 1  # integer factor: colour area-averaged, depth without mixing surfaces
    camera: str = ""  # TUM preset: freiburg1 | freiburg2 | freiburg3 (empty = from fx..cy or the folder)
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    width: int | None = None
    height: int | None = None
    depth_scale: float | None = None  # stored value / depth_scale = metres (Replica 6553.5, TUM 5000)
    # Lens distortion of the images on disk, OpenCV order (k1, k2, p1, p2[, k3]); frames (colour bilinear,
    # depth nearest) are undistorted at the dataset boundary with the same fx..cy. Unset or [] = none.
    distortion: tuple[float, ...] | None = None
    association_tolerance_s: float = 0.02  # TUM rgb-depth-groundtruth association
    # Seconds a rolling-shutter colour camera takes to read its rows, top to bottom (0 = a global shutter); each
    # row is moved to the frame's instant with the tracked motion (mipslam.sensor_sync; docs/tracking.md,
    # "A rolling shutter"). The frame's timestamp is taken as its middle row's instant.
    rolling_shutter_readout_s: float = 0.0
    realtime: bool = False  # realsense_bag: play at the recorded rate, dropping frames (false: every frame)

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


# Render config key -> renderer option (mipslam.render.RenderOptions): the options' defaults and range checks
# are the config's, defined once in the renderer (which imports no config).
RENDER_OPTION_KEYS = {
    "near_plane": "near_plane",
    "eaa_k_sigma": "k_sigma",
    "eaa_max_nodes": "eaa_max_nodes",
    "eaa_gamma": "eaa_gamma",
    "eaa_eta": "eaa_eta",
    "eaa_tau": "eaa_tau",
    "eaa_single_node_sigma": "eaa_single_node_sigma",
}


@dataclass(frozen=True)
class RenderConfig:
    """Renderer settings (docs/design.md, renderer contract and EAA). The EAA constants and the near plane default
    to :class:`~mipslam.render.RenderOptions`' values (measured against `exact`: docs/renderer.md,
    `mipslam bench --scenario aliasing`), and are checked by its rules."""

    mode: Literal["point", "mip", "ewa", "eaa", "exact"] = "eaa"
    backend: Literal["auto", "torch", "cpu"] = "auto"
    filter_3d: bool = False  # Mip-Splatting 3D smoothing filter
    filter_3d_scale: float = 0.2  # its strength s (the paper's 0.2)
    eaa_max_nodes: int = RenderOptions.eaa_max_nodes  # node cap n_max: the speed/accuracy knob (1 = point value)
    eaa_gamma: float = RenderOptions.eaa_gamma  # row growth of a sub-pixel splat with anisotropy
    eaa_eta: float = RenderOptions.eaa_eta  # boundary emphasis b(d) = 1 + eta exp(-d / tau)
    eaa_tau: float = RenderOptions.eaa_tau  # pixels
    eaa_single_node_sigma: float = RenderOptions.eaa_single_node_sigma  # minor-axis std-dev (px) of 1 node
    eaa_k_sigma: float = RenderOptions.k_sigma
    near_plane: float = RenderOptions.near_plane  # metres
    # Tracking and mapping render a view from the Gaussians that reach its image enlarged by this fraction of
    # the larger side, at the pose the view starts from (0.25: about 16 degrees of a 70-degree view, far
    # beyond what one optimisation moves a pose); the rest of the map cannot be drawn and is left out.
    frustum_margin: float = 0.25

    def __post_init__(self):
        keys = {option: key for key, option in RENDER_OPTION_KEYS.items()}
        for option, message in render_option_problems(**self.renderer_options()):
            _check(False, f"render.{keys[option]}", message)
        _check(self.filter_3d_scale > 0, "render.filter_3d_scale", "must be positive")
        _check(self.frustum_margin >= 0, "render.frustum_margin", "must be >= 0 (a fraction of the image size)")

    def renderer_options(self) -> dict[str, Any]:
        """The renderer options this section sets (keyword arguments of :func:`mipslam.render.rasterize`)."""
        return {option: getattr(self, key) for key, option in RENDER_OPTION_KEYS.items()}


@dataclass(frozen=True)
class TrackingConfig:
    iterations: int = 40
    # adam: every step moves each pose coordinate by about lr_* (m, rad) until the end. rprop: lr_* is
    # each coordinate's first step; it grows 1.2x while the coordinate's gradient keeps its sign and
    # halves when it flips, so a good motion-model pose is refined in small steps and a level stops once
    # the steps fall below convergence_threshold. The fast and balanced presets use rprop (lr 5e-4 / 1e-3,
    # threshold 1e-4: half of adam's tracking time at 320x240, docs/bench.md). adam stays the
    # default: at 40x30 with 15 iterations rprop's growing steps lag a 2 cm/frame motion.
    optimizer: Literal["adam", "rprop"] = "adam"
    lr_translation: float = 2e-3
    lr_rotation: float = 4e-3
    rprop_max_step_ratio: float = 50.0  # rprop: a coordinate's step never exceeds lr * this
    # Adam's steps stay near lr until it stops, which leaves the pose jittering by about lr; decaying the
    # rate geometrically to lr * lr_final_ratio over each level's iterations lets it settle (adam only).
    lr_final_ratio: float = 1.0
    # Stop a level when the pose update (se3 norm; rprop: the norm of its next steps) is below this.
    convergence_threshold: float = 1e-5
    alpha_color: float = 0.5  # weight of the photometric term against depth
    coarse_to_fine: tuple[float, ...] = ()  # e.g. (0.5,) tracks at half resolution first
    coarse_share: float = 0.5  # fraction of the iterations given to the coarse levels (split evenly between them)
    # Scale of tracking's finest level against the frame (coarse_to_fine scales multiply it): with a
    # feature front-end's start a few steps at low resolution refine the pose (docs/tracking.md).
    resolution_scale: float = 1.0
    # ... but never below this width (pixels): a small frame keeps enough pixels to pin the pose. 0 = no floor.
    min_width: int = 0
    use_exposure: bool = False
    opacity_threshold: float = 0.95  # pixels whose rendered opacity is below are ignored
    # a pixel the map renders at this opacity or more counts as mapped (keyframes.min_map_coverage)
    coverage_opacity: float = 0.5
    # The feature front-end's start replaces the motion model's only when the map renders it with a loss lower
    # by this fraction (Tracker.best_start).
    start_margin: float = 0.1
    gradient_mask_percentile: float = 0.0  # keep colour pixels above this image-gradient percentile (0-100)
    min_valid_fraction: float = 0.05
    failure_loss_ratio: float = 5.0  # loss above ratio * running level = failure
    # A frame whose loss stays above ratio * running level is aligned to the previous frame by RGB-D
    # odometry and tracked again from there (a jump, a bump, dropped frames); 0 turns it off.
    relocalise_loss_ratio: float = 1.3
    # Largest jump relocalisation accepts from the RGB-D alignment to the previous frame (a bump, dropped frames).
    relocalise_max_m: float = 1.0
    relocalise_max_deg: float = 45.0
    # Where the feature front-end gives no start (texture-poor or repeated texture, a large motion), align the
    # newest tracked frame to this one by dense RGB-D odometry (Open3D) from the motion model's pose; the render
    # loss then judges that pose against the motion model's (Tracker.best_start). Bounded by relocalise_max_*.
    dense_start: bool = False
    # Move each depth image to its colour image's instant with the motion model, where the dataset gives the two
    # their own timestamps (TUM's rgb.txt and depth.txt; mipslam.sensor_sync). It needs timestamps of the capture:
    # data_synth on fr1_rpy's motion with depth 8 ms late 1.92 / 1.99 -> 0.98 / 1.25 cm (seeds 0 / 1), but on
    # fr1_rpy itself, whose timestamps are the driver's, moving the depth by them is worse, even with the
    # ground-truth motion (docs/tracking.md, "Colour and depth at different instants"), so it is off.
    align_depth_time: bool = False
    # Momentum of the running level of good tracking losses (exponential moving average) that the failure and
    # relocalisation ratios compare a frame's loss with.
    running_loss_momentum: float = 0.9
    # Footprint mode of tracking's renders (null: render.mode); mapping always renders in render.mode. On a
    # 320x240 map EAA's row rule for sub-pixel splats made a pose-only render 3x as expensive as mip's, and
    # mip tracking kept the ATE within the seed spread; at 160x120 it costs the lap 0.05-0.23 cm (docs/bench.md).
    render_mode: Literal["point", "mip", "ewa", "eaa", "exact"] | None = None
    # Footprint mode of the coarse levels (coarse_to_fine; null: render_mode). They only bring the pose into the
    # finest level's basin, and below ~1 px per splat EAA's renders cost as much as at twice the resolution.
    coarse_render_mode: Literal["point", "mip", "ewa", "eaa", "exact"] | None = None
    # The first this many of the finest level's gradient steps render in coarse_render_mode when it differs
    # from render_mode (0: none): the cheaper footprint brings the pose near, render_mode's steps finish and
    # alone judge the best pose (docs/tracking.md, "Results").
    coarse_mode_iterations: int = 0
    # Depth term on the alpha-normalised rendered depth D / max(A, depth_alpha_floor) instead of the raw
    # D = sum T a z, which reads short wherever the map's opacity A < 1 and so pulls the camera towards
    # the surface (mipslam/losses/photometric.py; docs/mapping.md).
    depth_normalise: bool = False
    depth_alpha_floor: float = 0.5
    max_depth: float = 0.0  # metres; observed depth beyond it stays out of the depth term (0 = no limit)
    # Depth pixels whose residual exceeds this many times the median residual leave the depth term (0 = off):
    # disocclusions the map does not hold pull the pose back towards the keyframes that built it (docs/mapping.md).
    depth_outlier_ratio: float = 0.0
    # Direct RGB-D alignment (mipslam/geometry/direct.py) of the map's render onto the frame before the gradient
    # steps: Gauss-Newton on intensity and depth residuals, coarse to fine, converging in a few steps where the
    # gradient steps creep. direct_iterations: steps per pyramid level at most (0 = off); direct_levels: pyramid
    # levels, each half the next, the finest at tracking's finest resolution; direct_renders: renders of the map
    # it aligns to (each after the first at the pose the previous alignment reached; the loss of every render
    # is checked and a render that explains the frame worse ends the alignment at the pose before it).
    direct_iterations: int = 0
    direct_levels: int = 2
    direct_renders: int = 1
    direct_convergence: float = 1e-4  # a level stops once a step's se(3) norm falls below this
    # Weight of the intensity term against depth in the alignment, each term in units of its robust scale (so
    # not tracking.alpha_color's L1 weights). A hand-held camera's colour and depth are not taken at one
    # instant, and under fast turns the depth lags: 0.7-0.9 tracked fr1_rpy 2.36-2.67 cm, 0.5 2.87, 0.2 3.60,
    # while Replica, fr1_xyz and the data_synth lap moved by at most 0.03, 0.06, 0.24 cm over 0.5-0.9 (docs/tracking.md).
    direct_alpha_color: float = 0.8
    # The alignment's depth residuals in units of z^p (0: metres), z the point's depth: an active sensor's depth
    # noise grows as z^2 (Kinect, RealSense; the built-in tum config sets 2), so far pixels count less; its robust
    # scale stays per frame. Noise-free renders (Replica, data_synth) keep metres (docs/tracking.md, "Depth noise").
    direct_depth_noise_power: float = 0.0

    def __post_init__(self):
        _check(self.iterations >= 1, "tracking.iterations", "must be >= 1")
        _check(self.direct_iterations >= 0, "tracking.direct_iterations", "must be >= 0 (0 = off)")
        _check(self.direct_levels >= 1, "tracking.direct_levels", "must be >= 1")
        _check(self.direct_renders >= 1, "tracking.direct_renders", "must be >= 1")
        _check(self.direct_convergence > 0, "tracking.direct_convergence", "must be > 0")
        _check(0 <= self.direct_alpha_color <= 1, "tracking.direct_alpha_color", "must be in [0, 1]")
        _check(self.direct_depth_noise_power >= 0, "tracking.direct_depth_noise_power", "must be >= 0 (0 = metres)")
        _check(self.depth_outlier_ratio >= 0, "tracking.depth_outlier_ratio", "must be >= 0 (0 = off)")
        _check(0 < self.depth_alpha_floor <= 1, "tracking.depth_alpha_floor", "must be in (0, 1]")
        _check(self.max_depth >= 0, "tracking.max_depth", "must be >= 0 metres (0 = no limit)")
        _check(0 <= self.alpha_color <= 1, "tracking.alpha_color", "must be in [0, 1]")
        _check(0 < self.coverage_opacity <= 1, "tracking.coverage_opacity", "must be in (0, 1]")
        _check(self.lr_translation > 0 and self.lr_rotation > 0, "tracking.lr_*", "learning rates must be positive")
        _check(0 < self.lr_final_ratio <= 1, "tracking.lr_final_ratio", "must be in (0, 1] (1 = constant rate)")
        _check(self.rprop_max_step_ratio >= 1, "tracking.rprop_max_step_ratio", "must be >= 1")
        _check(all(0 < s <= 1 for s in self.coarse_to_fine), "tracking.coarse_to_fine", "scales must be in (0, 1]")
        _check(0 < self.resolution_scale <= 1, "tracking.resolution_scale", "must be in (0, 1]")
        _check(0 <= self.start_margin < 1, "tracking.start_margin", "must be in [0, 1)")
        _check(self.min_width >= 0, "tracking.min_width", "must be >= 0 pixels (0 = no floor)")
        _check(0 <= self.min_valid_fraction <= 1, "tracking.min_valid_fraction", "must be in [0, 1]")
        _check(0 <= self.gradient_mask_percentile < 100, "tracking.gradient_mask_percentile", "must be in [0, 100)")
        _check(self.failure_loss_ratio > 1, "tracking.failure_loss_ratio", "must be > 1")
        _check(self.relocalise_loss_ratio == 0 or self.relocalise_loss_ratio > 1, "tracking.relocalise_loss_ratio",
               "must be 0 (off) or > 1")
        _check(0 <= self.coarse_share < 1, "tracking.coarse_share", "must be in [0, 1)")
        _check(self.coarse_mode_iterations >= 0, "tracking.coarse_mode_iterations", "must be >= 0 (0 = none)")
        _check(self.relocalise_max_m > 0 and self.relocalise_max_deg > 0, "tracking.relocalise_max_*",
               "must be positive (metres, degrees)")
        _check(0 <= self.running_loss_momentum < 1, "tracking.running_loss_momentum", "must be in [0, 1)")


@dataclass(frozen=True)
class FrontendConfig:
    """Wide-basin start of tracking (mipslam/frontend.py): ORB features with depth matched to the previous
    frame, pose by PnP RANSAC; rendering then refines it. A failed match falls back to the motion model,
    and a frame whose tracking fails is relocalised against the newest keyframes the same way."""

    method: Literal["none", "orb_pnp"] = "orb_pnp"  # none: tracking starts from the motion model alone
    num_features: int = 1000  # ORB keypoints per frame
    pyramid_levels: int = 4  # ORB scale levels (factor 1.2 each)
    fast_threshold: int = 12  # FAST corner threshold, grey levels of 255
    ratio_test: float = 0.85  # Lowe's ratio test on the two nearest descriptors
    # matching first searches around the motion model's projection, this fraction of the image size wide
    # (repeated texture then cannot match the wrong copy); 0 matches over the whole image only
    guided_radius: float = 0.1
    max_hamming: int = 64  # descriptor distance above which a match is dropped (of 256 bits)
    ransac_reprojection_px: float = 3.0  # PnP RANSAC inlier threshold at the tracked image's resolution
    ransac_iterations: int = 200
    min_inliers: int = 25  # fewer agreeing matches: the features say nothing (fall back / lost)
    min_inlier_ratio: float = 0.25  # inliers / matches below this: not trusted
    relocalise_keyframes: int = 8  # a frame whose tracking failed is matched to this many newest keyframes

    def __post_init__(self):
        _check(self.num_features >= 50, "frontend.num_features", "must be >= 50")
        _check(1 <= self.pyramid_levels <= 8, "frontend.pyramid_levels", "must be in [1, 8]")
        _check(0 < self.ratio_test <= 1, "frontend.ratio_test", "must be in (0, 1]")
        _check(0 <= self.guided_radius <= 2, "frontend.guided_radius", "must be in [0, 2] (0 = off)")
        _check(0 < self.max_hamming <= 256, "frontend.max_hamming", "must be in (0, 256]")
        _check(self.ransac_reprojection_px > 0, "frontend.ransac_reprojection_px", "must be positive (pixels)")
        _check(self.ransac_iterations >= 1, "frontend.ransac_iterations", "must be >= 1")
        _check(self.min_inliers >= 6, "frontend.min_inliers", "must be >= 6 (PnP needs at least 6 points)")
        _check(0 <= self.min_inlier_ratio <= 1, "frontend.min_inlier_ratio", "must be in [0, 1]")
        _check(self.relocalise_keyframes >= 0, "frontend.relocalise_keyframes", "must be >= 0 (0 = off)")


@dataclass(frozen=True)
class KeyframeConfig:
    covisibility_threshold: float = 0.9  # new keyframe when overlap with the last drops below
    translation_ratio: float = 0.1  # ... or translation > ratio * median scene depth
    rotation_deg: float = 15.0
    # ... or the map renders less than this fraction of the frame's valid depth at the tracked pose (0 = off)
    min_map_coverage: float = 0.0
    window_size: int = 8
    random_past: int = 2
    # Covisibility (mipslam/keyframes.py): a point is seen by both frames when their depths agree within this
    # fraction, evaluated on every covisibility_pixel_stride-th pixel in u and v.
    covisibility_depth_tolerance: float = 0.1
    covisibility_pixel_stride: int = 4
    window_min_overlap: float = 0.05  # window keyframes seeing less of the new keyframe than this leave

    def __post_init__(self):
        _check(0 < self.covisibility_threshold <= 1, "keyframes.covisibility_threshold", "must be in (0, 1]")
        _check(0 <= self.min_map_coverage <= 1, "keyframes.min_map_coverage", "must be in [0, 1] (0 = off)")
        _check(self.covisibility_depth_tolerance > 0, "keyframes.covisibility_depth_tolerance", "must be positive")
        _check(self.covisibility_pixel_stride >= 1, "keyframes.covisibility_pixel_stride", "must be >= 1")
        _check(0 <= self.window_min_overlap <= 1, "keyframes.window_min_overlap", "must be in [0, 1]")
        _check(self.window_size >= 1, "keyframes.window_size", "must be >= 1")
        _check(self.random_past >= 0, "keyframes.random_past", "must be >= 0")


@dataclass(frozen=True)
class MappingConfig:
    iterations: int = 60
    first_frame_iterations: int = 200
    lr_means: float = 1e-3
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_colors: float = 5e-3
    # Adam rate of the joint refinement of the poses of the keyframes mapping trains on (m, rad; keyframe 0
    # stays fixed). Adam moves a pose by about this per step, so the rate times the steps bounds how far
    # mapping can correct tracking (docs/bench.md; fast takes 3e-4).
    lr_poses: float = 1e-4
    alpha_color: float = 0.5
    isotropy_weight: float = 10.0
    # Frequency-domain loss weight (docs/evaluation.md, `mipslam bench --scenario frequency_loss`): 1000 gives sharper
    # training views and lower LPIPS (Replica room0 fast +0.9 dB) at a slightly higher ATE (0.17 -> 0.31 cm), so
    # the balanced and accurate presets turn it on and the base config (speed, tracking first) leaves it off.
    lambda_freq: float = 0.0
    freq_patch: int = 16
    freq_alpha: float = 1.0
    # When the frequency loss's gradient may move the geometry (means, shapes, opacities) and the keyframe poses
    # in mapping: "always"; "final": never while frames are tracked (it moves the colours alone, as if the image it
    # scores were rendered with the geometry and the pose held fixed), so only the final refinement's loss moves
    # them. On rendered images every edge is geometry and "always" tracks best; on a real camera's the loss pulls
    # the geometry after detail that tracking then reads wrong, and the built-in tum config takes "final"
    # (docs/mapping.md, "The frequency loss and the geometry").
    freq_moves_geometry: Literal["final", "always"] = "always"
    add_opacity_threshold: float = 0.5
    add_depth_error_ratio: float = 10.0  # depth error above ratio * median error adds Gaussians
    densify_pixel_stride: int = 1  # one new Gaussian per stride x stride pixels
    # A new Gaussian's std-dev in units of its cell (stride pixels at its depth). 1 blurs neighbours into each
    # other (a 20-iteration map keeps that blur and biases tracking); below about 0.5 the splats leave gaps.
    initial_scale_factor: float = 1.0
    # A new Gaussian is not added when an existing centre lies within this many of its std-devs: a revisit
    # that misses the mapped surface by a little re-fits it instead of layering a copy over it. 0 = off.
    # The fast and balanced presets use 2 (docs/robustness.md); at 40x30 a radius of 2 std-devs (4 px)
    # also blocks real surfaces and costs tracking accuracy, so the base value is 1.
    add_min_distance_ratio: float = 1.0
    # A new Gaussian's opacity. With short mapping the map's rendered opacity stays below 1 (about 0.985 at 0.5), and
    # the raw depth term then places the Gaussians about 1 / A - 1 too far; `fast` uses 0.98 (`mipslam bench --scenario tracking_bias`).
    initial_opacity: float = 0.5
    prune_opacity: float = 0.005
    prune_max_sigma_px: float = 50.0  # std-dev larger than this many pixels (seen from the keyframe) is absurd
    max_gaussians: int = 200_000
    # Depth term on the alpha-normalised rendered depth D / max(A, depth_alpha_floor): where the map's
    # opacity A < 1 the raw D = sum T a z is minimised by Gaussians 1 / A - 1 too far (docs/mapping.md).
    depth_normalise: bool = False
    depth_alpha_floor: float = 0.5
    max_depth: float = 0.0  # metres; observed depth beyond it stays out of the depth term (0 = no limit)
    # Keyframe images (and loss masks) mapping keeps on the device, most recently used first, instead of reading
    # them from disk again on every revisit; 0 = none. 64 at 320x240 is about 80 MB (docs/mapping.md).
    keyframe_cache: int = 64
    # Weight of mean(1 - A) over pixels with valid depth (0 = off). The raw depth term raised the opacity A; the
    # alpha-normalised one does not, so depth_normalise needs this to keep the map opaque (docs/mapping.md).
    opacity_weight: float = 0.0

    def __post_init__(self):
        _check(self.iterations >= 0, "mapping.iterations", "must be >= 0")
        _check(self.opacity_weight >= 0, "mapping.opacity_weight", "must be >= 0 (0 = off)")
        _check(self.keyframe_cache >= 0, "mapping.keyframe_cache", "must be >= 0 (0 = no cache)")
        _check(0 < self.depth_alpha_floor <= 1, "mapping.depth_alpha_floor", "must be in (0, 1]")
        _check(self.max_depth >= 0, "mapping.max_depth", "must be >= 0 metres (0 = no limit)")
        _check(self.max_gaussians >= 1, "mapping.max_gaussians", "must be >= 1")
        _check(self.freq_patch >= 2, "mapping.freq_patch", "must be >= 2")
        _check(self.lambda_freq >= 0, "mapping.lambda_freq", "must be >= 0")
        _check(self.densify_pixel_stride >= 1, "mapping.densify_pixel_stride", "must be >= 1")
        _check(0 < self.initial_opacity < 1, "mapping.initial_opacity", "must be in (0, 1)")
        _check(self.prune_max_sigma_px > 0, "mapping.prune_max_sigma_px", "must be positive")
        _check(self.add_min_distance_ratio >= 0, "mapping.add_min_distance_ratio", "must be >= 0 (0 = off)")
        _check(self.initial_scale_factor > 0, "mapping.initial_scale_factor", "must be positive")


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
    """Loop closure and SA-PGO (docs/pgo.md): detection, verification, pose graph, map correction."""

    enabled: bool = True  # false: no loop stage at all (the run is exactly the one without it)
    # a loop candidate is at least this many keyframes older than the query
    min_keyframe_gap: int = CandidateOptions.min_gap
    # verification method: dense RGB-D alignment, tracking's Gauss-Newton (direct) or Open3D's (rgbd_odometry),
    # the most robust on the room scenes; direct verifies the same candidates 5x faster (docs/pgo.md)
    registration: Literal["direct", "rgbd_odometry", "point_to_plane", "colored"] = "direct"
    # direct verification's depth residuals in units of z^p, as tracking.direct_depth_noise_power (built-in tum: 2)
    registration_depth_noise_power: float = RegistrationOptions.direct_depth_noise_power
    icp_fitness_threshold: float = RegistrationOptions.fitness_threshold  # fraction of points with a correspondence
    icp_rmse_threshold: float = RegistrationOptions.rmse_threshold  # verification: inlier RMSE, metres
    # finest voxel of ICP and of the fitness/RMSE checks (ICP starts at 2x)
    icp_voxel_m: float = RegistrationOptions.voxel_sizes[-1]
    icp_pixel_stride: int = RegistrationOptions.pixel_stride  # every n-th pixel of each keyframe goes into the clouds
    # odometry edge (keyframe k-1 -> k) standard deviation: floor + drift_ratio * distance (rotation)
    # travelled since keyframe k-1, divided by sqrt(tracking quality), quality = running tracking
    # loss / this keyframe's loss, in [0.1, 1]
    odometry_sigma_m: float = 0.01
    odometry_sigma_deg: float = 0.5
    odometry_drift_ratio: float = 0.05
    # A loop edge's covariance is the registration's plus this floor (standard deviations, per axis): Open3D's
    # information claims millimetres, and a pose graph that believes it bends the odometry chain at its weakest
    # link. 1 cm / 0.5 deg helped `balanced` on fr1_rpy (4.39 -> 3.73 cm) and cost `fast` there (2.79 -> 3.26 cm),
    # the lap and the noisy loop unchanged (docs/tracking.md, "Loop closure"); 0 and 0 (the default): the
    # registration's information alone.
    loop_sigma_m: float = 0.0
    loop_sigma_deg: float = 0.0
    # SA-PGO's two switches (on here; PGOOptions' defaults are the plain full-LM baseline they are measured against)
    spectral_edge_weighting: bool = True
    low_frequency_correction: bool = True
    num_eigenvectors: int = PGOOptions.num_eigenvectors  # low-frequency basis size K
    full_iterations: int = PGOOptions.full_iterations  # full LM iterations after the subspace stage
    # Mapping steps over the loop's keyframes right after the map moved with its anchors: Gaussians
    # that mapping had pulled towards drifted views do not move back with any anchor; this re-fits them.
    refine_iterations: int = 20
    # Verification also rejects a registration that moved the current estimate by more than this many
    # standard deviations of the drift the odometry edges allow over the keyframe path from the candidate
    # to the query (odometry_sigma + odometry_drift_ratio * path, translation and rotation): a loop 20
    # keyframes back cannot need a 20 cm correction. With one loop edge the pose graph has nothing to
    # outvote a wrong one. 0 turns the check off.
    max_drift_sigmas: float = 3.0
    # New loop edges that already agree with the current poses (every e^T Omega e at most this, chi-square
    # with 6 dof; 12.6 is its 95% quantile) join the graph without an optimisation: on a revisited route
    # nearly every keyframe verifies a loop, and re-optimising the whole graph for each made the pose-graph
    # time per frame grow with the run's length. 0 optimises on every new loop edge.
    consistent_chi2: float = 12.6
    # ... as do edges whose disagreement is below what tracking resolves (the registration information
    # claims millimetres; re-optimising for a 1-2 cm residual on every revisit keyframe only churns the map).
    min_correction_m: float = 0.02
    min_correction_deg: float = 1.0
    # A loop edge that disagrees with the current poses enters the graph only when a second registration implies
    # the same correction: another verified loop edge of this keyframe (to a different old keyframe) or of one of
    # the previous `confirm_keyframes` keyframes (ORB-SLAM's consistency check over consecutive keyframes). Real
    # drift moves neighbouring keyframes alike; registration noise does not. Two corrections C = T_i Z_ik T_k^-1
    # agree when, seen from keyframe k, they differ by at most max(confirm_tolerance_m, confirm_relative x the
    # smaller one) in translation and likewise in rotation. 0 turns the check off (every verified edge may
    # trigger the optimisation). docs/tracking.md, "Loop closure".
    confirm_keyframes: int = 2
    confirm_tolerance_m: float = 0.01
    confirm_tolerance_deg: float = 0.5
    confirm_relative: float = 0.5
    # The pose-graph optimisation frees only the newest keyframes (older ones that share an edge with
    # them stay fixed as anchors); 0 frees the whole graph. A whole-graph solve costs time in proportion
    # to the keyframes, and a revisited room optimises every other keyframe: on a 2000-frame run the
    # optimiser's time per frame grew 7x over 8 laps (docs/robustness.md, "Long runs").
    pgo_window_keyframes: int = 200
    # An applied correction is undone (and its new loop edges leave the graph) when the map, moved with it,
    # renders the loop's keyframes more than this many dB (mean PSNR) worse than before: a loop edge that
    # tears the map apart contradicts what tracking and mapping measured. Negative: no check. Right corrections
    # of the data_synth lap dropped it by 1.3-1.9 dB before the map was refined (1 dB undid them: ATE 0.90 ->
    # 1.97 cm, docs/tracking.md "Loop closure"); 3 dB undoes only tears.
    max_correction_psnr_drop_db: float = 3.0

    def __post_init__(self):
        _check(self.pgo_window_keyframes >= 0, "loop.pgo_window_keyframes", "must be >= 0 (0 = the whole graph)")
        _check(self.max_drift_sigmas >= 0, "loop.max_drift_sigmas", "must be >= 0 (0 = no check)")
        _check(self.min_correction_m >= 0 and self.min_correction_deg >= 0, "loop.min_correction_*",
               "must be >= 0 (0 = no floor)")
        _check(self.consistent_chi2 >= 0, "loop.consistent_chi2", "must be >= 0 (0 = always optimise)")
        _check(self.confirm_keyframes >= 0, "loop.confirm_keyframes", "must be >= 0 (0 = no confirmation)")
        _check(self.confirm_tolerance_m >= 0 and self.confirm_tolerance_deg >= 0 and self.confirm_relative >= 0,
               "loop.confirm_*", "tolerances must be >= 0")
        _check(self.refine_iterations >= 0, "loop.refine_iterations", "must be >= 0")
        _check(self.min_keyframe_gap >= 1, "loop.min_keyframe_gap", "must be >= 1")
        _check(self.num_eigenvectors >= 1, "loop.num_eigenvectors", "must be >= 1")
        _check(self.full_iterations >= 0, "loop.full_iterations", "must be >= 0")
        _check(0 <= self.icp_fitness_threshold <= 1, "loop.icp_fitness_threshold", "must be in [0, 1]")
        _check(self.icp_rmse_threshold > 0, "loop.icp_rmse_threshold", "must be positive (metres)")
        _check(self.icp_voxel_m > 0, "loop.icp_voxel_m", "must be positive (metres)")
        _check(self.icp_pixel_stride >= 1, "loop.icp_pixel_stride", "must be >= 1")
        _check(self.registration_depth_noise_power >= 0, "loop.registration_depth_noise_power",
               "must be >= 0 (0 = metres)")
        _check(self.odometry_sigma_m > 0, "loop.odometry_sigma_m", "must be positive (metres)")
        _check(self.odometry_sigma_deg > 0, "loop.odometry_sigma_deg", "must be positive (degrees)")
        _check(self.odometry_drift_ratio >= 0, "loop.odometry_drift_ratio", "must be >= 0")
        _check(self.loop_sigma_m >= 0 and self.loop_sigma_deg >= 0, "loop.loop_sigma_*", "must be >= 0 (0 = no floor)")


@dataclass(frozen=True)
class EvalConfig:
    """The run's own evaluation (``mipslam eval RUN_DIR`` and the end of ``mipslam run``; docs/evaluation.md)."""

    alignment: Literal["se3", "sim3", "none"] = "se3"
    association_tolerance_s: float = 0.02
    # split: two rows, novel views (MonoGS: frames.json positions 0, 5, 10, ... that are not keyframes) and
    # training views (the keyframes); all | keyframes | non_keyframes: one row of that set
    frames: Literal["split", "all", "keyframes", "non_keyframes"] = "split"
    # what scale 1 means: native = the camera's own images (the dataset read with downscale 1, original
    # intrinsics); mapping = the frames the run mapped (after dataset.downscale)
    resolution: Literal["native", "mapping"] = "native"
    scales: tuple[float, ...] = (1.0,)  # of the `resolution` reference
    modes: tuple[str, ...] = ()  # empty = the run's render mode

    def __post_init__(self):
        _check(self.association_tolerance_s > 0, "eval.association_tolerance_s", "must be positive")
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
    refine: RefineConfig = field(default_factory=RefineConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)


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
    "render.eaa_point_area": "retired: EAA's 1-node threshold is now 'render.eaa_single_node_sigma' "
                             "(minor-axis std-dev in px, default 1.0; docs/renderer.md 2.2); delete the line or "
                             "set the new key",
    "mapping.final_iterations": "retired: the final refinement is now 'refine.passes' (passes over every keyframe, "
                                "a pass at least 10 steps; docs/mapping.md); delete the line or set the new key",
}


def _build(cls: type, data: Mapping[str, Any], prefix: str) -> Any:
    if not isinstance(data, Mapping):
        raise ConfigError(f"config key '{prefix.rstrip('.') or '<root>'}': expected a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    for key in data:
        if key not in names:
            if f"{prefix}{key}" in RETIRED_KEYS:
                raise ConfigError(f"config key '{prefix}{key}': {RETIRED_KEYS[f'{prefix}{key}']}")
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
