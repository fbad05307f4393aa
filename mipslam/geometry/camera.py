"""Pinhole projection and back-projection (OpenCV camera frame: x right, y down, z forward).

Pixel centres have integer coordinates (docs/design.md), so pixel (u, v) views the ray through
``((u - cx) / fx, (v - cy) / fy, 1)``.
"""
from __future__ import annotations

import torch


def pixel_grid(height: int, width: int, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> torch.Tensor:
    """Pixel-centre coordinates (u, v).  -> [H, W, 2]"""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device), torch.arange(width, dtype=dtype, device=device), indexing="ij"
    )
    return torch.stack([u, v], -1)


def project(points_c: torch.Tensor, K: torch.Tensor, min_depth: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """Project camera-frame points to pixels.

    points_c [..., 3] metres, K [3, 3] -> (uv [..., 2] pixels, z [..., ] metres). Points with
    ``z < min_depth`` get their depth clamped for the division (callers mask them with ``z``).
    """
    z = points_c[..., 2]
    z_safe = z.clamp_min(min_depth)
    u = K[0, 0] * points_c[..., 0] / z_safe + K[0, 2]
    v = K[1, 1] * points_c[..., 1] / z_safe + K[1, 2]
    return torch.stack([u, v], -1), z


def sampling_rate(K: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """Pixels per metre a camera samples at depth z: ``max(fx, fy) / z`` (Mip-Splatting's sampling rate,
    which sizes its 3D filter).  K [3, 3], depth [...] metres -> [...] px/m (differentiable; no clamp)."""
    return torch.maximum(K[0, 0], K[1, 1]).to(depth) / depth


def unproject(uv: torch.Tensor, depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Back-project pixels with depth (z, metres) to camera-frame points.

    uv [..., 2], depth [...], K [3, 3] -> points_c [..., 3]
    """
    x = (uv[..., 0] - K[0, 2]) / K[0, 0] * depth
    y = (uv[..., 1] - K[1, 2]) / K[1, 1] * depth
    return torch.stack([x, y, depth], -1)


def unproject_depth(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Back-project a whole depth image.  depth [H, W] metres, K [3, 3] -> points_c [H, W, 3]"""
    grid = pixel_grid(depth.shape[0], depth.shape[1], dtype=depth.dtype, device=depth.device)
    return unproject(grid, depth, K)
