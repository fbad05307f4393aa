"""Map refinement over every keyframe: the final refinement of a run and ``mipslam refine``.

Once the last frame is tracked nothing reads the map's geometry for tracking any more, so the refinement's loss may
favour appearance over the depth term that mapping keeps strong for tracking (docs/mapping.md, "The final
refinement"). One step renders one keyframe at its pose and takes an Adam step on the map (and, with
``lr_poses > 0``, on that keyframe's pose; keyframe 0 fixes the gauge):

    L = alpha_c |exposure(I) - I_gt|_1 + (1 - alpha_c) |D - D_gt|_1 + w_ssim (1 - SSIM(exposure(I), I_gt))
        + lambda_freq L_freq(exposure(I), I_gt) + w_iso isotropy(scales)

(the L1 + D-SSIM photometric term of 3D Gaussian Splatting, Kerbl et al. 2023, next to this project's depth and
frequency terms; means of the L1 terms over valid pixels as in mapping). The keyframes are visited in passes, each
pass in an order drawn from the run's generator, so every keyframe gets the same number of steps. Poses
``T_wc`` [4, 4] are camera-to-world (OpenCV camera) float64; images are float32 on the map's device, colour
[H, W, 3] in [0, 1] and depth [H, W] metres (0 = none); exposure [2] = (log_gain, bias), fixed.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import torch

from mipslam.config import Config, RenderConfig
from mipslam.gaussians import GaussianMap, GaussianOptimizer, GaussianParameters
from mipslam.geometry.se3 import quat_wxyz_to_rotmat, se3_exp, se3_inverse
from mipslam.losses.frequency import frequency_loss
from mipslam.losses.photometric import RGBDMasks, apply_affine_exposure, rgbd_l1_loss, rgbd_masks
from mipslam.losses.regularizers import isotropy_loss
from mipslam.losses.structural import SSIMTargetCache, ssim_loss
from mipslam.render import RenderOutput
from mipslam.rendering import frustum_indices, render_view
from mipslam.types import Intrinsics

SPLIT_SHRINK = 1.6  # a split Gaussian's two halves take 1/1.6 of its std-devs (3D Gaussian Splatting)


@dataclass(frozen=True)
class RefineOptions:
    """The refinement loss and what it may move (module docstring).

    alpha_color      weight of the colour L1 against the depth L1 (mapping keeps depth strong for tracking)
    ssim_weight      weight of 1 - SSIM (3DGS: 0.2)
    isotropy_weight  weight of the isotropy regulariser (metres): thin structures need elongated Gaussians
    lambda_freq      weight of the frequency-domain loss (mapping.lambda_freq; docs/design.md "Losses"); freq_patch px,
                     freq_alpha its focal exponent
    lr_poses         Adam rate of the keyframe poses (m, rad per step); 0 keeps them fixed
    max_depth        metres; observed depth beyond it leaves the depth term (0 = no limit)
    densify_grad     gradient-driven densification (3D Gaussian Splatting's clone and split): every
                     ``densify_every`` steps, each Gaussian whose mean view-space gradient ``|dL/d mean2d|`` in
                     normalised device units (pixels x (W/2, H/2), so resolution does not change it; 3DGS's 2e-4)
                     exceeds this is cloned (std-dev at most ``split_sigma_px`` px in the views that saw it) or
                     split in two at 1/1.6 of its size (larger); 0 = off
    split_sigma_px   the std-dev (px, mean over the views) above which a selected Gaussian is split, not cloned
    prune_opacity    at each densification, Gaussians below this opacity are removed
    max_gaussians    densification never grows the map beyond this many Gaussians
    """

    alpha_color: float = 0.9
    ssim_weight: float = 0.2
    isotropy_weight: float = 0.0
    lambda_freq: float = 0.0
    freq_patch: int = 16
    freq_alpha: float = 1.0
    lr_poses: float = 0.0
    max_depth: float = 0.0
    densify_grad: float = 0.0
    densify_every: int = 100
    split_sigma_px: float = 2.0
    prune_opacity: float = 0.005
    max_gaussians: int = 200_000

    def __post_init__(self):
        problems = [name for name, ok in (("alpha_color", 0 <= self.alpha_color <= 1),
                                          ("ssim_weight", self.ssim_weight >= 0),
                                          ("isotropy_weight", self.isotropy_weight >= 0),
                                          ("lambda_freq", self.lambda_freq >= 0), ("freq_patch", self.freq_patch >= 2),
                                          ("lr_poses", self.lr_poses >= 0), ("max_depth", self.max_depth >= 0),
                                          ("densify_grad", self.densify_grad >= 0),
                                          ("densify_every", self.densify_every >= 1),
                                          ("split_sigma_px", self.split_sigma_px > 0),
                                          ("prune_opacity", 0 <= self.prune_opacity < 1),
                                          ("max_gaussians", self.max_gaussians >= 1))
                    if not ok]
        if problems:
            raise ValueError(f"RefineOptions: {', '.join(problems)} out of range")


@dataclass(frozen=True)
class RefineKeyframe:
    """One keyframe to refine over: its id, the sequence index of its frame, its pose T_wc [4, 4] float64 and
    exposure [2] (log_gain, bias)."""

    keyframe_id: int
    frame_index: int
    T_wc: torch.Tensor
    exposure: torch.Tensor


@dataclass(frozen=True)
class KeyframeImage:
    """A keyframe's images at the refinement's resolution: colour [H, W, 3], depth [H, W] metres, and their
    intrinsics."""

    color: torch.Tensor
    depth: torch.Tensor
    intrinsics: Intrinsics


class KeyframeRefiner:
    """Steps of the refinement loss over ``keyframes`` (module docstring).

    ``load(keyframe)`` gives a keyframe's :class:`KeyframeImage`; the last ``cache_size`` are kept with their loss
    masks (a pass visits every keyframe once, so a cache of all keyframes reads each image once per run).
    ``generator`` draws the order of each pass. The map and its optimizer are changed in place.
    """

    def __init__(self, gmap: GaussianMap, optimizer: GaussianOptimizer, keyframes: Sequence[RefineKeyframe],
                 load: Callable[[RefineKeyframe], KeyframeImage], options: RefineOptions,
                 render_config: RenderConfig, generator: torch.Generator, *, cache_size: int = 64):
        if not keyframes:
            raise ValueError("KeyframeRefiner needs at least one keyframe")
        self.map, self.optimizer, self.keyframes = gmap, optimizer, list(keyframes)
        self.load, self.options, self.render_config, self.generator = load, options, render_config, generator
        self.cache_size = cache_size
        self.steps = 0
        self._pending: list[int] = []  # positions in self.keyframes still to visit in this pass
        self._images: OrderedDict[int, tuple[KeyframeImage, RGBDMasks]] = OrderedDict()
        self._ssim_targets = SSIMTargetCache(max_entries=max(1, cache_size))  # the keyframes' blurred moments
        device, dtype = gmap.device, gmap.dtype
        optimise_poses = options.lr_poses > 0
        # left increments T_cw = exp(xi) T_cw0, xi [K, 6] = [rho m, phi rad] in the camera frame
        self.pose_deltas = torch.zeros(len(self.keyframes), 6, device=device, dtype=dtype,
                                       requires_grad=optimise_poses)
        self._pose_optimizer = torch.optim.Adam([self.pose_deltas], lr=options.lr_poses) if optimise_poses else None
        self._T_cw = [se3_inverse(k.T_wc.to(torch.float64)).to(device=device, dtype=dtype) for k in self.keyframes]
        self.densified = self.pruned = 0
        self._reset_gradient_statistics()

    # ------------------------------------------------------------------ queries

    def T_wc(self, position: int) -> torch.Tensor:
        """The refined pose of ``self.keyframes[position]``.  -> [4, 4] float64 on CPU"""
        delta = self.pose_deltas[position].detach().to(device="cpu", dtype=torch.float64)
        T_wc = self.keyframes[position].T_wc.to(torch.float64).cpu()
        if not bool(delta.abs().max() > 0):
            return T_wc.clone()
        return se3_inverse(se3_exp(delta) @ se3_inverse(T_wc))

    def refined_poses(self) -> list[tuple[int, torch.Tensor]]:
        """(keyframe id, T_wc [4, 4] float64) of every keyframe whose pose moved."""
        if self._pose_optimizer is None:
            return []
        return [(k.keyframe_id, self.T_wc(i)) for i, k in enumerate(self.keyframes)
                if bool(self.pose_deltas[i].detach().abs().max() > 0)]

    # ------------------------------------------------------------------ steps

    def run(self, steps: int, should_stop: Callable[[], bool] | None = None) -> list[float]:
        """Up to ``steps`` steps; stops early at a non-finite loss (the map keeps its last finite state) or when
        ``should_stop()`` says so. Returns the loss of each step taken."""
        losses = []
        for _ in range(steps):
            if should_stop is not None and should_stop():
                break
            loss = self.step()
            if loss is None:
                break
            losses.append(loss)
        return losses

    def step(self) -> float | None:
        """One step on the next keyframe of the pass; returns its loss, or None when the loss was not finite
        (no step taken)."""
        position = self._next_position()
        image, masks = self._image(position)
        T_cw = self._T_cw[position]
        if self._pose_optimizer is not None and self.keyframes[position].keyframe_id != 0:
            T_cw = se3_exp(self.pose_deltas[position]) @ T_cw
        exposure = self.keyframes[position].exposure.to(self.map.device)
        rows = self._frustum_rows(position, image.intrinsics)
        loss, out = self.loss(image, masks, T_cw, exposure, rows, keep_view_gradient=self.options.densify_grad > 0)
        if not torch.isfinite(loss):
            return None
        self.optimizer.zero_grad()
        if self._pose_optimizer is not None:
            self._pose_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.options.densify_grad > 0:
            self._accumulate_view_gradients(out, rows, image.intrinsics)
        self.optimizer.step()
        if self._pose_optimizer is not None:
            self._pose_optimizer.step()
        self.steps += 1
        if self.options.densify_grad > 0 and self.steps % self.options.densify_every == 0:
            self.densify_and_prune()
        return float(loss.detach())

    def loss(self, image: KeyframeImage, masks: RGBDMasks, T_cw: torch.Tensor, exposure: torch.Tensor,
             rows: torch.Tensor | None, *, keep_view_gradient: bool = False) -> tuple[torch.Tensor, RenderOutput]:
        """The refinement loss of one keyframe (module docstring) rendered from ``T_cw`` [4, 4] (world-to-camera)
        with the Gaussians ``rows`` [M] int64 (None: all): (scalar tensor, the render). ``keep_view_gradient``:
        the render's ``means2d`` keeps its gradient after backward (densification)."""
        cfg = self.options
        g = self.map.activated(rows)
        out = render_view(g, T_cw, image.intrinsics, self.render_config)
        if keep_view_gradient:
            out.means2d.retain_grad()
        color = apply_affine_exposure(out.color, exposure[0], exposure[1])  # [H, W, 3]
        loss = rgbd_l1_loss(color, out.depth, image.color, image.depth, alpha_color=cfg.alpha_color,
                            masks=masks).total
        if cfg.ssim_weight > 0:
            loss = loss + cfg.ssim_weight * ssim_loss(color, image.color, cache=self._ssim_targets)
        if cfg.lambda_freq > 0:
            loss = loss + cfg.lambda_freq * frequency_loss(color, image.color, patch_size=cfg.freq_patch,
                                                           alpha=cfg.freq_alpha, mask=masks.color)
        if cfg.isotropy_weight > 0:
            loss = loss + cfg.isotropy_weight * isotropy_loss(g.scales)
        return loss, out

    # ------------------------------------------------------------------ densification (3D Gaussian Splatting)

    def _reset_gradient_statistics(self) -> None:
        """Per Gaussian [N] float64: summed view-space gradient norm (NDC units), summed std-dev in px and the
        number of views that drew it, since the last densification."""
        size, device = len(self.map), self.map.device
        self._gradient_sum = torch.zeros(size, dtype=torch.float64, device=device)
        self._sigma_sum = torch.zeros(size, dtype=torch.float64, device=device)
        self._views = torch.zeros(size, dtype=torch.float64, device=device)

    @torch.no_grad()
    def _accumulate_view_gradients(self, out: RenderOutput, rows: torch.Tensor | None, intrinsics: Intrinsics) -> None:
        grad = out.means2d.grad  # [M, 2] dL/d(pixel)
        if grad is None:
            return
        ndc = grad.to(torch.float64) * grad.new_tensor([intrinsics.width / 2.0, intrinsics.height / 2.0],
                                                       dtype=torch.float64)
        visible = out.visible
        norm = torch.where(visible, ndc.norm(dim=-1), torch.zeros_like(ndc[:, 0]))
        sigma = torch.where(visible, out.radii.to(torch.float64) / self.render_config.eaa_k_sigma,
                            torch.zeros_like(norm))
        index = rows if rows is not None else torch.arange(len(self.map), device=norm.device)
        self._gradient_sum.index_add_(0, index, norm)
        self._sigma_sum.index_add_(0, index, sigma)
        self._views.index_add_(0, index, visible.to(torch.float64))

    @torch.no_grad()
    def densify_and_prune(self) -> tuple[int, int]:
        """Clone or split the Gaussians whose mean view-space gradient exceeds ``densify_grad`` (within
        ``max_gaussians``, the largest gradients first), then remove those below ``prune_opacity``. Returns
        (added, removed) and resets the gradient statistics."""
        cfg, gmap = self.options, self.map
        seen = self._views > 0
        mean_gradient = torch.where(seen, self._gradient_sum / self._views.clamp_min(1), torch.zeros_like(self._views))
        selected = seen & (mean_gradient > cfg.densify_grad)
        budget = cfg.max_gaussians - len(gmap)
        chosen = torch.nonzero(selected).squeeze(1)
        large = (self._sigma_sum / self._views.clamp_min(1)) > cfg.split_sigma_px
        # a split adds one Gaussian net, a clone one: keep the strongest gradients within the budget
        if len(chosen) > max(0, budget):
            order = torch.argsort(mean_gradient[chosen], descending=True, stable=True)
            chosen = chosen[order[:max(0, budget)]]
        split = torch.zeros_like(selected)
        split[chosen] = large[chosen]
        clone = torch.zeros_like(selected)
        clone[chosen] = ~large[chosen]
        params = gmap.detached()
        new = [params.subset(clone)]
        if bool(split.any()):
            parent = params.subset(split)
            scales = torch.exp(parent.log_scales)  # [S, 3]
            rotation = quat_wxyz_to_rotmat(parent.quats_wxyz / parent.quats_wxyz.norm(dim=-1, keepdim=True))
            for _ in range(2):
                offset = (rotation @ (torch.randn(scales.shape, generator=self.generator, dtype=scales.dtype)
                                      .to(scales.device) * scales).unsqueeze(-1)).squeeze(-1)
                new.append(replace(parent, means=parent.means + offset,
                                   log_scales=parent.log_scales - math.log(SPLIT_SHRINK)))
        added = GaussianParameters.concatenate(new)
        gmap.add(added, self.optimizer)
        removed = gmap.remove(torch.cat([split, torch.zeros(len(added), dtype=torch.bool, device=split.device)]),
                              self.optimizer)
        opacities = torch.sigmoid(gmap.opacity_logits)
        pruned = gmap.remove(~torch.isfinite(opacities) | (opacities < cfg.prune_opacity), self.optimizer)
        self.densified += len(added) - removed
        self.pruned += pruned
        self._reset_gradient_statistics()
        return len(added) - removed, pruned

    # ------------------------------------------------------------------ state (resume)

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Plain tensors that :meth:`load_state_dict` restores (with the map, its optimizer and the generator,
        which the caller saves): steps taken, the rest of the current pass, the pose increments [K, 6] and their
        Adam moments."""
        state = {"steps": torch.tensor(self.steps, dtype=torch.int64),
                 "pending": torch.tensor(self._pending, dtype=torch.int64),
                 "pose_deltas": self.pose_deltas.detach().cpu().clone(),
                 "gradient_sum": self._gradient_sum.cpu().clone(), "sigma_sum": self._sigma_sum.cpu().clone(),
                 "views": self._views.cpu().clone()}
        if self._pose_optimizer is not None:
            moments = self._pose_optimizer.state.get(self.pose_deltas)
            if moments:
                state["pose_step"] = torch.as_tensor(moments["step"]).detach().cpu().clone()
                state["pose_exp_avg"] = moments["exp_avg"].detach().cpu().clone()
                state["pose_exp_avg_sq"] = moments["exp_avg_sq"].detach().cpu().clone()
        return state

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Restore :meth:`state_dict` output for the same keyframes (ValueError when their count differs)."""
        deltas = state["pose_deltas"]
        if tuple(deltas.shape) != tuple(self.pose_deltas.shape):
            raise ValueError(f"refinement state holds {deltas.shape[0]} keyframe poses, this refinement has "
                             f"{len(self.keyframes)}")
        if "views" in state and len(state["views"]) != len(self.map):
            raise ValueError(f"refinement state holds gradient statistics of {len(state['views'])} Gaussians, the "
                             f"map has {len(self.map)}")
        self.steps = int(state["steps"])
        self._pending = [int(v) for v in state["pending"].tolist()]
        if "views" in state:
            device = self.map.device
            self._gradient_sum = state["gradient_sum"].to(device=device, dtype=torch.float64).clone()
            self._sigma_sum = state["sigma_sum"].to(device=device, dtype=torch.float64).clone()
            self._views = state["views"].to(device=device, dtype=torch.float64).clone()
        with torch.no_grad():
            self.pose_deltas.copy_(deltas.to(self.pose_deltas))
        if self._pose_optimizer is not None and "pose_step" in state:
            self._pose_optimizer.state[self.pose_deltas] = {
                "step": state["pose_step"].clone().to(torch.float32),
                "exp_avg": state["pose_exp_avg"].to(self.pose_deltas).clone(),
                "exp_avg_sq": state["pose_exp_avg_sq"].to(self.pose_deltas).clone()}

    # ------------------------------------------------------------------ internals

    def _next_position(self) -> int:
        if not self._pending:
            self._pending = torch.randperm(len(self.keyframes), generator=self.generator).tolist()
        return self._pending.pop(0)

    def _image(self, position: int) -> tuple[KeyframeImage, RGBDMasks]:
        entry = self._images.get(position)
        if entry is not None:
            self._images.move_to_end(position)
            return entry
        image = self.load(self.keyframes[position])
        entry = (image, rgbd_masks(image.color, image.depth, max_depth=self.options.max_depth))
        if self.cache_size > 0:
            self._images[position] = entry
            while len(self._images) > self.cache_size:
                self._images.popitem(last=False)
        return entry

    def _frustum_rows(self, position: int, intrinsics: Intrinsics) -> torch.Tensor | None:
        """The Gaussians keyframe ``position`` can draw from where they are now (:func:`frustum_indices`), the
        others would get zero gradients; computed at every step, so a resumed refinement draws exactly the rows
        an uninterrupted one draws."""
        seen = frustum_indices(self.map.means.detach(), torch.exp(self.map.log_scales.detach()),
                               self._T_cw[position], intrinsics, self.render_config)
        return None if len(seen) == len(self.map) else seen


def refine_options(config: Config) -> RefineOptions:
    """The refinement loss of the ``refine`` config section, with the mapping section's frequency loss and depth
    range."""
    cfg, mapping = config.refine, config.mapping
    lambda_freq = mapping.lambda_freq if cfg.lambda_freq is None else cfg.lambda_freq
    return RefineOptions(alpha_color=cfg.alpha_color, ssim_weight=cfg.ssim_weight, isotropy_weight=cfg.isotropy_weight,
                         lambda_freq=lambda_freq, freq_patch=mapping.freq_patch, freq_alpha=mapping.freq_alpha,
                         lr_poses=cfg.lr_poses, max_depth=mapping.max_depth, densify_grad=cfg.densify_grad,
                         prune_opacity=mapping.prune_opacity, max_gaussians=mapping.max_gaussians)
