"""Structural similarity (SSIM) as a differentiable function of two images, for losses and for the evaluation.

``SSIM = (2 mu_x mu_y + C1)(2 sigma_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(sigma_x^2 + sigma_y^2 + C2))`` (Wang et al.,
2004) with Gaussian-weighted local moments (window ``window_size`` px, std-dev ``sigma`` px), ``C1 = (0.01 L)^2``,
``C2 = (0.03 L)^2``, per channel, averaged over channels and pixels. ``padding="same"`` convolves with zero padding of
``window // 2`` pixels and averages the full map, as 3D Gaussian Splatting's ``utils/loss_utils.ssim`` does (the
photometric loss ``(1 - l) L1 + l (1 - SSIM)`` of Kerbl et al., 2023, and the evaluation of the Gaussian-splatting
SLAM papers); ``"valid"`` averages only windows inside the image. Images are float, channels last, ``[..., H, W, C]``.
"""
from __future__ import annotations

from typing import Literal

import torch

__all__ = ["gaussian_window_1d", "ssim"]


def gaussian_window_1d(size: int, sigma: float, *, dtype=torch.float64, device=None) -> torch.Tensor:  # [size]
    """Normalised sampled Gaussian ``exp(-(x - size//2)^2 / (2 sigma^2))`` (the 1D factor of the SSIM window)."""
    x = torch.arange(size, dtype=torch.float64, device=device) - (size // 2)
    g = torch.exp(-(x * x) / (2.0 * sigma * sigma))
    return (g / g.sum()).to(dtype)


def ssim(
    image: torch.Tensor,  # [..., H, W, C] in [0, max_value]
    target: torch.Tensor,  # [..., H, W, C], the same shape
    *,
    window_size: int = 11,
    sigma: float = 1.5,
    padding: Literal["same", "valid"] = "same",
    max_value: float = 1.0,
) -> torch.Tensor:  # [...]
    """SSIM per image (module docstring); differentiable with respect to both images. Raises ValueError on
    mismatched shapes, an even window or a ``valid`` window larger than the image."""
    if image.shape != target.shape or image.dim() < 3:
        raise ValueError(f"SSIM: images must share a shape [..., H, W, C], got {tuple(image.shape)} and "
                         f"{tuple(target.shape)}")
    if window_size % 2 != 1:
        raise ValueError(f"SSIM: window size must be odd, got {window_size}")
    if padding not in ("same", "valid"):
        raise ValueError(f"SSIM: padding must be 'same' or 'valid', got {padding!r}")
    batch_shape = image.shape[:-3]
    height, width, channels = image.shape[-3:]
    if padding == "valid" and (height < window_size or width < window_size):
        raise ValueError(f"SSIM: 'valid' padding needs images of at least {window_size} px, got {height}x{width}")
    x = image.reshape(-1, height, width, channels).permute(0, 3, 1, 2)  # [B, C, H, W]
    y = target.reshape(-1, height, width, channels).permute(0, 3, 1, 2)
    g = gaussian_window_1d(window_size, sigma, dtype=x.dtype, device=x.device)
    weight_rows = g.view(1, 1, window_size, 1).expand(channels, 1, window_size, 1)
    weight_cols = g.view(1, 1, 1, window_size).expand(channels, 1, 1, window_size)
    pad = window_size // 2 if padding == "same" else 0

    def blur(z: torch.Tensor) -> torch.Tensor:  # [B, C, H, W] -> [B, C, H', W'], separable Gaussian
        z = torch.nn.functional.conv2d(z, weight_rows, padding=(pad, 0), groups=channels)
        return torch.nn.functional.conv2d(z, weight_cols, padding=(0, pad), groups=channels)

    c1, c2 = (0.01 * max_value) ** 2, (0.03 * max_value) ** 2
    mu_x, mu_y = blur(x), blur(y)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    sigma_xx = blur(x * x) - mu_xx
    sigma_yy = blur(y * y) - mu_yy
    sigma_xy = blur(x * y) - mu_xy
    ssim_map = ((2 * mu_xy + c1) * (2 * sigma_xy + c2)) / ((mu_xx + mu_yy + c1) * (sigma_xx + sigma_yy + c2))
    return ssim_map.mean(dim=(1, 2, 3)).reshape(batch_shape)
