"""Tracking: optimise one camera pose (and an affine exposure) against the frozen map.

The pose is parametrised as a left increment in the camera frame,
``T_cw = exp(xi) T_cw_init`` with ``xi = [rho, phi]`` (se(3), translation first), and optimised with
Adam or Rprop (``TrackingOptions.optimizer``) on the loss of docs/design.md ("Losses", tracking):
``alpha_c * mean(M_rgb |exposure(I) - I_gt|) + (1 - alpha_c) * mean(M_d |D - D_gt|)``,
where the masks keep valid depth, rendered opacity >= ``opacity_threshold`` (pixels the map explains)
and, for colour, pixels above an image-gradient percentile. Optional coarse-to-fine: the first
levels run at reduced resolution (area-averaged targets, intrinsics scaled with the pixel-centre rule),
optionally in a cheaper footprint mode (``TrackingOptions.coarse_render_mode``), as may the first
``tracking.coarse_mode_iterations`` steps at the finest resolution (the later steps alone judge the best pose).
The renderer's pose-only backward is used (the map is frozen), on the Gaussians that can reach the
view from the motion-model pose (:func:`~mipslam.rendering.frustum_indices`, ``mipslam.rendering.FRUSTUM_MARGIN``).
With ``tracking.direct_iterations`` > 0 the gradient steps start where a direct RGB-D alignment
(Gauss-Newton, :func:`~mipslam.geometry.direct.align_direct`) of the map's render onto the frame ends.

Failure (non-finite loss, too few valid pixels, loss far above its running level) keeps the
motion-model pose and is reported, never raised: the pipeline flags the frame and skips mapping.

:func:`track_frame` is the stage's step in the frame loop: the motion-model prediction, tracking,
relocalisation when the loss stays high (:func:`relocalise`), the check of a pose that the map's depth or the
motion disputes (:func:`verify_pose`: a wider search, else the frame is flagged with its best pose), and the
projection of the result onto SE(3).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Callable, Literal

import numpy as np
import torch

from mipslam.config import RenderConfig, TrackingConfig, section_options
from mipslam.errors import MipslamError
from mipslam.gaussians import ActivatedGaussians
from mipslam.geometry import nearest_rigid, resize_area
from mipslam.frontend import Frontend, FrontendStart
from mipslam.geometry.direct import DirectReference, DirectTarget, direct_reference, direct_target, pyramid_scales
from mipslam.geometry.se3 import relative_motion, se3_exp, se3_exp_times, se3_exp_times_vjp, se3_inverse, se3_log
from mipslam.losses.photometric import (RGBDLoss, RGBDMasks, apply_affine_exposure, rgbd_l1_loss,
                                        rgbd_masks)
from mipslam.loop.registration import RegistrationOptions, register_rgbd_odometry
from mipslam.render import RenderOutput, direct_aligner, rgbd_loss_and_gradients
from mipslam.rendering import frustum_subset, render_view, render_view_pose_only
from mipslam.types import Frame, Intrinsics

if TYPE_CHECKING:
    from mipslam.datasets import FrameCache
    from mipslam.state import SLAMState

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackingResult:
    """Outcome of tracking one frame.

    T_wc:           [4, 4] float64 camera-to-world (the motion-model pose when tracking failed)
    exposure:       [2] float32 (log_gain, bias) of the affine exposure model (zeros when off)
    loss:           final loss at the finest level (tracking.resolution_scale; NaN when it could not be computed)
    iterations:     tracking-loss renders over all levels plus the direct alignment's Gauss-Newton steps
    valid_fraction: fraction of pixels in the depth term at the finest level
    ok:             False when tracking failed (the frame is flagged and not mapped)
    status:         "ok", "initial", "non_finite_loss", "too_few_valid_pixels", "loss_jump" or
                    "depth_disagreement" (:func:`verify_pose`; the frame keeps the tracked pose, flagged)
    map_coverage:   fraction of the frame's valid-depth pixels (finest level) where the map renders a surface
                    (opacity >= TrackingOptions.coverage_opacity) at the returned pose; NaN when not rendered
    depth_disagreement: fraction of those covered pixels whose rendered depth D / A differs from the measured
                    depth by more than TrackingOptions.disagreement_tolerance of it; NaN when not rendered
    """

    T_wc: torch.Tensor
    exposure: torch.Tensor
    loss: float
    iterations: int
    valid_fraction: float
    ok: bool
    status: str
    map_coverage: float = math.nan
    depth_disagreement: float = math.nan


def constant_velocity_prediction(T_wc_prev: torch.Tensor, T_wc_prev_tracked: torch.Tensor,
                                 T_wc_prev2_tracked: torch.Tensor | None) -> torch.Tensor:
    """Pose predicted by repeating the last tracked motion.  [4, 4] x 3 -> [4, 4] float64

    ``T_wc_pred = T_prev (T2^-1 T1)``: T1 and T2 are the previous frame's pose and the one's before it as
    tracking estimated them, ``T_prev`` the previous pose as it stands now. Mapping may have refined it since
    (a keyframe's pose) or a loop correction moved it: the motion from the tracked poses applies such a change
    once, where the difference of the current poses would repeat it as motion. With no frame before the
    previous, the previous pose itself.
    """
    if T_wc_prev2_tracked is None:
        return T_wc_prev.clone()
    return T_wc_prev @ (se3_inverse(T_wc_prev2_tracked) @ T_wc_prev_tracked)


@dataclass(frozen=True)
class _Level:
    intrinsics: Intrinsics
    color: torch.Tensor  # [h, w, 3]
    depth: torch.Tensor  # [h, w]
    target_masks: RGBDMasks  # [h, w] bool each: valid targets (and the gradient mask), before the opacity test
    iterations: int
    render_mode: str | None  # footprint mode of this level's renders (None: render.mode)


@dataclass(frozen=True)
class _Seen:
    """A render at tracking's finest level: its loss, depth-term pixels, covered pixels and those whose depth
    disagrees (:meth:`Tracker._coverage`), and pose [4, 4] float64 world-to-camera."""

    loss: float
    depth_pixels: int
    covered: int
    disagreeing: int
    T_cw: torch.Tensor


@dataclass(frozen=True)
class _StartView:
    """One of best_start's renders: the map it rendered, the pose [4, 4] (the map's dtype, world-to-camera), the
    map's frustum subset there, the render and its tracking loss (tracking from that start reuses all three).
    ``loss`` is None on a view carried to a re-timed copy of the judged frame (:meth:`Tracker.retimed`): the
    render holds, its loss against the moved images is computed when read."""

    gaussians: ActivatedGaussians
    T_cw: torch.Tensor
    subset: ActivatedGaussians
    render: RenderOutput
    loss: RGBDLoss | None


@dataclass(frozen=True)
class _StepRender:
    """A gradient step's render (:meth:`Tracker._step_render`): its loss, opacity and depth [h, w] (no gradient),
    and ``backward()``, which sets the pose parameters' (and the exposure's) ``.grad``."""

    loss: RGBDLoss
    alpha: torch.Tensor
    depth: torch.Tensor
    backward: Callable[[], None]


@dataclass
class _FrameWork:
    """What tracking builds once for a frame and every read of it shares (the start judge, tracking and its
    retries): the pyramid and loss masks, the direct alignment's pyramid, and the start judge's renders."""

    frame: Frame
    levels: list[_Level]
    direct_targets: list[DirectTarget] | None = None
    starts: list[_StartView] = field(default_factory=list)

    def start_view(self, gaussians: ActivatedGaussians, T_cw: torch.Tensor) -> _StartView | None:
        """The start judge's render of ``gaussians`` at exactly ``T_cw``, if it made one."""
        for view in self.starts:
            if view.gaussians is gaussians and torch.equal(view.T_cw, T_cw):
                return view
        return None


@dataclass(frozen=True)
class TrackingOptions:
    """Everything tracking reads: the ``tracking`` config section's keys (defaults there) and the stage's
    constants (defined here; their evidence is in docs/tracking.md and docs/bench.md). Built from the config
    by :meth:`from_config`; a test or a benchmark that needs another constant ``replace``-s it."""

    iterations: int = TrackingConfig.iterations
    direct_iterations: int = TrackingConfig.direct_iterations
    resolution_scale: float = TrackingConfig.resolution_scale
    coarse_mode_iterations: int = TrackingConfig.coarse_mode_iterations
    use_exposure: bool = TrackingConfig.use_exposure
    opacity_threshold: float = TrackingConfig.opacity_threshold
    relocalise_loss_ratio: float = TrackingConfig.relocalise_loss_ratio
    # The sensor's depth noise power p (dataset.depth_noise_power): the direct alignment's depth residuals are in
    # units of z^p (0: metres); its robust scale stays per frame (docs/tracking.md, "Depth noise").
    direct_depth_noise_power: float = 0.0
    # rprop: lr_* is each coordinate's first step (m, rad); it grows 1.2x while the coordinate's gradient keeps its
    # sign and halves when it flips, never beyond lr * rprop_max_step_ratio, so a good start is refined in small
    # steps and a level stops once the steps fall below convergence_threshold. adam (no shipped config): every
    # step moves a coordinate by about lr until the end.
    optimizer: Literal["adam", "rprop"] = "rprop"
    lr_translation: float = 5e-4
    lr_rotation: float = 1e-3
    rprop_max_step_ratio: float = 50.0
    # Stop a level when the pose update (se3 norm; rprop: the norm of its next steps) is below this.
    convergence_threshold: float = 1e-4
    alpha_color: float = 0.5  # weight of the photometric term against depth
    coarse_to_fine: tuple[float, ...] = ()  # e.g. (0.5,) tracks at half resolution first
    coarse_share: float = 0.5  # fraction of the iterations given to the coarse levels (split evenly between them)
    min_width: int = 160  # the finest level is never narrower than this (pixels; 0 = no floor)
    # a pixel the map renders at this opacity or more counts as mapped (keyframes.min_map_coverage)
    coverage_opacity: float = 0.5
    # The feature front-end's start replaces the motion model's only when the map renders it with a loss lower
    # by this fraction (Tracker.best_start).
    start_margin: float = 0.1
    min_valid_fraction: float = 0.05
    failure_loss_ratio: float = 5.0  # loss above ratio * running level = failure
    # Geometric check of a tracked pose (verify_pose): a covered pixel disagrees when its rendered depth D / A is
    # off the measured depth by more than this fraction of it; a frame is checked when the fraction of disagreeing
    # pixels exceeds both disagreement_floor and disagreement_ratio times its running level (repeated texture
    # aligned one period off, where the photometric loss hardly rises; docs/tracking.md, "Checking a tracked pose").
    disagreement_tolerance: float = 0.1
    disagreement_floor: float = 0.015
    disagreement_ratio: float = 4.0
    # The checked frame's wider search runs the direct alignment over this many more pyramid levels (each halves
    # the image: a 9 degree turn is 36 pixels at 320x240, 4.5 at a 40x30 top level). Not always on: on fr1_rpy
    # two more levels everywhere cost ATE (1.39 -> 1.51 cm, fast; docs/tracking.md, "Checking a tracked pose").
    wide_search_levels: int = 2
    # A tracked pose this far from the motion model's prediction (a sudden turn or jolt: fr1_rpy's largest is
    # 2.8 degrees / 5.3 cm, a fast spin's onset 9 degrees) is checked by the same wider search.
    motion_check_deg: float = 4.0
    motion_check_m: float = 0.08
    # Largest jump relocalisation accepts from the RGB-D alignment to the previous frame (a bump, dropped frames).
    relocalise_max_m: float = 1.0
    relocalise_max_deg: float = 45.0
    # Where the feature front-end gives no start (texture-poor or repeated texture, a large motion), align the
    # newest tracked frame to this one by dense RGB-D odometry (Open3D) from the motion model's pose; the render
    # loss then judges that pose against the motion model's (Tracker.best_start). Bounded by relocalise_max_*.
    dense_start: bool = True
    # Move each depth image to its colour image's instant with the motion model, where the dataset gives the two
    # their own timestamps (mipslam.sensor_sync). Off: on fr1_rpy, whose timestamps are the driver's, it is worse
    # (docs/tracking.md, "Colour and depth at different instants").
    align_depth_time: bool = False
    # Momentum of the running level of good tracking losses (exponential moving average) that the failure and
    # relocalisation ratios compare a frame's loss with.
    running_loss_momentum: float = 0.9
    # Footprint mode of tracking's renders (None: render.mode), and of the coarse levels and the first
    # coarse_mode_iterations steps of the finest (None: render_mode).
    render_mode: Literal["point", "mip", "ewa", "eaa", "exact"] | None = None
    coarse_render_mode: Literal["point", "mip", "ewa", "eaa", "exact"] | None = "mip"
    # Depth term on the alpha-normalised rendered depth D / max(A, depth_alpha_floor) instead of the raw
    # D = sum T a z (mipslam/losses/photometric.py; docs/mapping.md).
    depth_normalise: bool = False
    depth_alpha_floor: float = 0.5
    max_depth: float = 0.0  # metres; observed depth beyond it stays out of the depth term (0 = no limit)
    # Depth pixels whose residual exceeds this many times the median residual leave the depth term (0 = off).
    depth_outlier_ratio: float = 0.0
    # Direct RGB-D alignment (mipslam/geometry/direct.py) of the map's render onto the frame before the gradient
    # steps: direct_iterations Gauss-Newton steps per pyramid level at most, direct_levels levels (each half the
    # next, the finest at tracking's finest resolution), direct_renders renders of the map it aligns to (each
    # after the first at the pose the previous alignment reached; a render that explains the frame worse ends
    # the alignment at the pose before it).
    direct_levels: int = 2
    direct_renders: int = 1
    direct_convergence: float = 1e-4  # a level stops once a step's se(3) norm falls below this
    # Weight of the intensity term against depth in the alignment, each term in units of its robust scale
    # (docs/tracking.md: 0.7-0.9 tracked fr1_rpy best under its colour-depth lag).
    direct_alpha_color: float = 0.8

    @classmethod
    def from_config(cls, section: TrackingConfig, *, depth_noise_power: float = 0.0) -> "TrackingOptions":
        """The options of a ``tracking`` config section and the dataset's ``depth_noise_power``."""
        return section_options(cls, section, direct_depth_noise_power=depth_noise_power)


class Tracker:
    """Tracks frames against a frozen map (its options and the render config section)."""

    def __init__(self, config: TrackingOptions, render_config: RenderConfig):
        self.config = config
        self.render_config = render_config
        self._work: _FrameWork | None = None  # of the frame tracked last

    def _frame_work(self, frame: Frame) -> _FrameWork:
        """The frame's shared work (:class:`_FrameWork`), started on the first read of a new frame."""
        if self._work is None or self._work.frame is not frame:
            self._work = _FrameWork(frame, self._build_levels(frame))
        return self._work

    def retimed(self, frame: Frame, moved: Frame) -> None:
        """Take ``moved``, a copy of ``frame`` with its images moved to another instant (same index, camera and
        pose; :mod:`mipslam.sensor_sync`), as the frame tracked next. The start judge's renders of ``frame`` are
        kept for it (they depend on the map, the pose and the camera alone); their losses and the image
        pyramid are computed again from the moved images."""
        if moved is frame or self._work is None or self._work.frame is not frame:
            return
        if moved.index != frame.index or moved.intrinsics != frame.intrinsics:
            raise ValueError(f"Tracker.retimed: frame {moved.index} is not a re-timed copy of frame {frame.index}")
        starts = [replace(view, loss=None) for view in self._work.starts]
        self._work = _FrameWork(moved, self._build_levels(moved), starts=starts)

    def _levels(self, frame: Frame) -> list[_Level]:
        """The frame's image pyramid and loss masks, coarse to fine (built once per frame)."""
        return self._frame_work(frame).levels

    def _build_levels(self, frame: Frame) -> list[_Level]:
        cfg = self.config
        finest = max(cfg.resolution_scale, min(1.0, cfg.min_width / frame.intrinsics.width))
        scales = [s * finest for s in cfg.coarse_to_fine if s < 1.0] + [finest]
        coarse_total = int(round(cfg.iterations * cfg.coarse_share)) if len(scales) > 1 else 0
        per_coarse = coarse_total // max(1, len(scales) - 1)
        levels = []
        for scale in scales:
            if scale == 1.0:
                color, depth, intrinsics = frame.color, frame.depth, frame.intrinsics
                iterations = cfg.iterations - per_coarse * (len(scales) - 1)
            elif scale == finest:
                intrinsics = frame.intrinsics.scaled(scale)
                color = resize_area(frame.color, scale)
                depth = resize_area(frame.depth, scale, valid=frame.depth > 0)
                iterations = cfg.iterations - per_coarse * (len(scales) - 1)
            else:
                intrinsics = frame.intrinsics.scaled(scale)
                color = resize_area(frame.color, scale)
                depth = resize_area(frame.depth, scale, valid=frame.depth > 0)
                iterations = per_coarse
            if iterations <= 0:
                continue
            target_masks = rgbd_masks(color, depth, max_depth=cfg.max_depth)
            mode = cfg.render_mode if scale == finest or cfg.coarse_render_mode is None else cfg.coarse_render_mode
            levels.append(_Level(intrinsics, color, depth, target_masks, iterations, mode))
        return self._split_finest_by_mode(levels)

    def _split_finest_by_mode(self, levels: list[_Level]) -> list[_Level]:
        """``levels`` with the finest level's first ``tracking.coarse_mode_iterations`` steps (at most all but
        one) as a level of their own in ``TrackingOptions.coarse_render_mode``: the same images, a cheaper footprint."""
        cfg, finest = self.config, levels[-1]
        finest_mode = finest.render_mode or self.render_config.mode
        split = min(cfg.coarse_mode_iterations, finest.iterations - 1)
        if split <= 0 or cfg.coarse_render_mode in (None, finest_mode):
            return levels
        return levels[:-1] + [replace(finest, iterations=split, render_mode=cfg.coarse_render_mode),
                              replace(finest, iterations=finest.iterations - split)]

    def _direct_targets(self, frame: Frame) -> list[DirectTarget]:
        """The frame's pyramid for the direct alignment, coarse to fine, the finest at tracking's finest level
        (built once per frame)."""
        work = self._frame_work(frame)
        if work.direct_targets is not None:
            return work.direct_targets
        full = work.levels[-1]
        depth = torch.where(full.target_masks.depth, full.depth, 0.0)  # the depth term's pixels (TrackingOptions.max_depth)
        targets = []
        for scale in pyramid_scales(self.config.direct_levels):
            color, level_depth = full.color, depth
            if scale < 1.0:
                color, level_depth = resize_area(full.color, scale), resize_area(depth, scale, valid=depth > 0)
            K = full.intrinsics.scaled(scale).matrix(dtype=torch.float32, device=full.color.device)
            targets.append(direct_target(color, level_depth, K))
        work.direct_targets = targets
        return targets

    def _direct_references(self, color: torch.Tensor, depth: torch.Tensor, mask: torch.Tensor,
                           intrinsics: Intrinsics) -> list[DirectReference]:
        """The render's pyramid as reference points, coarse to fine: color [h, w, 3], depth [h, w] (metres),
        mask [h, w] bool (opaque pixels) at tracking's finest level."""
        references = []
        for scale in pyramid_scales(self.config.direct_levels):
            level_color, level_depth, level_mask = color, depth, mask
            if scale < 1.0:
                level_color = resize_area(color, scale)
                level_depth = resize_area(depth, scale, valid=mask)
                level_mask = resize_area(mask.to(color.dtype), scale) >= 0.999  # wholly opaque pixels only
            K = intrinsics.scaled(scale).matrix(dtype=torch.float32, device=color.device)
            references.append(direct_reference(level_color, level_depth, level_mask, K))
        return references

    @torch.no_grad()
    def _direct_alignment(self, gaussians: ActivatedGaussians, frame: Frame, T_cw: torch.Tensor,
                          start_map: ActivatedGaussians | None = None) -> tuple[torch.Tensor, _Seen | None, int]:
        """Direct RGB-D alignment of the map's render at ``T_cw`` [4, 4] float64 onto the frame
        (``tracking.direct_*``; :func:`~mipslam.geometry.direct.align_direct`). ``gaussians`` is the frustum
        subset tracking renders; the first render is the start judge's where it rendered ``start_map`` (the
        whole map) at ``T_cw``.

        Returns the pose [4, 4] float64 (world-to-camera) the gradient steps start from, the render with the
        lowest loss seen on the way (None when none was finite) and the Gauss-Newton steps taken. Each render
        after the first is at the pose the previous alignment reached; one whose loss is not lower than the
        best before it ends the alignment at the best render's pose.
        """
        cfg = self.config
        full = self._levels(frame)[-1]
        targets = self._direct_targets(frame)
        dtype = gaussians.means.dtype
        best: _Seen | None = None
        steps = 0
        for round_index in range(cfg.direct_renders):
            start = self._frame_work(frame).start_view(start_map, T_cw.to(dtype)) if round_index == 0 else None
            if start is not None:
                out = start.render
                loss = start.loss if start.loss is not None else self._judged_loss(out, full)
            else:
                out = render_view(gaussians, T_cw.to(dtype), full.intrinsics, self.render_config,
                                  mode=full.render_mode, pose_only=True)
                loss = self._judged_loss(out, full)
            value = float(loss.total)
            if not math.isfinite(value) or (best is not None and value >= best.loss):
                return (T_cw if best is None else best.T_cw), best, steps
            best = _Seen(value, loss.num_depth_pixels, *self._coverage(out.depth, out.alpha, full), T_cw)
            opaque = out.alpha >= max(cfg.opacity_threshold, 1e-3)
            # The depth as the gradient steps' loss reads it (the composited sum(T a z) unless
            # TrackingOptions.depth_normalise): where the two objectives disagree the steps undo the alignment
            # (dividing by the opacity alone: the noisy dolly 0.75 -> 2.22 cm, docs/tracking.md).
            depth = out.depth / out.alpha.clamp_min(cfg.depth_alpha_floor) if cfg.depth_normalise else out.depth
            depth = torch.where(opaque, depth, 0.0)
            references = self._direct_references(out.color, depth, opaque, full.intrinsics)
            eye = torch.eye(4, dtype=torch.float64)
            align = direct_aligner(self.render_config.backend, out.color.device)
            result = align(references, targets, eye, iterations=cfg.direct_iterations,
                           alpha_color=cfg.direct_alpha_color, convergence=cfg.direct_convergence,
                           depth_noise_power=cfg.direct_depth_noise_power)
            steps += result.iterations
            if not result.ok:
                return T_cw, best, steps
            if log.isEnabledFor(logging.DEBUG):  # the logarithm costs more than the message
                motion = se3_log(result.T)
                log.debug("frame %d: direct alignment moved %.2f cm / %.2f deg in %d steps (render loss %.4f "
                          "before)", frame.index, 100 * float(motion[:3].norm()), math.degrees(float(motion[3:].norm())),
                          result.iterations, value)
            T_cw = result.T.to(T_cw) @ T_cw
        return T_cw, best, steps

    def _coverage(self, depth: torch.Tensor, alpha: torch.Tensor, level: _Level) -> tuple[int, int]:
        """(covered, disagreeing) pixel counts of a render with depth ``depth`` (metres) and opacity ``alpha`` ([h, w]
        each) against ``level``: its valid-depth pixels the render covers (opacity >=
        ``TrackingOptions.coverage_opacity``), and of those the ones where the rendered depth / alpha is off the
        measured depth by more than ``TrackingOptions.disagreement_tolerance`` of it."""
        covered = (alpha >= self.config.coverage_opacity) & level.target_masks.depth
        rendered = depth.detach() / alpha.detach().clamp_min(self.config.coverage_opacity)
        off = (rendered - level.depth).abs() > self.config.disagreement_tolerance * level.depth
        return int(covered.sum()), int((covered & off).sum())

    def _step_render(self, gaussians: ActivatedGaussians, rho: torch.Tensor, phi: torch.Tensor, T_cw_init: torch.Tensor,
                     level: _Level, exposure: torch.Tensor | None) -> _StepRender:
        """A gradient step's render at ``exp([rho, phi]) T_cw_init`` ([3], [3] leaf tensors; [4, 4] float64
        world-to-camera) against ``level``, and its backward into ``rho``, ``phi`` and ``exposure`` [2] (leaf
        tensors whose ``.grad`` it sets).

        On the compiled CPU backend the chain rule is carried by hand (:func:`se3_exp_times_vjp`,
        :func:`~mipslam.rendering.render_view_pose_only`, :func:`~mipslam.render.rgbd_loss_and_gradients`): the
        library's calls in place of autograd's graph and engine (about a quarter of a step's time at 160x120), and
        the loss and its gradient images in one library pass. The gradient images are autograd's bit for bit, the
        loss and the exposure's gradient sums equal to rounding. Elsewhere autograd (:meth:`_loss`), the reference
        (tests/test_tracking.py compares the two)."""
        dtype = gaussians.means.dtype
        T_cw, pose_vjp = se3_exp_times_vjp(rho, phi, T_cw_init, dtype)  # (se3_exp([rho, phi]) @ T_cw_init).to(dtype)
        render = render_view_pose_only(gaussians, T_cw, level.intrinsics, self.render_config, mode=level.render_mode)
        if render is None:
            T_cw = se3_exp_times(rho, phi, T_cw_init, dtype)
            loss, alpha, depth = self._loss(gaussians, T_cw, level, exposure)
            return _StepRender(loss, alpha, depth, loss.total.backward)
        affine = None if exposure is None else tuple(exposure.detach().unbind())
        loss, gradients = rgbd_loss_and_gradients(self.render_config.backend, render.color, render.depth, level.color,
                                                  level.depth, exposure=affine, **self._loss_terms(render.alpha, level))

        def backward() -> None:
            rho.grad, phi.grad = pose_vjp(render.viewmat_gradient(gradients.color, gradients.depth))
            if exposure is not None:
                exposure.grad = torch.stack([gradients.log_gain, gradients.bias])

        return _StepRender(loss, render.alpha, render.depth, backward)

    def _loss(self, gaussians: ActivatedGaussians, T_cw: torch.Tensor, level: _Level, exposure: torch.Tensor | None):
        """The loss of the map rendered at ``T_cw`` [4, 4] against ``level``, and the render's opacity and depth
        [h, w] (detached)."""
        out = render_view(gaussians, T_cw, level.intrinsics, self.render_config, mode=level.render_mode,
                          pose_only=True)
        return self._loss_of_render(out, level, exposure), out.alpha.detach(), out.depth.detach()

    def _loss_of_render(self, out: RenderOutput, level: _Level, exposure: torch.Tensor | None):
        """The tracking loss of the render ``out`` against ``level`` (differentiable where ``out`` is)."""
        color = out.color if exposure is None else apply_affine_exposure(out.color, exposure[0], exposure[1])
        return rgbd_l1_loss(color, out.depth, level.color, level.depth, **self._loss_terms(out.alpha, level))

    def _judged_loss(self, out: RenderOutput, level: _Level) -> RGBDLoss:
        """The tracking loss of the render ``out`` against ``level`` without exposure and without gradients (the
        start judge's and the direct alignment's), in one pass of the compiled library where it renders."""
        loss, _ = rgbd_loss_and_gradients(self.render_config.backend, out.color.detach(), out.depth.detach(),
                                          level.color, level.depth, gradients=False,
                                          **self._loss_terms(out.alpha, level))
        return loss

    def _loss_terms(self, alpha: torch.Tensor, level: _Level) -> dict:
        """The tracking loss's keyword arguments for a render with opacity ``alpha`` [h, w] against ``level``: its
        masks (the level's, where the render is opaque) and the tracking config's weights and depth options."""
        cfg = self.config
        return dict(alpha_color=cfg.alpha_color, masks=level.target_masks.where_opaque(alpha, cfg.opacity_threshold),
                    depth_alpha=alpha if cfg.depth_normalise else None, depth_alpha_floor=cfg.depth_alpha_floor,
                    depth_outlier_ratio=cfg.depth_outlier_ratio)

    def track(
        self,
        gaussians: ActivatedGaussians,  # the frozen map (detached)
        frame: Frame,  # on the map's device
        T_wc_init: torch.Tensor,  # [4, 4] float64 motion-model prediction, camera-to-world
        running_loss: float | None,  # typical loss of recent good frames (None: not known yet)
    ) -> TrackingResult:
        """Optimise the pose of ``frame`` from ``T_wc_init`` against the frozen map (module docstring)."""
        cfg = self.config
        device, dtype = gaussians.means.device, gaussians.means.dtype
        # Pose algebra in float64 (a float32 product is orthonormal only to ~1e-7, and the motion model
        # would amplify that from frame to frame); only the renderer's input is cast to the map's dtype.
        T_cw_init = se3_inverse(T_wc_init.to(torch.float64)).to(device=device)
        whole_map = gaussians
        start = self._frame_work(frame).start_view(whole_map, T_cw_init.to(dtype))
        gaussians = (start.subset if start is not None else
                     frustum_subset(gaussians, T_cw_init.to(dtype), frame.intrinsics, self.render_config))
        seen, iterations = None, 0
        if cfg.direct_iterations > 0:
            T_cw_init, seen, iterations = self._direct_alignment(gaussians, frame, T_cw_init, whole_map)
        rho = torch.zeros(3, device=device, dtype=dtype, requires_grad=True)
        phi = torch.zeros(3, device=device, dtype=dtype, requires_grad=True)
        groups = [{"params": [rho], "lr": cfg.lr_translation}, {"params": [phi], "lr": cfg.lr_rotation}]
        exposure = None
        if cfg.use_exposure:
            exposure = torch.zeros(2, device=device, dtype=dtype, requires_grad=True)
            groups.append({"params": [exposure], "lr": cfg.lr_rotation})
        optimizer = _pose_optimizer(cfg, groups)

        # The lowest full-resolution loss seen, its depth-pixel count, the valid-depth pixels the map renders there
        # (opacity >= coverage_opacity), and the pose (and exposure) it was seen at; the direct alignment's
        # renders count.
        best_loss, best_depth_pixels, best_covered, best_disagreeing = math.inf, 0, 0, 0
        best_step, full_steps = 0, 0  # the finest level's step that gave the best pose (0: the alignment's render)
        best = (torch.zeros(6, dtype=dtype, device=device), None)
        if seen is not None:
            best_loss, best_depth_pixels, best_covered = seen.loss, seen.depth_pixels, seen.covered
            best_disagreeing = seen.disagreeing
            xi_seen = se3_log(seen.T_cw @ se3_inverse(T_cw_init)).to(dtype)
            best = (xi_seen, None if exposure is None else torch.zeros_like(exposure.detach()))
        levels = self._levels(frame)
        # The finest level (tracking.resolution_scale) in render_mode is last; its steps alone judge the best pose
        # (tracking.coarse_mode_iterations may have moved its first steps into a level of their own before it).
        full = levels[-1]
        for level in levels:
            for i in range(level.iterations):
                xi = torch.cat([rho.detach(), phi.detach()])  # this step's twist, before the optimiser moves it
                step_render = self._step_render(gaussians, rho, phi, T_cw_init, level, exposure)
                loss, alpha = step_render.loss, step_render.alpha
                if not torch.isfinite(loss.total):
                    return self._failed(T_wc_init, iterations, "non_finite_loss", math.nan, 0.0)
                if level is full:
                    full_steps += 1
                if level is full and float(loss.total.detach()) < best_loss:
                    best_loss, best_depth_pixels = float(loss.total.detach()), loss.num_depth_pixels
                    best_step = full_steps
                    best_covered, best_disagreeing = self._coverage(step_render.depth, alpha, level)
                    best = (xi, None if exposure is None else exposure.detach().clone())
                if level is full and i == level.iterations - 1:
                    iterations += 1
                    break  # no render would judge a further step: its backward is skipped
                optimizer.zero_grad(set_to_none=True)
                step_render.backward()
                optimizer.step()
                iterations += 1
                step = float((torch.cat([rho.detach(), phi.detach()]) - xi).norm())
                if _converged(optimizer, [rho, phi], step, cfg.convergence_threshold):
                    break

        log.debug("frame %d: lowest tracking loss %.5f at gradient step %d of %d at the finest level", frame.index,
                  best_loss, best_step, full_steps)
        # The best pose's loss and valid-pixel count (seen when it was rendered) decide success.
        xi_best, exposure_best = best
        T_cw_best = se3_exp(xi_best.to(torch.float64)) @ T_cw_init
        valid_fraction = best_depth_pixels / max(1, full.depth.numel())
        map_coverage = best_covered / max(1, int(full.target_masks.depth.sum()))
        disagreement = best_disagreeing / best_covered if best_covered else math.nan
        final_loss = best_loss
        if not math.isfinite(final_loss):
            return self._failed(T_wc_init, iterations, "non_finite_loss", math.nan, valid_fraction)
        if valid_fraction < cfg.min_valid_fraction:
            return self._failed(T_wc_init, iterations, "too_few_valid_pixels", final_loss, valid_fraction)
        if running_loss is not None and final_loss > cfg.failure_loss_ratio * running_loss:
            return self._failed(T_wc_init, iterations, "loss_jump", final_loss, valid_fraction)
        T_wc = se3_inverse(T_cw_best.detach().to(torch.float64).cpu())
        exposure_out = torch.zeros(2) if exposure_best is None else exposure_best.detach().float().cpu()
        return TrackingResult(T_wc, exposure_out, final_loss, iterations, valid_fraction, True, "ok", map_coverage,
                              disagreement)

    @torch.no_grad()
    def best_start(
        self,
        gaussians: ActivatedGaussians,  # the frozen map (detached)
        frame: Frame,
        candidates: list[torch.Tensor],  # [4, 4] float64 start poses, the preferred first (e.g. the motion model's)
    ) -> int:
        """Index of the candidate start whose render at tracking's finest level explains the frame best (lowest
        loss, no exposure; a candidate seeing under ``min_valid_fraction`` of the pixels through the map loses).
        A later candidate replaces an earlier one only when its loss is lower by the fraction
        ``TrackingOptions.start_margin``: on gentle motion the motion model's start is already in the basin, and a
        feature pose a few millimetres off must not replace it on the noise of one render.

        One forward render per candidate: the features' pose and the motion model's are judged by the same
        objective that refinement then descends, so a consensus of wrong matches (repeated texture) cannot
        replace a better motion-model start.
        """
        if len(candidates) < 2:
            return 0
        work = self._frame_work(frame)
        level = work.levels[-1]
        device, dtype = gaussians.means.device, gaussians.means.dtype
        losses = []
        for T_wc in candidates:
            T_cw = se3_inverse(T_wc.to(torch.float64)).to(device=device, dtype=dtype)
            subset = frustum_subset(gaussians, T_cw, frame.intrinsics, self.render_config)
            out = render_view(subset, T_cw, level.intrinsics, self.render_config, mode=level.render_mode,
                              pose_only=True)
            loss = self._judged_loss(out, level)
            # tracking from this start takes the same subset, and the direct alignment's first render is this one
            work.starts.append(_StartView(gaussians, T_cw, subset, out, loss))
            valid = loss.num_depth_pixels / max(1, level.depth.numel())
            value = float(loss.total)
            losses.append(value if math.isfinite(value) and valid >= self.config.min_valid_fraction else math.inf)
        best = 0
        for i in range(1, len(candidates)):
            if losses[i] < (1.0 - self.config.start_margin) * losses[best]:
                best = i
        return best

    @staticmethod
    def _failed(T_wc_init: torch.Tensor, iterations: int, status: str, loss: float, valid_fraction: float) -> TrackingResult:
        return TrackingResult(T_wc_init.detach().to(torch.float64).cpu().clone(), torch.zeros(2), loss, iterations,
                              valid_fraction, False, status)


def _pose_optimizer(cfg: TrackingOptions, groups: list[dict]) -> "torch.optim.Optimizer | PoseRprop":
    """Adam, or Rprop (Riedmiller & Braun 1993) started at the configured rates and capped at
    ``rprop_max_step_ratio`` times them; the etas are Rprop's published 0.5 / 1.2."""
    if cfg.optimizer == "adam":
        return torch.optim.Adam(groups)
    if all(p.device.type == "cpu" for group in groups for p in group["params"]):
        return PoseRprop(groups, max_step_ratio=cfg.rprop_max_step_ratio, etas=(0.5, 1.2))
    for group in groups:
        group["step_sizes"] = (0.0, group["lr"] * cfg.rprop_max_step_ratio)
    return torch.optim.Rprop(groups, etas=(0.5, 1.2))


class PoseRprop:
    """Rprop for a pose's few parameters: ``torch.optim.Rprop``'s arithmetic (its single-tensor path) in numpy.

    Per coordinate: the step size grows by ``etas[1]`` while the gradient keeps its sign, shrinks by ``etas[0]``
    when it flips (and that step moves nothing), and stays within [0, lr * max_step_ratio]; the parameter moves
    by ``-sign(grad) * step size``. The same float32 operations in the same order as torch's Rprop, so the
    parameters and step sizes are bit-equal to it (tests/test_tracking.py); torch's per-step machinery (hooks,
    state dicts, a dozen tensor operations per parameter) cost 0.4 ms a step for six numbers.

    ``groups``: ``[{"params": [tensor], "lr": float}, ...]`` as for a torch optimizer; the parameters are CPU
    leaf tensors (on another device tracking takes torch's Rprop).
    """

    def __init__(self, groups: list[dict], *, max_step_ratio: float, etas: tuple[float, float] = (0.5, 1.2)):
        self.param_groups = groups
        self.params = [p for group in groups for p in group["params"]]
        for p in self.params:
            if p.device.type != "cpu" or not p.is_floating_point():
                raise ValueError(f"PoseRprop: floating-point CPU parameters, got {p.dtype} on {p.device}")
        lrs = [group["lr"] for group in groups for _ in group["params"]]
        dtypes = [p.detach().numpy().dtype for p in self.params]
        self.step_sizes = {p: np.full(p.shape, lr, dtype=t) for p, lr, t in zip(self.params, lrs, dtypes)}
        self._max_steps = {p: t.type(lr * max_step_ratio) for p, lr, t in zip(self.params, lrs, dtypes)}
        self._previous = {p: np.zeros(p.shape, dtype=t) for p, t in zip(self.params, dtypes)}
        self._etas = {t: (t.type(etas[0]), t.type(etas[1])) for t in set(dtypes)}

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        for p in self.params:
            if p.grad is None:
                continue
            grad = p.grad.detach().numpy()
            eta_minus, eta_plus = self._etas[grad.dtype]
            sign = np.sign(grad * self._previous[p])
            factor = sign.copy()  # NaN stays NaN, as in torch's masked assignments
            factor[sign > 0], factor[sign < 0], factor[sign == 0] = eta_plus, eta_minus, 1.0
            step_size = self.step_sizes[p]
            np.clip(step_size * factor, step_size.dtype.type(0.0), self._max_steps[p], out=step_size)
            grad = grad.copy()
            grad[factor == eta_minus] = 0.0  # a flipped sign moves nothing this step
            p.copy_(torch.from_numpy(p.detach().numpy() - np.sign(grad) * step_size))
            self._previous[p] = grad


def _converged(optimizer: "torch.optim.Optimizer | PoseRprop", pose_params: list[torch.Tensor],
               update_norm: float, threshold: float) -> bool:
    """Whether the pose has settled: its last update (se3 norm), or for Rprop the size of its next one.

    Rprop leaves a coordinate in place on the step its gradient changes sign, so a zero update there
    says nothing; the per-coordinate step sizes bound every later move and shrink as it converges.
    """
    if isinstance(optimizer, PoseRprop):
        sizes = [torch.from_numpy(optimizer.step_sizes[p]).flatten() for p in pose_params]  # [3] each
    elif isinstance(optimizer, torch.optim.Rprop):
        sizes = [optimizer.state[p]["step_size"].flatten() for p in pose_params]
    else:
        return update_norm < threshold
    return float(torch.cat(sizes).norm()) < threshold


def initial_result(T_wc: torch.Tensor) -> TrackingResult:
    """The first frame defines the map's frame: nothing to track against.  T_wc [4, 4] camera-to-world -> the
    result at that pose (float64 on CPU), status "initial"."""
    return TrackingResult(T_wc.to(torch.float64).cpu().clone(), torch.zeros(2), 0.0, 0, 1.0, True, "initial")


# ----------------------------------------------------------------------------- the step in the frame loop

def track_frame(tracker: Tracker, state: "SLAMState", frame: Frame, frames: "FrameCache",
                T_wc_first: torch.Tensor, frontend: Frontend | None = None,
                at_start: Callable[[torch.Tensor], Frame] | None = None) -> TrackingResult:
    """Track ``frame`` against the frozen map of ``state``; the first frame (or any frame while the map is
    empty) takes its pose from ``T_wc_first`` [4, 4] float64 or the start without tracking.

    The start: the feature front-end's pose against the newest tracked frame (:func:`frontend_start`) where
    the map renders it better than the motion model's prediction (:meth:`Tracker.best_start`), else the
    prediction. ``at_start(T_wc_start)``, where given, is the frame with its images re-timed by the motion to
    the start (:mod:`mipslam.sensor_sync`), which the refinement tracks. A frame whose tracking fails is matched
    to the newest keyframes (:func:`relocalise_keyframes`), then aligned to the previous frame
    (:func:`relocalise`). ``frames[index]`` is an earlier frame. The result's ``T_wc`` [4, 4] float64
    (camera-to-world) is projected onto SE(3) (:func:`~mipslam.geometry.nearest_rigid`).
    """
    previous = state.frames[-2:]
    if not previous:
        return initial_result(T_wc_first)
    prediction = constant_velocity_prediction(previous[-1].T_wc, previous[-1].T_wc_tracked,
                                              previous[-2].T_wc_tracked if len(previous) == 2 else None)
    start = frontend_start(frontend, state, frame, frames, prediction)
    if len(state.gaussian_map) == 0:
        return initial_result(start.T_wc)
    with torch.no_grad():  # a frozen map: no autograd graph over every Gaussian's activations
        detached = state.gaussian_map.activated().detached()
    candidates = [prediction]  # the render loss judges between the motion model's pose and the other one
    asks_dense = start.source != "features" and tracker.config.dense_start
    if start.source == "features":
        candidates.append(start.T_wc)
    elif asks_dense:
        aligned = dense_start(tracker.config, state, frame, frames, prediction)
        if aligned is not None:
            candidates.append(aligned)
    chosen = tracker.best_start(detached, frame, candidates)
    if asks_dense:
        outcome = ("failed its checks" if len(candidates) == 1 else
                   "taken" if chosen == 1 else "rejected by the render loss")
        log.debug("frame %d: features gave no start (%s); dense RGB-D start %s", frame.index, start.reason, outcome)
    T_wc_start = candidates[chosen]
    if at_start is not None:
        moved = at_start(T_wc_start)
        tracker.retimed(frame, moved)
        frame = moved
    result = tracker.track(detached, frame, T_wc_start, state.running_loss)
    result = relocalise_keyframes(tracker, frontend, state, frame, frames, detached, result)
    result = relocalise(tracker, state, frame, frames, detached, result)
    result = verify_pose(tracker, frontend, state, frame, frames, detached, result, prediction, T_wc_start)
    return replace(result, T_wc=nearest_rigid(result.T_wc))


def frontend_start(frontend: Frontend | None, state: "SLAMState", frame: Frame, frames: "FrameCache",
                   prediction: torch.Tensor) -> FrontendStart:
    """Tracking's start: the feature front-end against the newest tracked frame, or the motion model's
    ``prediction`` [4, 4] float64 (camera-to-world) when there is no front-end or no tracked frame."""
    reference = state.newest_tracked_frame()
    if frontend is None or reference is None:
        return Frontend.motion_model(prediction)
    return frontend.start_from(frame, reference.index, lambda: frames[reference.index], reference.T_wc, prediction)


def relocalise_keyframes(tracker: Tracker, frontend: Frontend | None, state: "SLAMState", frame: Frame,
                         frames: "FrameCache", gaussians: ActivatedGaussians, result: TrackingResult) -> TrackingResult:
    """A frame whose tracking failed is matched to the newest ``FeatureOptions.relocalise_keyframes`` keyframes
    (features + PnP) and tracked again from the best match; it stays failed (not mapped) when no keyframe
    agrees or the retry fails too."""
    if result.ok:
        return result
    start = match_newest_keyframes(frontend, state, frame, frames)
    if start is None:
        return result
    retry = tracker.track(gaussians, frame, start.T_wc, state.running_loss)
    if retry.ok:
        log.info("frame %d: relocalised against frame %d (%d feature inliers; tracking had failed: %s)",
                 frame.index, start.reference_index, start.inliers, result.status)
        return retry
    return result


def match_newest_keyframes(frontend: Frontend | None, state: "SLAMState", frame: Frame, frames: "FrameCache",
                           prediction: torch.Tensor | None = None) -> FrontendStart | None:
    """The feature front-end's best match (PnP) of ``frame`` against the newest
    ``FeatureOptions.relocalise_keyframes`` keyframes, guided by ``prediction`` [4, 4] (camera-to-world) where
    given; None without a front-end, a keyframe, or an agreeing match."""
    if frontend is None or not state.keyframe_frames:
        return None
    newest = [state.frames[p] for p in reversed(state.keyframe_frames)][: frontend.options.relocalise_keyframes]
    return frontend.relocalise(frame, [(frames[r.index], r.T_wc) for r in newest], prediction)


def relocalise(tracker: Tracker, state: "SLAMState", frame: Frame, frames: "FrameCache",
               gaussians: ActivatedGaussians, result: TrackingResult) -> TrackingResult:
    """Re-track a frame from a pose found by RGB-D alignment to the previous frame; returns the better result.

    Runs when the tracking loss stays above ``tracking.relocalise_loss_ratio`` times its running level
    (the camera jumped, was bumped, or frames were dropped: the motion model started tracking far from
    the truth and its small steps could not get there); the lower loss wins. Ratio 0 turns it off. The
    alignment is dense RGB-D odometry (Open3D's coarse-to-fine hybrid term, as loop verification uses),
    accepted up to ``TrackingOptions.relocalise_max_m`` / ``relocalise_max_deg`` from the tracked pose.
    """
    cfg = tracker.config
    running = state.running_loss
    ratio = cfg.relocalise_loss_ratio
    if (ratio <= 0 or running is None or result.status not in ("ok", "loss_jump") or not state.frames
            or result.loss <= ratio * running or not state.frames[-1].tracked):
        return result
    previous = state.frames[-1]
    aligned = align_to_frame(cfg, frames[previous.index], previous.T_wc, frame, result.T_wc)
    if aligned is None:
        return result
    retry = tracker.track(gaussians, frame, aligned, running)
    if retry.ok and (not result.ok or retry.loss < result.loss):
        log.info("frame %d: relocalised (tracking loss %.4f, %.1fx its running level; %.4f after an RGB-D "
                 "alignment to frame %d)", frame.index, result.loss, result.loss / running, retry.loss, previous.index)
        return retry
    return result


def disagreement_limit(cfg: TrackingOptions, running: float | None) -> float:
    """The depth disagreement above which a tracked pose is checked (:func:`verify_pose`): the larger of
    ``disagreement_floor`` and ``disagreement_ratio`` times the running level of tracked frames; infinite before
    the first (what is usual differs from camera to camera: 5 % of fr3_teddy's pixels, 0.1 % of a synthetic
    room's)."""
    if running is None:
        return math.inf
    return max(cfg.disagreement_floor, cfg.disagreement_ratio * running)


def verify_pose(tracker: Tracker, frontend: Frontend | None, state: "SLAMState", frame: Frame, frames: "FrameCache",
                gaussians: ActivatedGaussians, result: TrackingResult, prediction: torch.Tensor,
                T_wc_start: torch.Tensor) -> TrackingResult:
    """Check a tracked pose that the map's geometry or the motion disputes, by a wider search.

    Checked: a pose at which more of the map's depth disagrees with the frame's
    (``TrackingResult.depth_disagreement``) than :func:`disagreement_limit` allows, or one further from the motion
    model's ``prediction`` [4, 4] than ``motion_check_m`` / ``motion_check_deg``. The wider search tracks again
    with ``wide_search_levels`` more levels of direct alignment from the prediction, from tracking's start
    ``T_wc_start`` [4, 4] and from the tracked pose, and from the features' match to the newest keyframes and
    a dense RGB-D alignment to the newest tracked frame. Of the results within the disagreement limit the lowest
    tracking loss wins; when none is within it, the frame keeps the pose of least disagreement and is flagged
    ``depth_disagreement`` (not mapped, out of the running levels).

    Photometric alignment over repeated texture (blinds, checkers) can settle a period or more away, where the
    colour loss hardly rises: the depth of the surfaces around them does not follow (docs/tracking.md, "Checking a
    tracked pose").
    """
    cfg = tracker.config
    if not result.ok:
        return result
    limit = disagreement_limit(cfg, state.running_disagreement)
    moved_m, moved_deg = (float(v) for v in relative_motion(prediction, result.T_wc))
    disputed = result.depth_disagreement > limit  # NaN (nothing covered) is not
    jolted = moved_m > cfg.motion_check_m or moved_deg > cfg.motion_check_deg
    if not (disputed or jolted):
        return result
    wide = Tracker(replace(cfg, direct_levels=cfg.direct_levels + cfg.wide_search_levels), tracker.render_config)
    starts = [prediction] + ([] if torch.equal(T_wc_start, prediction) else [T_wc_start]) + [result.T_wc]
    retries = [(wide, start) for start in starts] if cfg.direct_iterations > 0 else []
    matched = match_newest_keyframes(frontend, state, frame, frames, result.T_wc)
    if matched is not None:
        retries.append((tracker, matched.T_wc))
    reference = state.newest_tracked_frame()
    if reference is not None:
        aligned = align_to_frame(cfg, frames[reference.index], reference.T_wc, frame, result.T_wc)
        if aligned is not None:
            retries.append((tracker, aligned))
    results = [result] + [r for r in (retracker.track(gaussians, frame, start, state.running_loss)
                                      for retracker, start in retries) if r.ok]
    agreeing = [r for r in results if not r.depth_disagreement > limit]
    if agreeing:
        best = min(agreeing, key=lambda r: r.loss)
        if best is not result:
            shift_m, shift_deg = (float(v) for v in relative_motion(result.T_wc, best.T_wc))
            log.info("frame %d: %s; a wider search moved it %.1f cm / %.1f deg (depth disagreement %.1f%% -> %.1f%%, "
                     "loss %.4f -> %.4f)", frame.index,
                     "tracked pose disputed by the map's depth" if disputed else "tracked pose far from the motion model's",
                     100 * shift_m, shift_deg, 100 * result.depth_disagreement, 100 * best.depth_disagreement,
                     result.loss, best.loss)
        return best
    best = min(results, key=lambda r: r.depth_disagreement)
    log.info("frame %d: flagged: the map's depth disagrees on %.1f%% of the pixels at the best pose found "
             "(limit %.1f%%); the frame is not mapped", frame.index, 100 * best.depth_disagreement, 100 * limit)
    return replace(best, ok=False, status="depth_disagreement")


def dense_start(cfg: TrackingOptions, state: "SLAMState", frame: Frame, frames: "FrameCache",
                prediction: torch.Tensor) -> torch.Tensor | None:
    """A start for a frame the features could not place (texture-poor or repeated texture, a large motion):
    the newest tracked frame aligned to it by dense RGB-D odometry from the motion model's ``prediction``
    [4, 4] float64 (camera-to-world). Returns T_wc [4, 4] float64, or None when the alignment fails its checks.
    :func:`track_frame` calls it only with ``TrackingOptions.dense_start`` on; :meth:`Tracker.best_start` then judges
    it against the prediction."""
    reference = state.newest_tracked_frame()
    if reference is None:
        return None
    return align_to_frame(cfg, frames[reference.index], reference.T_wc, frame, prediction)


def align_to_frame(cfg: TrackingOptions, reference: Frame, T_wc_reference: torch.Tensor, frame: Frame,
                   T_wc_guess: torch.Tensor) -> torch.Tensor | None:
    """``frame``'s pose T_wc [4, 4] float64 from Open3D's dense RGB-D odometry (coarse-to-fine hybrid term, as
    loop verification uses) against ``reference`` at ``T_wc_reference`` [4, 4], started at ``T_wc_guess`` [4, 4].
    None when Open3D is missing or the alignment fails its checks or moves further than
    ``TrackingOptions.relocalise_max_m`` / ``relocalise_max_deg`` from the guess."""
    T_wc_reference = T_wc_reference.to(torch.float64)
    options = RegistrationOptions(method="rgbd_odometry", pixel_stride=1, min_points=100,
                                  max_correction_m=cfg.relocalise_max_m, max_correction_deg=cfg.relocalise_max_deg)
    try:
        aligned = register_rgbd_odometry(reference.color, reference.depth, frame.color, frame.depth,
                                         frame.intrinsics, se3_inverse(T_wc_reference) @ T_wc_guess.to(torch.float64),
                                         options)
    except MipslamError as exc:  # Open3D unavailable: no dense pose
        log.debug("RGB-D alignment of frame %d skipped: %s", frame.index, exc)
        return None
    if not aligned.accepted:
        return None
    return T_wc_reference @ aligned.T_ij
