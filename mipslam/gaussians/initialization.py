"""New Gaussians from an RGB-D frame: one isotropic Gaussian per selected pixel with valid depth.

A pixel (u, v) with depth z back-projects to ``p_c = z K^-1 (u, v, 1)`` and to the world by
``T_wc``. It covers a patch of the surface ``z / fx`` by ``z / fy`` metres (its footprint); with
every ``pixel_stride``-th pixel sampled each Gaussian stands for ``stride^2`` pixels, so its
std-dev is ``sigma = scale_factor * stride * z / f`` with ``f = sqrt(fx fy)`` (the SplaTAM
choice, where ``sigma = z / f``), the same along all three axes; rotation identity, colour the
pixel's, opacity ``initial_opacity``.
"""
from __future__ import annotations

import math

import torch

from mipslam.gaussians.model import GaussianParameters, color_logit
from mipslam.geometry.camera import sampling_rate, unproject
from mipslam.geometry.se3 import transform_points


def gaussians_from_rgbd(
    color: torch.Tensor,  # [H, W, 3] float in [0, 1]
    depth: torch.Tensor,  # [H, W] metres, 0 = no measurement
    K: torch.Tensor,  # [3, 3]
    T_wc: torch.Tensor,  # [4, 4] camera to world
    mask: torch.Tensor | None = None,  # [H, W] bool, where Gaussians may be added
    *,
    initial_opacity: float = 0.5,
    anchor_keyframe: int = -1,
    created_frame: int = -1,
    pixel_stride: int = 1,
    scale_factor: float = 1.0,
    min_depth: float = 1e-3,
    max_depth: float = math.inf,
) -> GaussianParameters:
    """Gaussians for the pixels of ``mask`` that have finite depth in [min_depth, max_depth].

    Pixels are taken on the grid ``(stride*i, stride*j)``; the result is on the device and
    dtype of ``depth`` (colour converted). Returns raw parameters for ``GaussianMap.add``:
    means [M, 3] world metres, quats_wxyz [M, 4] = (1, 0, 0, 0), log_scales [M, 3] = log sigma,
    opacity_logits [M] = logit(initial_opacity), colors_raw [M, 3] = logit(rgb), anchor and
    created ids [M], max_sampling_rate [M] = max(fx, fy) / z px/m.
    """
    height, width = depth.shape
    if color.shape[:2] != (height, width) or color.shape[-1] != 3:
        raise ValueError(f"color must be [H, W, 3] matching depth {tuple(depth.shape)}, got {tuple(color.shape)}")
    if not 0.0 < initial_opacity < 1.0:
        raise ValueError(f"initial_opacity must be in (0, 1), got {initial_opacity}")
    if pixel_stride < 1:
        raise ValueError(f"pixel_stride must be >= 1, got {pixel_stride}")
    device, dtype = depth.device, depth.dtype
    valid = torch.isfinite(depth) & (depth >= min_depth) & (depth <= max_depth)
    if mask is not None:
        if tuple(mask.shape) != (height, width):
            raise ValueError(f"mask must be [H, W] = {(height, width)}, got {tuple(mask.shape)}")
        valid &= mask.to(device=device, dtype=torch.bool)
    grid = torch.zeros_like(valid)
    grid[::pixel_stride, ::pixel_stride] = True
    valid &= grid
    v, u = torch.nonzero(valid, as_tuple=True)
    z = depth[v, u]  # [M]
    K = K.to(device=device, dtype=dtype)
    uv = torch.stack([u, v], -1).to(dtype)  # [M, 2]
    points_c = unproject(uv, z, K)  # [M, 3]
    means = transform_points(T_wc.to(device=device, dtype=dtype), points_c)
    focal = torch.sqrt(K[0, 0] * K[1, 1])
    sigma = scale_factor * pixel_stride * z / focal  # [M]
    count = z.shape[0]
    quats = torch.zeros((count, 4), dtype=dtype, device=device)
    quats[:, 0] = 1.0
    rgb = color.to(device=device, dtype=dtype)[v, u]  # [M, 3]
    return GaussianParameters(
        means=means,
        quats_wxyz=quats,
        log_scales=torch.log(sigma).unsqueeze(-1).expand(count, 3).clone(),
        opacity_logits=torch.full((count,), math.log(initial_opacity / (1.0 - initial_opacity)), dtype=dtype, device=device),
        colors_raw=color_logit(rgb),
        anchor_keyframe=torch.full((count,), int(anchor_keyframe), dtype=torch.int64, device=device),
        created_frame=torch.full((count,), int(created_frame), dtype=torch.int64, device=device),
        max_sampling_rate=sampling_rate(K, z),  # the rate of the view that creates it
    )


def fill_depth_holes(depth: torch.Tensor, max_distance_px: int) -> torch.Tensor:  # [H, W] metres -> [H, W]
    """``depth`` with each pixel that has no measurement (0 or not finite) within ``max_distance_px`` (chessboard
    distance) of a measured one given the farthest measured depth among its nearest measured neighbours; the rest
    stay 0.

    A Kinect-type sensor leaves a quarter of its pixels without depth: bands along the image borders (the depth
    camera sees less than the colour camera), object edges (occlusion shadows) and dark or shiny surfaces. Their
    colour is real, and without Gaussians there a view renders them black. Growing the measured depth into them
    ring by ring (3x3 max filter) places such Gaussians at the depth of the surface beside them, biased towards the
    background, which is what an occlusion shadow at an object's edge shows.
    """
    filled = torch.where(torch.isfinite(depth) & (depth > 0), depth, torch.zeros_like(depth))
    measured = filled > 0
    if not bool(measured.any()):
        return filled
    for _ in range(max(0, int(max_distance_px))):
        missing = ~measured
        if not bool(missing.any()):
            break
        grown = torch.nn.functional.max_pool2d(filled[None, None], 3, stride=1, padding=1)[0, 0]
        new = missing & (grown > 0)
        if not bool(new.any()):
            break
        filled = torch.where(new, grown, filled)
        measured = measured | new
    return filled
