"""The bridge between the render config and the pure renderer: one call renders a map from a pose.

``mipslam.render`` imports no config (pure functions on tensors); tracking, mapping and evaluation
render through :func:`render_view`, which turns a :class:`~mipslam.config.RenderConfig` into the
renderer's keyword options.
"""
from __future__ import annotations

import torch

from mipslam.config import RenderConfig
from mipslam.gaussians import ActivatedGaussians
from mipslam.render import RenderOutput, rasterize
from mipslam.types import Intrinsics


def render_options(config: RenderConfig) -> dict:
    """Keyword options of :func:`mipslam.render.rasterize` for a render config."""
    return {
        "near_plane": config.near_plane,
        "k_sigma": config.eaa_k_sigma,
        "eaa_max_nodes": config.eaa_max_nodes,
        "eaa_gamma": config.eaa_gamma,
        "eaa_eta": config.eaa_eta,
        "eaa_tau": config.eaa_tau,
        "eaa_single_node_sigma": config.eaa_single_node_sigma,
        "filter_3d_scale": config.filter_3d_scale if config.filter_3d else None,
    }


def render_view(
    gaussians: ActivatedGaussians,
    T_cw: torch.Tensor,  # [4, 4] world-to-camera, float32 on the map's device (may require grad)
    intrinsics: Intrinsics,
    config: RenderConfig,
    *,
    mode: str | None = None,
    pose_only: bool = False,
    normalized_depth: bool = False,
) -> RenderOutput:
    """Render the map at ``intrinsics`` from ``T_cw`` with the configured footprint mode and backend.

    ``pose_only`` asks the renderer for gradients with respect to ``T_cw`` alone (tracking).
    """
    dtype, device = gaussians.means.dtype, gaussians.means.device
    return rasterize(
        gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.colors,
        T_cw.to(dtype=dtype, device=device), intrinsics.matrix(dtype=dtype, device=device),
        intrinsics.width, intrinsics.height, mode=mode or config.mode, backend=config.backend,
        pose_only=pose_only, normalized_depth=normalized_depth, **render_options(config),
    )
