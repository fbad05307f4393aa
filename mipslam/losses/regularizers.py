"""Regularisers of the mapping loss (docs/design.md, "Losses": "plus an isotropy regulariser").

All take the *activated* scales (standard deviations along the Gaussian's principal axes, metres), not the
log-scales the optimiser holds, so their meaning does not depend on the parametrisation.

* Isotropy (MonoGS, Matsuki et al. 2024, eq. "L_iso"; SplaTAM uses isotropic Gaussians outright):

      L_iso = 1/(3N) sum_n sum_k | s_nk - sbar_n |,   sbar_n = (s_n1 + s_n2 + s_n3) / 3

  It is zero exactly for spheres and penalises needle- and disc-shaped Gaussians, which a few views
  cannot constrain and which streak in novel views. With ``relative=True`` each Gaussian's deviation is divided
  by its own mean scale (``|s_nk / sbar_n - 1|``), which makes the penalty independent of scene units and of
  Gaussian size (large Gaussians no longer dominate).
* Scale cap: ``L_cap = 1/(3N) sum_n sum_k relu(s_nk - s_max)^2`` (metres^2), a soft bound that keeps the
  optimiser from growing a few huge Gaussians to paint over unexplained pixels; hard removal of absurd sizes is
  the pruning policy's job.

Empty maps (N = 0) give an exact zero that keeps a gradient path to ``scales``.
"""
from __future__ import annotations

import torch

__all__ = ["isotropy_loss", "scale_cap_loss"]


def _check_scales(scales: torch.Tensor, name: str) -> None:
    if scales.dim() != 2 or scales.shape[1] not in (2, 3):
        raise ValueError(f"{name} expects activated scales of shape [N, 3] (or [N, 2]), got {tuple(scales.shape)}")


def isotropy_loss(scales: torch.Tensor, *, relative: bool = False) -> torch.Tensor:  # [N, 3] metres -> []
    """Mean absolute deviation of each Gaussian's scales from their mean (formula in the module docstring).

    Units: metres (``relative=False``) or dimensionless (``relative=True``).
    """
    _check_scales(scales, "isotropy_loss")
    if scales.shape[0] == 0:
        return scales.sum() * 0.0
    mean_scale = scales.mean(dim=1, keepdim=True)  # [N, 1]
    deviation = scales - mean_scale  # [N, 3]
    if relative:
        deviation = deviation / mean_scale.clamp_min(torch.finfo(scales.dtype).tiny)
    return deviation.abs().mean()


def scale_cap_loss(scales: torch.Tensor, max_scale: float) -> torch.Tensor:  # [N, 3] metres -> [] metres^2
    """Squared excess of each scale over ``max_scale`` (metres), averaged over all N x 3 scales."""
    _check_scales(scales, "scale_cap_loss")
    if not max_scale > 0:
        raise ValueError(f"scale_cap_loss needs max_scale > 0 metres, got {max_scale}")
    if scales.shape[0] == 0:
        return scales.sum() * 0.0
    excess = torch.relu(scales - max_scale)
    return (excess * excess).mean()
