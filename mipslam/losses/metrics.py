"""PSNR, the image measure of the evaluation protocol (docs/evaluation.md; :mod:`mipslam.evaluation.image_metrics`
states its conventions), here below the stages and the evaluation so that both use it: the loop-closure stage
measures a correction's effect on the map with it (docs/design.md "Import layers").
"""
from __future__ import annotations

import torch

from mipslam.errors import EvaluationError


def check_image_pair(image: torch.Tensor, target: torch.Tensor, what: str, min_dims: int) -> None:
    """EvaluationError unless ``image`` and ``target`` have one shape of at least ``min_dims`` dimensions."""
    if image.shape != target.shape:
        raise EvaluationError(f"{what}: rendered {tuple(image.shape)} and ground truth {tuple(target.shape)} differ in shape")
    if image.dim() < min_dims:
        raise EvaluationError(f"{what}: expected at least {min_dims} dimensions, got shape {tuple(image.shape)}")


def psnr(
    image: torch.Tensor,  # [..., H, W, C] in [0, max_value]
    target: torch.Tensor,  # [..., H, W, C]
    *,
    mask: torch.Tensor | None = None,  # [..., H, W] bool (broadcast over the batch)
    max_value: float = 1.0,
) -> torch.Tensor:  # [...] dB
    """Peak signal-to-noise ratio per image, ``10 log10(max_value^2 / MSE)`` over the (masked) pixels."""
    check_image_pair(image, target, "PSNR", 3)
    squared = (image - target).pow(2).mean(dim=-1)  # [..., H, W]
    if mask is None:
        mse = squared.mean(dim=(-2, -1))
    else:
        if mask.shape[-2:] != squared.shape[-2:]:
            raise EvaluationError(f"PSNR: mask {tuple(mask.shape)} does not match the images {tuple(image.shape)}")
        mask = mask.to(torch.bool).expand_as(squared)
        count = mask.sum(dim=(-2, -1))
        if bool((count == 0).any()):
            raise EvaluationError("PSNR: the mask selects no pixel of an image; evaluate it without a mask or skip it")
        mse = torch.where(mask, squared, 0.0).sum(dim=(-2, -1)) / count
    return 10.0 * torch.log10(max_value**2 / mse)
