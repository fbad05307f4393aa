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

from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Sequence

import torch

from mipslam.config import Config, RenderConfig
from mipslam.gaussians import GaussianMap, GaussianOptimizer
from mipslam.geometry.se3 import se3_exp, se3_inverse
from mipslam.losses.frequency import frequency_loss
from mipslam.losses.photometric import RGBDMasks, apply_affine_exposure, rgbd_l1_loss, rgbd_masks
from mipslam.losses.regularizers import isotropy_loss
from mipslam.losses.structural import SSIMTargetCache, ssim_loss
from mipslam.rendering import frustum_indices, render_view
from mipslam.types import Frame, Intrinsics

if TYPE_CHECKING:
    from mipslam.state import SLAMState


MIN_STEPS_PER_PASS = 10  # a run's final refinement: one pass is at least this many steps
# Over a refinement of known length the means' learning rate decays exponentially to this fraction (3D Gaussian
# Splatting's position schedule, 100x): fr3_teddy_100 `balanced` novel PSNR 25.39 -> 25.93 dB (docs/mapping.md)
MEANS_LR_FINAL_RATIO = 0.01


@dataclass(frozen=True)
class RefineOptions:
    """The refinement loss and what it may move (module docstring).

    alpha_color      weight of the colour L1 against the depth L1 (mapping keeps depth strong for tracking)
    ssim_weight      weight of 1 - SSIM (3DGS: 0.2; 0.4 gave lower LPIPS on the real sequences, docs/bench.md)
    isotropy_weight  weight of the isotropy regulariser (metres): thin structures need elongated Gaussians
    lambda_freq      weight of the frequency-domain loss (docs/design.md "Losses"; off: it raised LPIPS on real
                     sequences once D-SSIM is in the loss, docs/bench.md); freq_patch px, freq_alpha its exponent
    lr_poses         Adam rate of the keyframe poses (m, rad per step); 0 keeps them fixed
    max_depth        metres; observed depth beyond it leaves the depth term (0 = no limit)
    """

    alpha_color: float = 0.9
    ssim_weight: float = 0.4
    isotropy_weight: float = 0.0
    lambda_freq: float = 0.0
    freq_patch: int = 16
    freq_alpha: float = 1.0
    lr_poses: float = 0.0
    max_depth: float = 0.0

    def __post_init__(self):
        problems = [name for name, ok in (("alpha_color", 0 <= self.alpha_color <= 1),
                                          ("ssim_weight", self.ssim_weight >= 0),
                                          ("isotropy_weight", self.isotropy_weight >= 0),
                                          ("lambda_freq", self.lambda_freq >= 0), ("freq_patch", self.freq_patch >= 2),
                                          ("lr_poses", self.lr_poses >= 0), ("max_depth", self.max_depth >= 0))
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


def state_keyframes(state: "SLAMState") -> list[RefineKeyframe]:
    """Every keyframe of ``state`` as the refinement visits it: id, frame index, current pose, exposure."""
    records = (state.keyframe_record(kf) for kf in range(len(state.keyframe_frames)))
    return [RefineKeyframe(kf, record.index, record.T_wc, record.exposure.to(torch.float32))
            for kf, record in enumerate(records)]


def image_loader(frames: Callable[[int], Frame], device: torch.device) -> Callable[[RefineKeyframe], KeyframeImage]:
    """``load(keyframe)`` for :class:`KeyframeRefiner`: frame ``keyframe.frame_index`` of ``frames`` (a sequence's
    or a frame cache's ``__getitem__``) with its images on ``device``."""

    def load(keyframe: RefineKeyframe) -> KeyframeImage:
        frame = frames(keyframe.frame_index)
        return KeyframeImage(frame.color.to(device), frame.depth.to(device), frame.intrinsics)

    return load


class KeyframeRefiner:
    """Steps of the refinement loss over ``keyframes`` (module docstring).

    ``load(keyframe)`` gives a keyframe's :class:`KeyframeImage`; the last ``cache_size`` are kept with their loss
    masks (a pass visits every keyframe once, so a cache of all keyframes reads each image once per run).
    ``generator`` draws the order of each pass. The map and its optimizer are changed in place.
    """

    def __init__(self, gmap: GaussianMap, optimizer: GaussianOptimizer, keyframes: Sequence[RefineKeyframe],
                 load: Callable[[RefineKeyframe], KeyframeImage], options: RefineOptions,
                 render_config: RenderConfig, generator: torch.Generator, *, cache_size: int = 64,
                 decay_steps: int = 0):
        if not keyframes:
            raise ValueError("KeyframeRefiner needs at least one keyframe")
        self.map, self.optimizer, self.keyframes = gmap, optimizer, list(keyframes)
        self.load, self.options, self.render_config, self.generator = load, options, render_config, generator
        self.cache_size = cache_size
        self.steps = 0
        # decay_steps > 0: the means' rate falls from the optimizer's to MEANS_LR_FINAL_RATIO of it over that many
        # steps (:meth:`step`; the caller restores it with :meth:`restore_learning_rates`); 0 keeps it constant
        self.decay_steps = decay_steps
        self._means_lr = optimizer.learning_rates["means"]
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
        loss = self.loss(image, masks, T_cw, exposure, rows)
        if not torch.isfinite(loss):
            return None
        if self.decay_steps > 0:
            progress = min(self.steps, self.decay_steps - 1) / max(1, self.decay_steps - 1)
            self.optimizer.set_learning_rate("means", self._means_lr * MEANS_LR_FINAL_RATIO ** progress)
        self.optimizer.zero_grad()
        if self._pose_optimizer is not None:
            self._pose_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        if self._pose_optimizer is not None:
            self._pose_optimizer.step()
        self.steps += 1
        return float(loss.detach())

    def loss(self, image: KeyframeImage, masks: RGBDMasks, T_cw: torch.Tensor, exposure: torch.Tensor,
             rows: torch.Tensor | None) -> torch.Tensor:
        """The refinement loss of one keyframe (module docstring) rendered from ``T_cw`` [4, 4] (world-to-camera)
        with the Gaussians ``rows`` [M] int64 (None: all): a scalar tensor."""
        cfg = self.options
        g = self.map.activated(rows)
        out = render_view(g, T_cw, image.intrinsics, self.render_config)
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
        return loss

    def restore_learning_rates(self) -> None:
        """The means' learning rate the optimizer had before a decaying refinement."""
        self.optimizer.set_learning_rate("means", self._means_lr)

    # ------------------------------------------------------------------ state (resume)

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Plain tensors that :meth:`load_state_dict` restores (with the map, its optimizer and the generator,
        which the caller saves): steps taken, the rest of the current pass, the pose increments [K, 6] and their
        Adam moments."""
        state = {"steps": torch.tensor(self.steps, dtype=torch.int64),
                 "pending": torch.tensor(self._pending, dtype=torch.int64),
                 "pose_deltas": self.pose_deltas.detach().cpu().clone()}
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
        self.steps = int(state["steps"])
        self._pending = [int(v) for v in state["pending"].tolist()]
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
    """The refinement of the ``refine`` config section (keyframe poses' rate); the loss weights and the depth
    range are this module's (docs/mapping.md, "The final refinement")."""
    return RefineOptions(lr_poses=config.refine.lr_poses)


def final_refinement_steps(passes: int, keyframes: int) -> int:
    """Steps of a run's final refinement: ``passes`` over the keyframes, a pass at least
    ``MIN_STEPS_PER_PASS`` steps (a short clip's one or two keyframes are otherwise under-fitted)."""
    return passes * max(keyframes, MIN_STEPS_PER_PASS) if keyframes else 0
