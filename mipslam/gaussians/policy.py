"""Densify / prune policy as pure functions returning masks ("model only what a scene requires").

- :func:`densify_pixel_mask`: pixels of a keyframe the map does not explain yet: valid depth and
  either low rendered opacity, or the map's surface lies well *behind* the measurement (depth
  error above ``ratio`` times the median error of the covered pixels: something new in front of
  what is mapped; SplaTAM's rule). Pixels where the map is in front of the measurement are not
  densified: a Gaussian behind mapped geometry would be hidden; pruning deals with such floaters.
- :func:`far_from_existing`: of the Gaussians about to be added, those with no existing centre within
  ``ratio`` of their own std-dev: a revisit that misses the old surface by a little re-fits it
  instead of layering a copy over it.
- :func:`cap_pixel_mask`: at most ``budget`` of those pixels, evenly spread over the image.
- :func:`prune_mask`: Gaussians with negligible opacity, non-finite parameters, or an absurd
  size: a std-dev larger than ``max_sigma_px`` pixels when seen from a reference camera
  (``sigma * f / distance``), i.e. relative to the pixel footprint at its distance.
- :func:`cap_count_mask`: the lowest-opacity Gaussians beyond a hard cap on the count.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree


def densify_pixel_mask(
    rendered_alpha: torch.Tensor,  # [H, W] accumulated opacity of the map in this view, in [0, 1]
    rendered_depth: torch.Tensor,  # [H, W] metres, alpha-normalised rendered depth
    depth: torch.Tensor,  # [H, W] measured metres, 0 = no measurement
    *,
    opacity_threshold: float,
    depth_error_ratio: float,
    valid_mask: torch.Tensor | None = None,  # [H, W] bool, extra restriction (e.g. colour valid)
) -> torch.Tensor:
    """Pixels where new Gaussians should go.  -> [H, W] bool

    ``valid & (alpha < opacity_threshold | (D_r - D > ratio * median(|D_r - D|) over covered))``
    where ``covered = valid & alpha >= opacity_threshold``. With no covered pixels only the
    opacity test applies.
    """
    valid = torch.isfinite(depth) & (depth > 0)
    if valid_mask is not None:
        valid &= valid_mask.to(torch.bool)
    uncovered = rendered_alpha < opacity_threshold
    covered = valid & ~uncovered & torch.isfinite(rendered_depth)
    behind = torch.zeros_like(valid)
    if covered.any():
        error = rendered_depth - depth  # > 0: the map's surface is behind the measurement
        median_error = error[covered].abs().median()
        behind = covered & (error > depth_error_ratio * median_error)
    return valid & (uncovered | behind)


def cap_pixel_mask(mask: torch.Tensor, budget: int) -> torch.Tensor:
    """Keep at most ``budget`` True pixels of ``mask`` [H, W], evenly spaced in raster order.  -> [H, W] bool

    Deterministic (no RNG): the i-th kept pixel is candidate ``floor(i * n / budget)``.
    """
    flat = mask.reshape(-1)
    index = torch.nonzero(flat, as_tuple=True)[0]
    count = index.shape[0]
    if count <= budget:
        return mask.clone()
    out = torch.zeros_like(flat)
    if budget > 0:
        pick = (torch.arange(budget, device=mask.device, dtype=torch.float64) * (count / budget)).long()
        out[index[pick]] = True
    return out.reshape(mask.shape)


def distances_to_camera(means: torch.Tensor, T_wc: torch.Tensor) -> torch.Tensor:
    """Euclidean distance of each mean to the camera centre.  means [N, 3], T_wc [4, 4] -> [N] metres"""
    return (means - T_wc[:3, 3].to(means)).norm(dim=-1)


def prune_mask(
    opacities: torch.Tensor,  # [N] activated, in (0, 1)
    scales: torch.Tensor,  # [N, 3] activated std-devs, metres
    distances: torch.Tensor,  # [N] metres, to a reference camera centre (distances_to_camera)
    *,
    focal_px: float,
    min_opacity: float,
    max_sigma_px: float = 50.0,
    means: torch.Tensor | None = None,  # [N, 3]; non-finite rows are pruned when given
    min_distance: float = 1e-2,
) -> torch.Tensor:
    """Gaussians to delete.  -> [N] bool

    ``opacity < min_opacity``, or ``max(scale) * focal_px / max(distance, min_distance) >
    max_sigma_px`` (absurdly large relative to the pixel footprint ``distance / focal_px``), or
    any non-finite value.
    """
    largest = scales.amax(dim=-1)
    footprint_px = largest * focal_px / distances.clamp_min(min_distance)
    bad = ~torch.isfinite(opacities) | ~torch.isfinite(scales).all(dim=-1) | ~torch.isfinite(distances)
    if means is not None:
        bad |= ~torch.isfinite(means).all(dim=-1)
    return bad | (opacities < min_opacity) | (footprint_px > max_sigma_px)


def cap_count_mask(opacities: torch.Tensor, max_count: int) -> torch.Tensor:
    """Gaussians to delete so that at most ``max_count`` remain: the least opaque.  opacities [N] -> [N] bool

    Ties are broken by index (older Gaussians, at lower indices, are kept first).
    """
    count = opacities.shape[0]
    remove = torch.zeros(count, dtype=torch.bool, device=opacities.device)
    excess = count - max_count
    if excess <= 0:
        return remove
    # stable sort of the reversed array: among equal opacities the newest (highest index) come first
    keys = torch.nan_to_num(opacities, nan=-1.0).flip(0)
    order = count - 1 - torch.argsort(keys, stable=True)
    remove[order[:excess]] = True
    return remove


def far_from_existing(
    new_means: torch.Tensor,  # [M, 3] world metres
    new_sigmas: torch.Tensor,  # [M] metres, std-dev of each new Gaussian
    existing_means: torch.Tensor,  # [N, 3] world metres
    ratio: float,
) -> torch.Tensor:  # [M] bool
    """True where no existing centre lies within ``ratio * new_sigmas`` of the new centre (a k-d tree query).

    ``ratio <= 0`` or an empty map keeps every new Gaussian.
    """
    keep = torch.ones(new_means.shape[0], dtype=torch.bool, device=new_means.device)
    if ratio <= 0 or existing_means.shape[0] == 0 or new_means.shape[0] == 0:
        return keep
    radius = (ratio * new_sigmas).detach().double().cpu().numpy()
    tree = cKDTree(existing_means.detach().double().cpu().numpy())
    distance, _ = tree.query(new_means.detach().double().cpu().numpy(), k=1, distance_upper_bound=float(radius.max()))
    near = np.asarray(distance) <= radius  # a miss is inf
    return torch.from_numpy(~near).to(new_means.device)
