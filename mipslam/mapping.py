"""Mapping: grow, refine and prune the Gaussian map over a window of keyframes.

On each keyframe (docs/design.md "Losses" and "Model only what a scene requires"):

1. densify: render the map at the new keyframe; new Gaussians go only where the map does not
   explain it (rendered opacity below ``add_opacity_threshold`` or the map's surface far behind the
   measurement), one per selected pixel (every ``densify_pixel_stride``-th), sized from depth and the
   pixel footprint, within the ``max_gaussians`` cap, and not within ``add_min_distance_ratio`` of its
   std-dev from an existing centre;
2. optimise the map (and the window's keyframe poses, except the first keyframe, which fixes the
   gauge) for ``iterations`` Adam steps; step ``i`` uses the newest keyframe on even steps and a
   keyframe drawn with the run's generator from the others on odd steps. Loss per view:
   ``alpha_c |exposure(I) - I_gt| + (1 - alpha_c) |D - D_gt|`` (means over valid pixels)
   ``+ opacity_weight * mean(1 - A) + isotropy_weight * isotropy(scales) + lambda_freq * L_freq(I, I_gt)``
   (``A`` the rendered opacity over pixels with valid depth; ``L_freq``, where it moves the geometry
   (``freq_moves_geometry`` "always"), over pixels within ``FREQ_DEPTH_REACH_PX`` of a valid depth); with
   ``depth_normalise`` the depth term compares
   ``D / A`` and no longer raises opacity itself); each view renders the
   Gaussians that can reach it from its starting pose (``mipslam.rendering.FRUSTUM_MARGIN``), the isotropy term
   covers the whole map;
3. prune Gaussians with negligible opacity, non-finite values or an absurd size, and enforce the cap.

After the last frame, :func:`refine_map` fills the keyframes' depth holes (:meth:`Mapper.fill_holes`) and takes
``refine.passes`` passes of the refinement loss over all keyframes (mipslam/refinement.py; the pipeline's final
refinement).

The stage's steps in the frame loop read and update the :class:`~mipslam.state.SLAMState`:
:func:`map_keyframe` (a new keyframe), :func:`refine_after_correction` (after a loop correction) and
:func:`refine_map` (after the last frame). Poses are camera-to-world ``T_wc`` [4, 4] float64 (OpenCV
camera), images float32 on the map's device: colour [H, W, 3] in [0, 1], depth [H, W] metres (0 = none).
"""
from __future__ import annotations

import logging
import math
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Iterable, Literal

import torch

from mipslam.config import MappingConfig, RenderConfig, section_options
from mipslam.gaussians import (
    GaussianMap,
    GaussianOptimizer,
    cap_count_mask,
    cap_pixel_mask,
    densify_pixel_mask,
    distances_to_camera,
    far_from_existing,
    fill_depth_holes,
    gaussians_from_rgbd,
    prune_mask,
)
from mipslam.geometry import nearest_rigid
from mipslam.geometry.se3 import se3_exp, se3_inverse
from mipslam.losses.frequency import frequency_loss
from mipslam.losses.photometric import RGBDMasks, apply_affine_exposure, coverage_loss, rgbd_l1_loss, rgbd_masks
from mipslam.losses.regularizers import isotropy_loss
from mipslam.refinement import (KeyframeImage, KeyframeRefiner, RefineKeyframe, RefineOptions, final_refinement_steps,
                                image_loader, state_keyframes)
from mipslam.rendering import frustum_indices, render_view, view_sampling_rates
from mipslam.types import Intrinsics

# The final refinement fills a keyframe's missing depth up to this fraction of the image width from a measured pixel
# (Kinect-type sensors leave image borders and object edges without depth; 16 px at 320 px wide)
FILL_HOLES_WIDTH_RATIO = 0.05

if TYPE_CHECKING:
    from mipslam.datasets import FrameCache, RGBDSequence
    from mipslam.types import Frame
    from mipslam.state import FrameRecord, SLAMState

# Where the frequency term moves the geometry it reads only pixels within this many pixels of a valid depth
FREQ_DEPTH_REACH_PX = 2

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MappingView:
    """One keyframe as mapping sees it (tensors on the map's device, pose float64 on CPU).

    color [H, W, 3], depth [H, W] metres, T_wc [4, 4], exposure [2] (log_gain, bias, fixed in mapping)
    """

    keyframe_id: int
    color: torch.Tensor
    depth: torch.Tensor
    T_wc: torch.Tensor
    exposure: torch.Tensor
    intrinsics: Intrinsics
    optimize_pose: bool
    masks: RGBDMasks | None = None  # the loss masks of color/depth (:func:`rgbd_masks`); None: computed when used


@dataclass(frozen=True)
class MappingResult:
    """What one mapping call did.  refined_T_wc: (keyframe id, new T_wc [4, 4] float64) per optimised pose."""

    added: int
    pruned: int
    iterations: int
    initial_loss: float
    final_loss: float
    refined_T_wc: tuple[tuple[int, torch.Tensor], ...]


class KeyframeImages:
    """The images and loss masks of the last ``capacity`` keyframes mapping trained on, on the frames' device.

    Mapping revisits its window's keyframes on every keyframe; the run's frame cache holds the latest *frames*,
    so most of those keyframes would be read and resized from disk again (178 reads for 40 TUM frames instead of
    40: 7 % of the CPU time of a ``fast`` run). Readers are deterministic, so a cached keyframe is exactly the one
    a read would give.
    """

    def __init__(self, capacity: int, max_depth: float = 0.0):
        self.capacity, self.max_depth = capacity, max_depth
        self._entries: OrderedDict[int, tuple["Frame", RGBDMasks]] = OrderedDict()

    def get(self, frames: "FrameCache", index: int) -> tuple["Frame", RGBDMasks]:
        """Frame ``index`` (colour [H, W, 3], depth [H, W] metres) and its :func:`rgbd_masks`."""
        entry = self._entries.get(index)
        if entry is not None:
            self._entries.move_to_end(index)
            return entry
        frame = frames[index]
        entry = (frame, rgbd_masks(frame.color, frame.depth, max_depth=self.max_depth))
        if self.capacity > 0:
            self._entries[index] = entry
            while len(self._entries) > self.capacity:
                self._entries.popitem(last=False)
        return entry


@dataclass(frozen=True)
class MappingOptions:
    """Everything mapping reads: the ``mapping`` config section's keys (defaults there) and the stage's
    constants (defined here; evidence in docs/mapping.md and docs/bench.md). Built by :meth:`from_config`."""

    iterations: int = MappingConfig.iterations
    first_frame_iterations: int = MappingConfig.first_frame_iterations
    densify_pixel_stride: int = MappingConfig.densify_pixel_stride
    max_gaussians: int = MappingConfig.max_gaussians
    initial_scale_factor: float = MappingConfig.initial_scale_factor
    initial_opacity: float = MappingConfig.initial_opacity
    add_min_distance_ratio: float = MappingConfig.add_min_distance_ratio
    lr_poses: float = MappingConfig.lr_poses
    lambda_freq: float = MappingConfig.lambda_freq
    freq_moves_geometry: Literal["final", "always"] = MappingConfig.freq_moves_geometry
    # Adam rates of the map's parameters (GaussianOptimizer.from_config)
    lr_means: float = 1e-3
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_colors: float = 5e-3
    alpha_color: float = 0.5  # weight of the colour L1 against the depth L1
    isotropy_weight: float = 10.0
    freq_patch: int = 16  # the frequency loss's patch (px) and exponent
    freq_alpha: float = 1.0
    add_opacity_threshold: float = 0.5  # pixels the map renders below this opacity get new Gaussians ...
    add_depth_error_ratio: float = 10.0  # ... as do those whose depth error is above ratio * median error
    prune_opacity: float = 0.005
    prune_max_sigma_px: float = 50.0  # std-dev larger than this many pixels (seen from the keyframe) is absurd
    # Depth term on the alpha-normalised rendered depth D / max(A, depth_alpha_floor): where the map's
    # opacity A < 1 the raw D = sum T a z is minimised by Gaussians 1 / A - 1 too far (docs/mapping.md).
    depth_normalise: bool = False
    depth_alpha_floor: float = 0.5
    max_depth: float = 0.0  # metres; observed depth beyond it stays out of the depth term (0 = no limit)
    # Keyframe images (and loss masks) mapping keeps on the device, most recently used first, instead of reading
    # them from disk again on every revisit; 0 = none. 64 at 320x240 is about 80 MB (docs/mapping.md).
    keyframe_cache: int = 64
    # Weight of mean(1 - A) over pixels with valid depth (0 = off): depth_normalise needs it to keep the map opaque.
    opacity_weight: float = 0.0

    @classmethod
    def from_config(cls, section: MappingConfig) -> "MappingOptions":
        return section_options(cls, section)


def near_valid_depth(valid: torch.Tensor, reach_px: int) -> torch.Tensor:
    """Pixels within ``reach_px`` (Chebyshev distance) of a valid depth.  valid [H, W] bool -> [H, W] bool"""
    if reach_px <= 0:
        return valid
    size = 2 * reach_px + 1
    return torch.nn.functional.max_pool2d(valid[None, None].float(), size, stride=1, padding=reach_px)[0, 0] > 0


class Mapper:
    """Maps keyframes (its options and the render config section)."""

    def __init__(self, config: MappingOptions, render_config: RenderConfig):
        self.config = config
        self.render_config = render_config
        self.keyframe_images = KeyframeImages(config.keyframe_cache, config.max_depth)

    # ------------------------------------------------------------------ densify / prune

    @torch.no_grad()
    def densify(self, gmap: GaussianMap, optimizer: GaussianOptimizer, view: MappingView, frame_index: int) -> int:
        """Add Gaussians where the map does not explain ``view``; returns how many were added.

        The map is rendered at ``view.T_wc`` [4, 4] (camera-to-world, OpenCV camera); a selected pixel (u, v) with
        depth d metres becomes a Gaussian at ``T_wc K^-1 d (u, v, 1)`` (world, metres) with std-dev
        ``initial_scale_factor * stride * d / f`` metres. ``frame_index`` is recorded as its creation frame."""
        cfg = self.config
        if len(gmap) == 0:
            mask = view.depth > 0
        else:
            out = render_view(gmap.activated(), se3_inverse(view.T_wc).to(gmap.dtype), view.intrinsics,
                              self.render_config, normalized_depth=True)
            mask = densify_pixel_mask(out.alpha, out.depth_normalized, view.depth,
                                      opacity_threshold=cfg.add_opacity_threshold,
                                      depth_error_ratio=cfg.add_depth_error_ratio)
        return self._add_at_pixels(gmap, optimizer, view, view.depth, mask, frame_index)

    @torch.no_grad()
    def fill_holes(self, gmap: GaussianMap, optimizer: GaussianOptimizer, view: MappingView, frame_index: int) -> int:
        """Add Gaussians where ``view`` has colour but no depth and the map renders it transparent, at the depth
        grown from the measured pixels beside them (:func:`fill_depth_holes`, up to ``FILL_HOLES_WIDTH_RATIO`` of the
        image width away);
        returns how many were added. The final refinement calls it: tracking never sees these Gaussians, whose
        depth is a guess."""
        cfg = self.config
        if len(gmap) == 0:
            return 0
        depth = fill_depth_holes(view.depth, max(1, round(FILL_HOLES_WIDTH_RATIO * view.depth.shape[1])))
        out = render_view(gmap.activated(), se3_inverse(view.T_wc).to(gmap.dtype), view.intrinsics,
                          self.render_config)
        mask = (view.depth <= 0) & (depth > 0) & (out.alpha < cfg.add_opacity_threshold)
        return self._add_at_pixels(gmap, optimizer, view, depth, mask, frame_index)

    def _add_at_pixels(self, gmap: GaussianMap, optimizer: GaussianOptimizer, view: MappingView,
                       depth: torch.Tensor, mask: torch.Tensor, frame_index: int) -> int:
        """One Gaussian per pixel of ``mask`` [H, W] on the ``densify_pixel_stride`` grid at ``depth`` [H, W]
        metres, within the ``max_gaussians`` cap and away from existing centres (``add_min_distance_ratio``)."""
        cfg = self.config
        budget = cfg.max_gaussians - len(gmap)
        if budget <= 0:
            return 0
        stride = cfg.densify_pixel_stride
        grid = torch.zeros_like(mask)
        grid[::stride, ::stride] = True
        mask = cap_pixel_mask(mask & grid, budget)
        new = gaussians_from_rgbd(view.color, depth, view.intrinsics.matrix(gmap.dtype, gmap.device),
                                  view.T_wc.to(gmap.dtype), mask, initial_opacity=cfg.initial_opacity,
                                  anchor_keyframe=view.keyframe_id, created_frame=frame_index, pixel_stride=stride,
                                  scale_factor=cfg.initial_scale_factor)
        if cfg.add_min_distance_ratio > 0 and len(gmap) > 0:
            new = new.subset(far_from_existing(new.means, new.log_scales[:, 0].exp(), gmap.means.detach(),
                                               cfg.add_min_distance_ratio))
        gmap.add(new, optimizer)
        return len(new)

    @torch.no_grad()
    def observe_sampling_rates(self, gmap: GaussianMap, views: Iterable[MappingView]) -> None:
        """Raise each Gaussian's ``max_sampling_rate`` [N] (px/m) to its rate in every view that trains it (the
        Mip-Splatting 3D filter's training cameras). :meth:`map_keyframe` calls it when ``render.filter_3d``
        is on; otherwise each Gaussian keeps the rate of the view that created it."""
        for view in views:
            T_cw = se3_inverse(view.T_wc).to(gmap.dtype)
            gmap.observe_sampling_rates(view_sampling_rates(gmap.means, T_cw, view.intrinsics))

    @torch.no_grad()
    def prune(self, gmap: GaussianMap, optimizer: GaussianOptimizer, view: MappingView) -> int:
        """Remove negligible, non-finite or absurdly large Gaussians and enforce the count cap; returns how many.

        Sizes are judged in pixels as seen from ``view.T_wc`` [4, 4] (std-dev metres x focal px / distance m)."""
        if len(gmap) == 0:
            return 0
        g = gmap.activated()
        remove = prune_mask(g.opacities, g.scales, distances_to_camera(g.means, view.T_wc.to(g.means)),
                            focal_px=max(view.intrinsics.fx, view.intrinsics.fy), min_opacity=self.config.prune_opacity,
                            max_sigma_px=self.config.prune_max_sigma_px, means=g.means)
        removed = gmap.remove(remove, optimizer)
        removed += gmap.remove(cap_count_mask(torch.sigmoid(gmap.opacity_logits), self.config.max_gaussians), optimizer)
        return removed

    # ------------------------------------------------------------------ optimisation

    def view_loss(self, gmap: GaussianMap, view: MappingView, T_cw: torch.Tensor,
                  masks: RGBDMasks | None = None, rows: torch.Tensor | None = None,
                  frequency_mask: torch.Tensor | None = None) -> torch.Tensor:
        """The mapping loss of one view (module docstring), differentiable w.r.t. the map and ``T_cw`` [4, 4]
        (world-to-camera, the map's dtype and device). Returns a scalar tensor.

        What :meth:`optimize` computes once per view and passes in: ``masks``, the view's
        :func:`rgbd_masks` (they depend on the targets alone), ``rows`` [M] int64, the Gaussians
        the view can draw (:func:`frustum_indices`; the others would get zero gradients anyway), and
        ``frequency_mask`` [H, W] bool, the pixels the frequency term reads (:meth:`frequency_mask`).
        """
        cfg = self.config
        g = gmap.activated(rows)
        appearance = cfg.lambda_freq > 0 and cfg.freq_moves_geometry != "always"
        out = render_view(g, T_cw, view.intrinsics, self.render_config, appearance_color=appearance)
        color = apply_affine_exposure(out.color, view.exposure[0], view.exposure[1])
        if masks is None:
            masks = view.masks if view.masks is not None else rgbd_masks(view.color, view.depth,
                                                                          max_depth=cfg.max_depth)
        loss = rgbd_l1_loss(color, out.depth, view.color, view.depth, alpha_color=cfg.alpha_color, masks=masks,
                            depth_alpha=out.alpha if cfg.depth_normalise else None,
                            depth_alpha_floor=cfg.depth_alpha_floor).total
        if cfg.opacity_weight > 0:  # the sensor saw a surface at these pixels: the map should be opaque there
            loss = loss + cfg.opacity_weight * coverage_loss(out.alpha, masks.depth)
        if cfg.isotropy_weight > 0:  # over the whole map, seen or not
            scales = g.scales if rows is None else torch.exp(gmap.log_scales)
            loss = loss + cfg.isotropy_weight * isotropy_loss(scales)
        if cfg.lambda_freq > 0:
            if appearance:  # the same values, whose gradient reaches the colours alone (MappingConfig)
                color = apply_affine_exposure(out.color_appearance, view.exposure[0], view.exposure[1])
            if frequency_mask is None:
                frequency_mask = self.frequency_mask(masks)
            loss = loss + cfg.lambda_freq * frequency_loss(color, view.color, patch_size=cfg.freq_patch,
                                                           alpha=cfg.freq_alpha, mask=frequency_mask)
        return loss

    def optimize(self, gmap: GaussianMap, optimizer: GaussianOptimizer, views: list[MappingView], iterations: int,
                 generator: torch.Generator) -> tuple[float, float, tuple[tuple[int, torch.Tensor], ...]]:
        """Adam steps over ``views`` (newest first); returns (first loss, last loss, refined poses).

        Step i uses ``views[0]`` on even steps and a view drawn with ``generator`` from the others on odd ones.
        A view with ``optimize_pose`` gets a left increment ``T_cw = exp(xi) T_cw0`` (xi [6] = [rho m, phi rad],
        camera frame); refined poses come back as (keyframe id, T_wc [4, 4] float64 on CPU)."""
        device, dtype = gmap.device, gmap.dtype
        T_cw_init = [se3_inverse(v.T_wc).to(device=device, dtype=dtype) for v in views]
        pose_deltas = {i: torch.zeros(6, device=device, dtype=dtype, requires_grad=True)
                       for i, v in enumerate(views) if v.optimize_pose and self.config.lr_poses > 0}
        pose_optimizer = torch.optim.Adam(list(pose_deltas.values()), lr=self.config.lr_poses) if pose_deltas else None
        first = last = math.nan
        inputs: dict[int, tuple[RGBDMasks, torch.Tensor | None, torch.Tensor | None]] = {}  # per view, once
        for step in range(iterations):
            if step % 2 == 0 or len(views) == 1:
                index = 0
            else:
                index = 1 + int(torch.randint(len(views) - 1, (1,), generator=generator))
            T_cw = T_cw_init[index]
            if index in pose_deltas:
                T_cw = se3_exp(pose_deltas[index]) @ T_cw
            if index not in inputs:
                inputs[index] = self._view_inputs(gmap, views[index], T_cw_init[index])
            loss = self.view_loss(gmap, views[index], T_cw, *inputs[index])
            if not torch.isfinite(loss):
                break  # never step on a non-finite loss: the map keeps its last finite state
            optimizer.zero_grad()
            if pose_optimizer is not None:
                pose_optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            if pose_optimizer is not None:
                pose_optimizer.step()
            last = float(loss.detach())
            first = last if math.isnan(first) else first
        refined = tuple(
            (views[i].keyframe_id, se3_inverse((se3_exp(delta.detach()) @ T_cw_init[i]).to(torch.float64).cpu()))
            for i, delta in pose_deltas.items()
        )
        return first, last, refined

    def _view_inputs(self, gmap: GaussianMap, view: MappingView,
                     T_cw: torch.Tensor) -> tuple[RGBDMasks, torch.Tensor | None, torch.Tensor | None]:
        """A view's loss masks, the rows of the Gaussians it can draw from ``T_cw`` [4, 4] (None: all) and the
        pixels its frequency term reads (None: no frequency term)."""
        seen = frustum_indices(gmap.means, torch.exp(gmap.log_scales.detach()), T_cw, view.intrinsics,
                               self.render_config)
        masks = view.masks
        if masks is None:
            masks = rgbd_masks(view.color, view.depth, max_depth=self.config.max_depth)
        frequency_mask = self.frequency_mask(masks) if self.config.lambda_freq > 0 else None
        return masks, None if len(seen) == len(gmap) else seen, frequency_mask

    def frequency_mask(self, masks: RGBDMasks) -> torch.Tensor:
        """The pixels a view's frequency term reads, from its loss ``masks``: its colour pixels, and where the term
        moves the geometry (``freq_moves_geometry`` "always") only those within ``FREQ_DEPTH_REACH_PX`` of a valid
        depth: a region without any (a border the depth camera does not see) holds no geometry of the view to
        sharpen, and the term would pull the map towards its colour; a dropout inside a surface stays in.
        -> [H, W] bool"""
        if self.config.freq_moves_geometry != "always":
            return masks.color
        return masks.color & near_valid_depth(masks.depth, FREQ_DEPTH_REACH_PX)

    def map_keyframe(self, gmap: GaussianMap, optimizer: GaussianOptimizer, views: list[MappingView], *,
                     iterations: int, generator: torch.Generator, frame_index: int) -> MappingResult:
        """Densify at the newest view (``views[0]``), optimise over all views for ``iterations`` steps, prune.
        Views carry images on the map's device (colour [H, W, 3], depth [H, W] metres) and T_wc [4, 4] float64."""
        added = self.densify(gmap, optimizer, views[0], frame_index)
        if self.render_config.filter_3d:  # 3-4 % of a balanced keyframe's mapping: only when it is used
            self.observe_sampling_rates(gmap, views)
        first, last, refined = self.optimize(gmap, optimizer, views, iterations, generator)
        pruned = self.prune(gmap, optimizer, views[0])
        return MappingResult(added, pruned, iterations, first, last, refined)


# ----------------------------------------------------------------------------- the steps in the frame loop

def mapping_view(state: "SLAMState", frames: "FrameCache", keyframe_id: int,
                 images: KeyframeImages | None = None) -> MappingView:
    """Keyframe ``keyframe_id`` as mapping sees it: its image, its current pose and its exposure (keyframe 0's
    pose stays fixed: it fixes the gauge). ``images``: the mapper's keyframe cache (None reads ``frames``)."""
    record = state.keyframe_record(keyframe_id)
    if images is None:
        frame, masks = frames[record.index], None
    else:
        frame, masks = images.get(frames, record.index)
    return MappingView(keyframe_id, frame.color, frame.depth, record.T_wc, record.exposure.to(frame.color.device),
                       frame.intrinsics, optimize_pose=keyframe_id != 0, masks=masks)


def map_keyframe(mapper: Mapper, state: "SLAMState", frames: "FrameCache", record: "FrameRecord",
                 keyframe_ids: tuple[int, ...]) -> MappingResult:
    """Map the new keyframe ``record`` over the keyframes ``keyframe_ids`` (the window, newest first, then the
    random past ones; :func:`mipslam.keyframes.insert_keyframe`), and take the refined poses (projected onto
    SE(3)) into ``state``. ``mapping.first_frame_iterations`` steps on the first keyframe, ``iterations`` after."""
    views = [mapping_view(state, frames, kf, mapper.keyframe_images) for kf in keyframe_ids]
    cfg = mapper.config
    iterations = cfg.first_frame_iterations if record.keyframe_id == 0 else cfg.iterations
    result = mapper.map_keyframe(state.gaussian_map, state.optimizer, views, iterations=iterations,
                                 generator=state.generator, frame_index=record.index)
    for keyframe_id, T_wc in result.refined_T_wc:
        state.set_keyframe_pose(keyframe_id, nearest_rigid(T_wc))
    return result


def refine_after_correction(mapper: Mapper, state: "SLAMState", frames: "FrameCache", keyframe_ids: list[int],
                            iterations: int) -> int:
    """``iterations`` mapping steps over ``keyframe_ids`` at their corrected poses (held fixed); returns the steps.

    Moving Gaussians with their anchors cannot undo what mapping did before a loop correction: old
    Gaussians re-fitted from drifted views sit where those views put them. A few steps of the mapping loss
    over the loop's keyframes (no densification, no pose updates, so the pose-graph solution stands)
    reconcile the map with the corrected poses.
    """
    if iterations == 0 or len(state.gaussian_map) == 0:
        return 0
    views = [replace(mapping_view(state, frames, k, mapper.keyframe_images), optimize_pose=False)
             for k in keyframe_ids]
    mapper.optimize(state.gaussian_map, state.optimizer, views, iterations, state.generator)
    return iterations


def refine_map(mapper: Mapper, state: "SLAMState", frames: "FrameCache", options: RefineOptions,
               passes: int, images: "RGBDSequence | None" = None) -> int:
    """The final refinement (mipslam/refinement.py) after the last frame: ``passes`` passes of the refinement loss
    (:func:`final_refinement_steps`), one keyframe per step, every keyframe once per pass in an order drawn from
    the run's generator, on the keyframes' images as the camera recorded them, read from ``images`` (any
    resolution; None: the frames the run kept, ``frames``) after :meth:`Mapper.fill_holes`.
    Keyframe poses move only with ``options.lr_poses`` > 0; every frame then follows its keyframes
    (:meth:`SLAMState.correct_keyframe_poses`, the map held where the refinement left it). The means' learning rate
    decays over the steps (``MEANS_LR_FINAL_RATIO``). Returns the steps taken
    (fewer if a loss turned non-finite; the map then keeps its last finite state)."""
    count = len(state.keyframe_frames)
    iterations = final_refinement_steps(passes, count)
    if iterations == 0:
        return 0
    keyframes = state_keyframes(state)
    # the images as the camera recorded them: what a view of the map is compared with (a rolling shutter's rows
    # moved to one instant for tracking are a resampled image, and not what the camera saw)
    read = image_loader((frames if images is None else images).__getitem__, state.gaussian_map.device)
    loaded: dict[int, KeyframeImage] = {}  # read once for the hole filling, handed on to the refiner's cache

    filled = 0
    for keyframe in keyframes:
        image = loaded[keyframe.keyframe_id] = read(keyframe)
        filled += mapper.fill_holes(state.gaussian_map, state.optimizer, MappingView(
            keyframe.keyframe_id, image.color, image.depth, keyframe.T_wc, keyframe.exposure, image.intrinsics,
            optimize_pose=False), keyframe.frame_index)

    def load(keyframe: RefineKeyframe) -> KeyframeImage:
        image = loaded.pop(keyframe.keyframe_id, None)
        return read(keyframe) if image is None else image

    refiner = KeyframeRefiner(state.gaussian_map, state.optimizer, keyframes, load, options, mapper.render_config,
                              state.generator, cache_size=max(count, mapper.config.keyframe_cache),
                              decay_steps=iterations)
    losses = refiner.run(iterations)
    refiner.restore_learning_rates()
    refined = refiner.refined_poses()
    if refined:
        poses = state.keyframe_poses()
        for keyframe_id, T_wc in refined:
            poses[keyframe_id] = nearest_rigid(T_wc)
        state.correct_keyframe_poses(poses, move_map=False)
    if losses:
        n = min(count, len(losses))
        log.info("final refinement: %d Gaussians where keyframes had no depth, %d steps over %d keyframes; mean loss "
                 "%.4f over the first %d steps, %.4f over the last %d", filled, len(losses), count,
                 sum(losses[:n]) / n, n, sum(losses[-n:]) / n, n)
    return len(losses)
