"""Front-to-back alpha compositing (docs/design.md "Renderer contract"), pure functions on tensors.

Along the last axis the Gaussians are in depth order, nearest first. Per pixel:
``alpha_i = min(0.99, a_i)``; ``alpha_i = 0`` when ``a_i < 1/255`` (skipped); ``T_0 = 1``; Gaussian i
contributes iff ``T_i (1 - alpha_i) >= 1e-4`` (the first one that fails stops the pixel, as in the
3DGS rasterizer); ``w_i = alpha_i T_i``; colour, depth and opacity are ``sum w_i c_i``,
``sum w_i z_i`` and ``sum w_i = 1 - T_final``.
"""
from __future__ import annotations

import math

import torch

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
TRANSMITTANCE_MIN = 1e-4


def clamp_alpha(opacity: torch.Tensor) -> torch.Tensor:
    """``min(0.99, a)``, and 0 where ``a < 1/255``.  [...] -> [...]"""
    alpha = opacity.clamp(max=ALPHA_MAX)
    return torch.where(opacity < ALPHA_MIN, torch.zeros_like(alpha), alpha)


def blend_weights(alpha: torch.Tensor) -> torch.Tensor:
    """Compositing weights ``w_i = alpha_i T_i`` with early termination.  alpha [..., L] -> [..., L]

    ``T`` is accumulated in log space (``log(1 - alpha)`` is finite because alpha <= 0.99), which
    keeps long lists and their gradients stable.
    """
    log_keep = torch.log1p(-alpha)  # [..., L] <= 0
    log_after = torch.cumsum(log_keep, dim=-1)  # log T_{i+1}
    log_before = log_after - log_keep  # log T_i
    contributes = log_after >= math.log(TRANSMITTANCE_MIN)
    # T is non-increasing, so "T_{i+1} >= 1e-4" fails from the first failing Gaussian onwards.
    return torch.where(contributes, alpha * torch.exp(log_before), torch.zeros_like(alpha))


def composite(opacity: torch.Tensor, colors: torch.Tensor, depths: torch.Tensor):
    """Composite depth-ordered per-pixel opacities.

    opacity [..., L] (per-pixel opacity a before clamping), colors [..., L, C], depths [..., L] metres
    -> (color [..., C], depth [...], alpha [...]).
    """
    return composite_weighted(blend_weights(clamp_alpha(opacity)), colors, depths)


def composite_weighted(weights: torch.Tensor, colors: torch.Tensor, depths: torch.Tensor):
    """:func:`composite` from its blending weights ``w_i = alpha_i T_i`` [..., L] (:func:`blend_weights`), for a
    caller that reuses them.  colors [..., L, C], depths [..., L] -> (color [..., C], depth [...], alpha [...])"""
    color = (weights.unsqueeze(-1) * colors).sum(-2)
    depth = (weights * depths).sum(-1)
    return color, depth, weights.sum(-1)
