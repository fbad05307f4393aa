"""Image metrics of the rendering evaluation: PSNR, SSIM, depth L1, and area resampling of ground truth.

Conventions (the protocol that ``metrics.json`` states):

* Images are float in [0, 1], channels last: ``[..., H, W, C]``; any leading dimensions are a batch and every
  metric returns one value per image (``[...]``). Depth is metres, ``[..., H, W]``, 0 = no measurement.
* PSNR: ``10 log10(max_value^2 / MSE)``, the MSE over all channels of the selected pixels (all pixels when no
  mask is given). Identical images give ``+inf``. No clamping or quantisation is applied (3DGS's evaluation
  reads back 8-bit PNGs; quantise before calling if you want to reproduce that exactly).
* SSIM: Wang et al. 2004 with the 11x11 Gaussian window of sigma 1.5, ``C1 = (0.01 L)^2``, ``C2 = (0.03 L)^2``,
  computed per channel and averaged over channels and pixels, exactly as the Gaussian-splatting papers' code
  (3DGS ``utils/loss_utils.ssim``, also used by Mip-Splatting, MonoGS, SplaTAM) computes it: ``padding="same"``
  convolves with *zero* padding of ``window // 2`` pixels and averages the full ``H x W`` map (the border
  windows see zeros). ``padding="valid"`` averages only windows that lie inside the image (MATLAB/skimage-like
  ``valid`` region; equal to kornia's ``ssim(..., padding="valid")``).
* Depth L1: mean ``|D - D_gt|`` in metres over pixels whose ground-truth depth is valid (finite and > 0),
  optionally intersected with a caller's mask.
* ``resize_area``: exact box-filter (area-averaging) resampling for any positive factor, consistent with
  :meth:`mipslam.types.Intrinsics.scaled`: output pixel j covers the input interval ``[j / f, (j + 1) / f]``
  (pixel edges at integers, i.e. the pixel-centre convention), and the output size is ``round(f * size)``.
  Downsampling averages every input pixel with its overlap area (never bilinear sampling, which aliases the
  ground truth); upsampling replicates pixels and blends across the edges an output pixel straddles.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from mipslam.errors import EvaluationError
from mipslam.geometry.resample import resize_area
from mipslam.losses.metrics import check_image_pair, psnr
from mipslam.losses.structural import gaussian_window_1d, ssim as structural_ssim

__all__ = [
    "ImageMetrics",
    "depth_l1",
    "gaussian_window_1d",
    "image_metrics",
    "psnr",
    "resize_area",
    "ssim",
]


def ssim(
    image: torch.Tensor,  # [..., H, W, C] in [0, max_value]
    target: torch.Tensor,  # [..., H, W, C]
    *,
    window_size: int = 11,
    sigma: float = 1.5,
    padding: Literal["same", "valid"] = "same",
    max_value: float = 1.0,
) -> torch.Tensor:  # [...]
    """Structural similarity per image (conventions in the module docstring; ``same`` = 3DGS zero padding):
    :func:`mipslam.losses.structural.ssim` with the evaluation's checks. Differentiable."""
    check_image_pair(image, target, "SSIM", 3)
    try:
        return structural_ssim(image, target, window_size=window_size, sigma=sigma, padding=padding,
                               max_value=max_value)
    except ValueError as exc:
        raise EvaluationError(str(exc)) from None


def depth_l1(
    depth: torch.Tensor,  # [..., H, W] metres
    depth_gt: torch.Tensor,  # [..., H, W] metres, 0 = no measurement
    *,
    mask: torch.Tensor | None = None,  # [..., H, W] bool, extra restriction (e.g. rendered opacity)
) -> torch.Tensor:  # [...] metres
    """Mean absolute depth error in metres over pixels with valid ground truth (and ``mask``), per image."""
    check_image_pair(depth, depth_gt, "depth L1", 2)
    valid = torch.isfinite(depth_gt) & (depth_gt > 0)
    if mask is not None:
        valid = valid & mask.to(torch.bool)
    count = valid.sum(dim=(-2, -1))
    if bool((count == 0).any()):
        raise EvaluationError("depth L1: an image has no pixel with valid ground-truth depth; skip it or report it as missing")
    error = torch.where(valid, (depth - torch.where(valid, depth_gt, 0.0)).abs(), 0.0)
    return error.sum(dim=(-2, -1)) / count


@dataclass(frozen=True)
class ImageMetrics:
    """Metrics of one rendered view against its ground truth (plain floats, for metrics.json)."""

    psnr: float  # dB
    ssim: float
    depth_l1: float | None  # metres; None when no depth ground truth was evaluated


def image_metrics(
    color: torch.Tensor,  # [H, W, 3] rendered, [0, 1]
    color_gt: torch.Tensor,  # [H, W, 3]
    depth: torch.Tensor | None = None,  # [H, W] metres
    depth_gt: torch.Tensor | None = None,  # [H, W] metres, 0 = none
) -> ImageMetrics:
    """PSNR, SSIM (3DGS convention) and depth L1 of one view, computed without gradients."""
    with torch.no_grad():
        value_depth = None
        if depth is not None and depth_gt is not None:
            value_depth = float(depth_l1(depth, depth_gt))
        return ImageMetrics(psnr=float(psnr(color, color_gt)), ssim=float(ssim(color, color_gt)), depth_l1=value_depth)
