"""Photometric + depth L1 loss of tracking and mapping (docs/design.md, "Losses").

    L = alpha_c * mean_{p in M_rgb}(|exposure(I)(p) - I_gt(p)|) + (1 - alpha_c) * mean_{p in M_d}(|D(p) - D_gt(p)|)

* ``I``, ``I_gt``: rendered and observed colour, float in [0, 1], ``[H, W, C]`` (channels last, as the renderer
  returns them). The colour mean runs over the selected pixels *and* the channels.
* ``D``, ``D_gt``: rendered and observed depth in metres, ``[H, W]``; ``D_gt == 0`` means "no measurement".
* Masks (built by :func:`rgbd_masks`, or passed in by the caller):
  - depth mask ``M_d``: observed depth is valid (finite and > 0) and, when a rendered opacity is given, the
    rendered opacity is at least ``opacity_threshold`` (the map explains the pixel; MonoGS-style);
  - colour mask ``M_rgb``: the same opacity condition, the observed colour is finite, the image-gradient mask
    (pixels whose target gradient magnitude is above a percentile, see :func:`image_gradient_mask`), and, where
    asked, valid observed depth too (SplaTAM-style).
* Alpha-normalised depth (optional, ``depth_alpha``): the renderer's depth is ``D = sum_i T_i a_i z_i``, which
  equals ``A * z`` for a surface at ``z`` rendered with accumulated opacity ``A = sum_i T_i a_i``. Where
  ``A < 1`` the raw term ``|D - D_gt|`` is minimised by Gaussians at ``D_gt / A`` (too far by ``1 / A - 1``) or
  by a camera that moved towards the surface. With ``depth_alpha`` the term compares
  ``D / stopgrad(max(A, floor))`` instead: unbiased wherever ``A >= floor``; below the floor (a thin map) it
  keeps the raw term's push towards more opacity. The stop-gradient leaves opacity to the colour term, so
  the depth term cannot lower ``A`` to move the normalised depth.
* Depth outliers (optional, ``depth_outlier_ratio``): pixels whose depth residual exceeds that many times the
  median residual of the depth mask leave the depth term (SplaTAM's rule). Those are disocclusions and
  depth edges the map does not hold from this view; their residuals are metres where the rest are
  millimetres, and since they grow as the camera moves away from the views that built the map, an L1 term
  that keeps them pulls the pose back towards those views.
* Depth range (optional, ``max_depth`` of :func:`rgbd_masks`): observed depth beyond it is ignored in the depth
  term (the sensor's error grows with ``z^2``; far readings are the least reliable).
* Exposure: ``exp(a) * I + b`` per frame (gain ``a`` in log space so the gain stays positive), see
  :func:`apply_affine_exposure` and :class:`AffineExposure`.

An empty mask gives a term that is exactly zero, keeps a (zero) gradient path to the rendered inputs and is
reported through the pixel counts of :class:`RGBDLoss`, so the caller can flag "too few valid pixels".
Pure functions on tensors: any device, no config import.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

__all__ = [
    "AffineExposure",
    "RGBDLoss",
    "coverage_loss",
    "RGBDMasks",
    "apply_affine_exposure",
    "image_gradient_magnitude",
    "image_gradient_mask",
    "depth_inlier_mask",
    "masked_l1",
    "normalised_depth",
    "rgbd_l1_loss",
    "rgbd_masks",
]

# ITU-R BT.601 luma weights, used to reduce a colour target to one channel for the gradient mask.
_LUMA_WEIGHTS = (0.299, 0.587, 0.114)
# Opacity floor of the alpha-normalised depth when the caller gives none: at 0.5 a thin map's depth
# is at most doubled, so a pixel the map barely covers cannot dominate the depth term.
DEFAULT_DEPTH_ALPHA_FLOOR = 0.5


@dataclass(frozen=True)
class RGBDMasks:
    """Which pixels each term of the loss uses.

    color: pixels of the colour term   # [H, W] bool
    depth: pixels of the depth term    # [H, W] bool
    """

    color: torch.Tensor
    depth: torch.Tensor

    def where_opaque(self, alpha: torch.Tensor, opacity_threshold: float) -> "RGBDMasks":
        """These masks restricted to pixels whose rendered opacity ``alpha`` [H, W] is at least
        ``opacity_threshold`` (the map explains them); a threshold <= 0 returns the masks unchanged.

        Lets a caller build the target's masks once (:func:`rgbd_masks` without ``alpha``) and add the
        opacity condition at every render, which gives the same masks as :func:`rgbd_masks` with ``alpha``.
        """
        if opacity_threshold <= 0.0:
            return self
        if alpha.shape != self.depth.shape:
            raise ValueError(f"rgbd_masks: opacity {tuple(alpha.shape)} must match depth {tuple(self.depth.shape)}")
        opaque = alpha.detach() >= opacity_threshold
        return RGBDMasks(color=self.color & opaque, depth=self.depth & opaque)


@dataclass(frozen=True)
class RGBDLoss:
    """Result of :func:`rgbd_l1_loss`.

    total: alpha_c * color + (1 - alpha_c) * depth, differentiable   # [] scalar
    color: mean colour L1 over the colour mask (unweighted)          # [] scalar
    depth: mean depth L1 over the depth mask, metres (unweighted)    # [] scalar
    num_color_pixels / num_depth_pixels: how many pixels each term averaged over (0 = the term is a zero).
    """

    total: torch.Tensor
    color: torch.Tensor
    depth: torch.Tensor
    num_color_pixels: int
    num_depth_pixels: int


def apply_affine_exposure(
    image: torch.Tensor,  # [..., C]
    log_gain: torch.Tensor,  # [] or [C]
    bias: torch.Tensor,  # [] or [C]
) -> torch.Tensor:  # [..., C]
    """Affine exposure model ``exp(a) * I + b`` (MonoGS's per-frame brightness model).

    ``log_gain`` (a) and ``bias`` (b) are scalars or per-channel vectors broadcast over the last (channel)
    dimension. ``a = 0, b = 0`` is the identity. The result is not clamped (clamping would cut the gradient).
    """
    return torch.exp(log_gain) * image + bias


class AffineExposure(nn.Module):
    """Learnable per-frame affine exposure ``exp(a) * I + b``, initialised to the identity.

    Args:
        channels: 1 for one gain/bias shared by all channels (MonoGS), or the number of colour channels for a
            per-channel model.
        device, dtype: where the two parameters live (take them from the images you will correct).
    """

    def __init__(self, channels: int = 1, *, device: torch.device | str | None = None, dtype: torch.dtype | None = None):
        super().__init__()
        if channels < 1:
            raise ValueError(f"AffineExposure needs channels >= 1, got {channels}")
        shape = () if channels == 1 else (channels,)
        self.log_gain = nn.Parameter(torch.zeros(shape, device=device, dtype=dtype))  # [] or [C]
        self.bias = nn.Parameter(torch.zeros(shape, device=device, dtype=dtype))  # [] or [C]

    def forward(self, image: torch.Tensor) -> torch.Tensor:  # [..., C] -> [..., C]
        return apply_affine_exposure(image, self.log_gain, self.bias)


def image_gradient_magnitude(image: torch.Tensor) -> torch.Tensor:  # [H, W, C] or [H, W] -> [H, W]
    """Sobel gradient magnitude of the image's luma (BT.601 weights for 3 channels, channel mean otherwise).

    Units: intensity per pixel; the Sobel kernels are normalised by 1/8 so that a unit ramp gives 1.
    Borders use replicate padding (a constant continuation adds no gradient).
    """
    if image.dim() == 3:
        if image.shape[-1] == 3:
            weights = torch.tensor(_LUMA_WEIGHTS, dtype=image.dtype, device=image.device)
            gray = (image * weights).sum(dim=-1)
        else:
            gray = image.mean(dim=-1)
    elif image.dim() == 2:
        gray = image
    else:
        raise ValueError(f"image_gradient_magnitude expects [H, W] or [H, W, C], got shape {tuple(image.shape)}")
    gray = gray.to(torch.promote_types(gray.dtype, torch.float32))
    padded = torch.nn.functional.pad(gray[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    # Sobel: derivative (-1, 0, 1)/2 along one axis, smoothing (1, 2, 1)/4 along the other.
    dx = padded[:, 2:] - padded[:, :-2]  # [H+2, W]
    dy = padded[2:, :] - padded[:-2, :]  # [H, W+2]
    grad_x = (dx[:-2] + 2.0 * dx[1:-1] + dx[2:]) / 8.0
    grad_y = (dy[:, :-2] + 2.0 * dy[:, 1:-1] + dy[:, 2:]) / 8.0
    return torch.sqrt(grad_x * grad_x + grad_y * grad_y)


def image_gradient_mask(image: torch.Tensor, percentile: float) -> torch.Tensor:  # [H, W(, C)] -> [H, W] bool
    """Pixels whose target gradient magnitude lies above the ``percentile``-th percentile (0..100).

    ``percentile <= 0`` keeps every pixel. Otherwise a pixel is kept when its magnitude is strictly greater than
    the percentile value (linear interpolation between order statistics, as ``torch.quantile``), so a flat image
    keeps no pixel: it holds no photometric information. Compute it on the *target* (observed) image, once per
    frame; it carries no gradient.
    """
    if not 0.0 <= percentile < 100.0:
        raise ValueError(f"gradient percentile must be in [0, 100), got {percentile}")
    height, width = image.shape[0], image.shape[1]
    if percentile <= 0.0:
        return torch.ones((height, width), dtype=torch.bool, device=image.device)
    with torch.no_grad():
        magnitude = image_gradient_magnitude(image)  # [H, W]
        flat = magnitude.reshape(-1)
        finite = flat[torch.isfinite(flat)]
        if finite.numel() == 0:
            return torch.zeros((height, width), dtype=torch.bool, device=image.device)
        threshold = torch.quantile(finite, percentile / 100.0)
        return magnitude > threshold


def rgbd_masks(
    color_gt: torch.Tensor,  # [H, W, C]
    depth_gt: torch.Tensor,  # [H, W] metres, 0 = no measurement
    alpha: torch.Tensor | None = None,  # [H, W] rendered opacity in [0, 1]
    *,
    opacity_threshold: float = 0.0,
    gradient_percentile: float = 0.0,
    color_needs_valid_depth: bool = False,
    extra_color_mask: torch.Tensor | None = None,  # [H, W] bool
    max_depth: float = 0.0,
) -> RGBDMasks:
    """Masks of the colour and depth terms (see the module docstring). No gradient flows through masks.

    ``alpha=None`` (or ``opacity_threshold <= 0``) skips the opacity condition. ``max_depth`` (metres, > 0)
    leaves observed depth beyond it out of the depth term (and out of "valid depth" for the colour term's
    ``color_needs_valid_depth``); 0 keeps every depth.
    """
    if depth_gt.dim() != 2 or color_gt.shape[:2] != depth_gt.shape:
        raise ValueError(
            f"rgbd_masks: colour {tuple(color_gt.shape)} and depth {tuple(depth_gt.shape)} must be [H, W, C] and [H, W]"
        )
    with torch.no_grad():
        valid_depth = torch.isfinite(depth_gt) & (depth_gt > 0)  # [H, W]
        if max_depth > 0:
            valid_depth = valid_depth & (depth_gt <= max_depth)
        color_ok = torch.isfinite(color_gt).all(dim=-1) if color_gt.dim() == 3 else torch.isfinite(color_gt)
        color_mask = color_ok & image_gradient_mask(color_gt, gradient_percentile)
        if color_needs_valid_depth:
            color_mask = color_mask & valid_depth
        if extra_color_mask is not None:
            color_mask = color_mask & extra_color_mask.to(torch.bool)
        masks = RGBDMasks(color=color_mask, depth=valid_depth)
        if alpha is not None:
            masks = masks.where_opaque(alpha, opacity_threshold)
    return masks


def masked_l1(
    prediction: torch.Tensor,  # [H, W] or [H, W, C]
    target: torch.Tensor,  # same shape as prediction
    mask: torch.Tensor,  # [H, W] bool
) -> tuple[torch.Tensor, int]:
    """Mean of ``|prediction - target|`` over the masked pixels (and all channels), and the pixel count.

    Unselected pixels are removed with ``torch.where`` (not a multiplication), so a NaN or inf outside the mask
    neither reaches the value nor the gradient. An empty mask gives an exact zero that still depends on
    ``prediction`` (its gradient is zero), never a division by zero.
    """
    pixel_mask, norm, count = _masked_pixels(prediction, target, mask)
    return _MaskedMeanAbs.apply(prediction, target, pixel_mask, norm), count


def _masked_pixels(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor
                   ) -> tuple[torch.Tensor, float, int]:
    """:func:`masked_l1`'s checks, then the mask broadcast to ``prediction`` ([H, W] or [H, W, 1] bool), the
    normaliser (pixels x channels, at least one pixel) and the pixel count."""
    if prediction.shape != target.shape:
        raise ValueError(f"masked_l1: prediction {tuple(prediction.shape)} and target {tuple(target.shape)} differ")
    if mask.shape != prediction.shape[:2]:
        raise ValueError(f"masked_l1: mask {tuple(mask.shape)} must be the [H, W] of {tuple(prediction.shape)}")
    channels = prediction.shape[2] if prediction.dim() == 3 else 1
    mask = mask.to(torch.bool)
    count = int(mask.sum())
    return (mask if prediction.dim() == 2 else mask[..., None]), float(max(count, 1) * channels), count


class _MaskedMeanAbs(torch.autograd.Function):
    """``sum(|where(mask, prediction - target, 0)|) / norm`` with the backward ``sign(residual) / norm``
    written out: two image passes instead of autograd's six (abs, where and their zero-filled gradients),
    about 1 ms less per 320x240 colour image, on every tracking and mapping iteration. Values and
    gradients are those of the plain autograd expression (tests/test_losses.py)."""

    @staticmethod
    def forward(ctx, prediction, target, pixel_mask, norm: float):
        residual = torch.where(pixel_mask, prediction - target, 0.0)  # NaN outside the mask stops here
        ctx.save_for_backward(residual)
        ctx.norm = norm
        return residual.abs().sum() / norm

    @staticmethod
    def backward(ctx, grad_output):
        (residual,) = ctx.saved_tensors
        grad = residual.sign().mul_(grad_output / ctx.norm)  # 0 at masked pixels (their residual is 0)
        return (grad if ctx.needs_input_grad[0] else None, -grad if ctx.needs_input_grad[1] else None, None, None)


@dataclass(frozen=True)
class RGBDLossGradients:
    """Gradients of :func:`rgbd_l1_loss`'s total, from :func:`rgbd_l1_loss_and_gradients`.

    color:    [H, W, C] dL/d(rendered colour, before the exposure model)
    depth:    [H, W]    dL/d(rendered depth), 1/metre
    log_gain: []        dL/d(exposure log-gain), None without the exposure model
    bias:     []        dL/d(exposure bias), None without the exposure model
    """

    color: torch.Tensor
    depth: torch.Tensor
    log_gain: torch.Tensor | None = None
    bias: torch.Tensor | None = None


@torch.no_grad()
def rgbd_l1_loss_and_gradients(
    color: torch.Tensor,  # [H, W, C] rendered colour in [0, 1]
    depth: torch.Tensor,  # [H, W] rendered depth, metres
    color_gt: torch.Tensor,  # [H, W, C] observed colour in [0, 1]
    depth_gt: torch.Tensor,  # [H, W] observed depth, metres, 0 = none
    *,
    alpha_color: float,
    masks: RGBDMasks,
    exposure: tuple[torch.Tensor, torch.Tensor] | None = None,  # ([] log_gain, [] bias) of apply_affine_exposure
    depth_alpha: torch.Tensor | None = None,  # [H, W] rendered opacity (see rgbd_l1_loss)
    depth_alpha_floor: float = DEFAULT_DEPTH_ALPHA_FLOOR,
    depth_outlier_ratio: float = 0.0,
) -> tuple[RGBDLoss, RGBDLossGradients]:
    """:func:`rgbd_l1_loss` (with precomputed ``masks`` and :func:`apply_affine_exposure`'s scalar model) and
    its gradients, without autograd: for a caller that carries the chain rule itself (tracking's compiled
    step, which skips autograd's graph and engine on every step).

    The value and every gradient are those autograd gives for the same expression, bit for bit: the same
    tensor operations in the same order (the L1 terms' ``sign(r) * w / n``, the exposure's broadcast sums as
    autograd's ``sum_to_size``); tests/test_losses.py compares them with ``torch.equal``.
    """
    check_rgbd_loss_inputs("rgbd_l1_loss_and_gradients", color, depth, color_gt, depth_gt, alpha_color)
    gain = None
    if exposure is not None:
        log_gain, bias = exposure
        if log_gain.dim() != 0 or bias.dim() != 0:
            raise ValueError("rgbd_l1_loss_and_gradients: a scalar exposure model (log_gain [] and bias []) only")
        gain = torch.exp(log_gain)
        corrected = gain * color + bias
    else:
        corrected = color
    color_residual, color_norm, num_color = _masked_residual(corrected, color_gt, masks.color)
    alpha_clamped = None
    if depth_alpha is not None:
        alpha_clamped = _depth_divisor(depth, depth_alpha, depth_alpha_floor)
        depth = depth / alpha_clamped
    depth_mask = masks.depth
    if depth_outlier_ratio > 0:
        depth_mask = depth_inlier_mask(depth, depth_gt, depth_mask, depth_outlier_ratio)
    depth_residual, depth_norm, num_depth = _masked_residual(depth, depth_gt, depth_mask)
    color_term = color_residual.abs().sum() / color_norm
    depth_term = depth_residual.abs().sum() / depth_norm
    total = alpha_color * color_term + (1.0 - alpha_color) * depth_term
    loss = RGBDLoss(total=total, color=color_term, depth=depth_term, num_color_pixels=num_color,
                    num_depth_pixels=num_depth)

    # The chain rule as autograd runs it: d total / d term = 1 * weight, then _MaskedMeanAbs.backward.
    one = torch.ones_like(total)
    grad_corrected = color_residual.sign().mul_((one * alpha_color) / color_norm)
    grad_depth = depth_residual.sign().mul_((one * (1.0 - alpha_color)) / depth_norm)
    if alpha_clamped is not None:
        grad_depth = grad_depth / alpha_clamped
    if gain is None:
        return loss, RGBDLossGradients(color=grad_corrected, depth=grad_depth)
    grad_gain = (grad_corrected * color).sum_to_size(())
    gradients = RGBDLossGradients(color=grad_corrected * gain, depth=grad_depth, log_gain=grad_gain * gain,
                                  bias=grad_corrected.sum_to_size(()))
    return loss, gradients


def _masked_residual(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor
                     ) -> tuple[torch.Tensor, float, int]:
    """:func:`masked_l1`'s residual ``where(mask, prediction - target, 0)``, its normaliser and the pixel count
    (:func:`_masked_pixels`)."""
    pixel_mask, norm, count = _masked_pixels(prediction, target, mask)
    return torch.where(pixel_mask, prediction - target, 0.0), norm, count


def normalised_depth(
    depth: torch.Tensor,  # [H, W] rendered depth sum_i T_i a_i z_i, metres
    alpha: torch.Tensor,  # [H, W] rendered opacity sum_i T_i a_i in [0, 1]
    floor: float = DEFAULT_DEPTH_ALPHA_FLOOR,
) -> torch.Tensor:  # [H, W] metres
    """``D / stopgrad(max(A, floor))``: the opacity-weighted mean depth of the Gaussians a pixel sees.

    Where ``A >= floor`` this is the depth of the surface whatever the opacity (a surface at ``z`` with
    ``A < 1`` renders ``D = A z``); the gradient flows through ``D`` alone (scaled by ``1 / A``).
    """
    return depth / _depth_divisor(depth, alpha, floor)


def _depth_divisor(depth: torch.Tensor, alpha: torch.Tensor, floor: float) -> torch.Tensor:
    """:func:`normalised_depth`'s checks and divisor ``stopgrad(max(A, floor))`` [H, W]."""
    check_depth_alpha(depth, alpha, floor)
    return alpha.detach().clamp(min=floor)


def check_depth_alpha(depth: torch.Tensor, alpha: torch.Tensor, floor: float) -> None:
    """:func:`normalised_depth`'s argument checks: ``alpha`` [H, W] the shape of ``depth``, ``floor`` in (0, 1]."""
    if depth.shape != alpha.shape:
        raise ValueError(f"normalised_depth: depth {tuple(depth.shape)} and opacity {tuple(alpha.shape)} differ")
    if not 0.0 < floor <= 1.0:
        raise ValueError(f"normalised_depth: floor must be in (0, 1], got {floor}")


def depth_inlier_mask(
    depth: torch.Tensor,  # [H, W] rendered depth, metres
    depth_gt: torch.Tensor,  # [H, W] observed depth, metres
    mask: torch.Tensor,  # [H, W] bool, the depth term's pixels
    ratio: float,
) -> torch.Tensor:  # [H, W] bool
    """``mask`` without the pixels whose residual ``|D - D_gt|`` exceeds ``ratio`` times its median over ``mask``."""
    if ratio <= 0:
        raise ValueError(f"depth_inlier_mask: ratio must be positive, got {ratio}")
    with torch.no_grad():
        residual = torch.where(mask, (depth.detach() - depth_gt).abs(), torch.zeros_like(depth_gt))
        if not bool(mask.any()):
            return mask
        median = residual[mask].median()
        return mask & (residual <= ratio * median)


def coverage_loss(
    alpha: torch.Tensor,  # [H, W] rendered opacity in [0, 1]
    mask: torch.Tensor,  # [H, W] bool, pixels where the sensor measured a surface
) -> torch.Tensor:  # [] scalar
    """``mean(1 - A)`` over ``mask``: where the sensor saw a surface the map should be opaque (0 for an empty mask).

    Pairs with the alpha-normalised depth term, which places the surface but leaves opacity alone."""
    value, _ = masked_l1(alpha, torch.ones_like(alpha), mask)
    return value


def check_rgbd_loss_inputs(name: str, color: torch.Tensor, depth: torch.Tensor, color_gt: torch.Tensor,
                            depth_gt: torch.Tensor, alpha_color: float) -> None:
    """The loss's argument checks, shared by :func:`rgbd_l1_loss` and :func:`rgbd_l1_loss_and_gradients`."""
    if not 0.0 <= alpha_color <= 1.0:
        raise ValueError(f"alpha_color must be in [0, 1], got {alpha_color}")
    if color.shape != color_gt.shape or depth.shape != depth_gt.shape:
        raise ValueError(
            f"{name}: rendered colour {tuple(color.shape)} / depth {tuple(depth.shape)} do not match "
            f"the observed {tuple(color_gt.shape)} / {tuple(depth_gt.shape)}"
        )


def rgbd_l1_loss(
    color: torch.Tensor,  # [H, W, C] rendered colour in [0, 1]
    depth: torch.Tensor,  # [H, W] rendered depth, metres
    color_gt: torch.Tensor,  # [H, W, C] observed colour in [0, 1]
    depth_gt: torch.Tensor,  # [H, W] observed depth, metres, 0 = none
    *,
    alpha_color: float,
    masks: RGBDMasks | None = None,
    alpha: torch.Tensor | None = None,  # [H, W] rendered opacity (used only when masks is None)
    opacity_threshold: float = 0.0,
    gradient_percentile: float = 0.0,
    color_needs_valid_depth: bool = False,
    exposure: nn.Module | None = None,
    depth_alpha: torch.Tensor | None = None,  # [H, W] rendered opacity: compare the alpha-normalised depth
    depth_alpha_floor: float = DEFAULT_DEPTH_ALPHA_FLOOR,
    depth_outlier_ratio: float = 0.0,
) -> RGBDLoss:
    """The tracking/mapping loss of docs/design.md (formula in the module docstring).

    Pass precomputed ``masks`` (e.g. the gradient mask once per frame, see :func:`rgbd_masks`), or let the
    function build them from ``alpha``/``opacity_threshold``/``gradient_percentile``. ``exposure`` (e.g.
    :class:`AffineExposure`) is applied to the rendered colour before the comparison. ``depth_alpha`` (the
    render's opacity [H, W]) makes the depth term compare :func:`normalised_depth` ``D / stopgrad(max(A,
    depth_alpha_floor))`` with the observed depth (module docstring); None compares the raw ``D``.
    ``depth_outlier_ratio`` > 0 drops depth pixels whose residual exceeds that many times the median residual.
    """
    check_rgbd_loss_inputs("rgbd_l1_loss", color, depth, color_gt, depth_gt, alpha_color)
    if masks is None:
        masks = rgbd_masks(
            color_gt,
            depth_gt,
            alpha,
            opacity_threshold=opacity_threshold,
            gradient_percentile=gradient_percentile,
            color_needs_valid_depth=color_needs_valid_depth,
        )
    corrected = exposure(color) if exposure is not None else color
    color_term, num_color = masked_l1(corrected, color_gt, masks.color)
    if depth_alpha is not None:
        depth = normalised_depth(depth, depth_alpha, depth_alpha_floor)
    depth_mask = masks.depth
    if depth_outlier_ratio > 0:
        depth_mask = depth_inlier_mask(depth, depth_gt, depth_mask, depth_outlier_ratio)
    depth_term, num_depth = masked_l1(depth, depth_gt, depth_mask)
    total = alpha_color * color_term + (1.0 - alpha_color) * depth_term
    return RGBDLoss(
        total=total, color=color_term, depth=depth_term, num_color_pixels=num_color, num_depth_pixels=num_depth
    )
