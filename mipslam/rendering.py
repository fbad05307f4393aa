"""The bridge between the render config and the pure renderer: one call renders a map from a pose.

``mipslam.render`` imports no config (pure functions on tensors); tracking, mapping and evaluation
render through :func:`render_view`, which turns a :class:`~mipslam.config.RenderConfig` into the
renderer's keyword options (the renderer's constants are :class:`~mipslam.render.RenderOptions`' defaults).
"""
from __future__ import annotations

import torch

from mipslam.config import RenderConfig
from mipslam.gaussians import ActivatedGaussians
from mipslam.geometry.camera import project, sampling_rate
from mipslam.geometry.se3 import transform_points
from mipslam.render import RenderOptions, RenderOutput, compiled_library, rasterize, rasterize_pose_only
from mipslam.types import Intrinsics


# Strength s of the Mip-Splatting 3D filter (render.filter_3d): the paper's 0.2.
FILTER_3D_SCALE = 0.2
# Tracking and mapping render a view from the Gaussians that reach its image enlarged by this fraction of the
# larger side, at the pose the view starts from (0.25: about 16 degrees of a 70-degree view, far beyond what one
# optimisation moves a pose); the rest of the map cannot be drawn and is left out.
FRUSTUM_MARGIN = 0.25


def render_options(config: RenderConfig) -> dict:
    """Keyword options of :func:`mipslam.render.rasterize` for a render config."""
    return {"eaa_max_nodes": config.eaa_max_nodes, "filter_3d_scale": FILTER_3D_SCALE if config.filter_3d else None}


def render_view(
    gaussians: ActivatedGaussians,
    T_cw: torch.Tensor,  # [4, 4] world-to-camera, float32 on the map's device (may require grad)
    intrinsics: Intrinsics,
    config: RenderConfig,
    *,
    mode: str | None = None,
    pose_only: bool = False,
    normalized_depth: bool = False,
    appearance_color: bool = False,
) -> RenderOutput:
    """Render the map at ``intrinsics`` from ``T_cw`` with the configured footprint mode and backend.

    ``pose_only`` asks the renderer for gradients with respect to ``T_cw`` alone (tracking). With
    ``render.filter_3d`` the 3D filter is sized by the map's own sampling rates
    (:func:`filter_sampling_rates`), so it is the same at every resolution and pose that renders the map.
    """
    dtype, device = gaussians.means.dtype, gaussians.means.device
    T_cw = T_cw.to(dtype=dtype, device=device)
    K = intrinsics.matrix(dtype=dtype, device=device)
    rates = filter_sampling_rates(gaussians, T_cw, K) if config.filter_3d else None  # None: the renderer's own
    return rasterize(
        gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.colors,
        T_cw, K, intrinsics.width, intrinsics.height, mode=mode or config.mode, backend=config.backend,
        pose_only=pose_only, normalized_depth=normalized_depth, appearance_color=appearance_color,
        max_sampling_rate=rates, **render_options(config),
    )


def render_view_pose_only(
    gaussians: ActivatedGaussians,
    T_cw: torch.Tensor,  # [4, 4] world-to-camera, the map's dtype and device
    intrinsics: Intrinsics,
    config: RenderConfig,
    *,
    mode: str | None = None,
):
    """:func:`render_view` with ``pose_only`` and the backward to ``T_cw`` written out
    (:func:`mipslam.render.rasterize_pose_only`): a :class:`mipslam.render.cpu.PoseOnlyRender`, or None where
    only autograd can render the call (render with :func:`render_view` then)."""
    dtype, device = gaussians.means.dtype, gaussians.means.device
    T_cw = T_cw.to(dtype=dtype, device=device)
    K = intrinsics.matrix(dtype=dtype, device=device)
    rates = filter_sampling_rates(gaussians, T_cw, K) if config.filter_3d else None
    return rasterize_pose_only(
        gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.colors,
        T_cw, K, intrinsics.width, intrinsics.height, mode=mode or config.mode, backend=config.backend,
        max_sampling_rate=rates, **render_options(config),
    )


@torch.no_grad()
def filter_sampling_rates(
    gaussians: ActivatedGaussians,
    T_cw: torch.Tensor,  # [4, 4] world-to-camera of the render
    K: torch.Tensor,  # [3, 3] intrinsics of the render, pixels
) -> torch.Tensor | None:  # [N] px/m
    """The sampling rate that sizes each Gaussian's 3D filter: the map's ``max_sampling_rate``.

    Where the map does not know it (0: a PLY written without it, a checkpoint from before it existed)
    this camera's ``max(fx, fy) / z`` stands in. When no rate is known at all the result is None, and the
    renderer computes that same per-camera value itself.
    """
    stored = gaussians.max_sampling_rate
    known = None if stored is None else stored > 0  # [N]
    if known is None or not bool(known.any()):
        return None
    means = gaussians.means.detach()
    if bool(known.all()):
        return stored.to(means)
    z = transform_points(T_cw.to(means), means)[:, 2]
    return torch.where(known, stored.to(means), sampling_rate(K.to(means), z.clamp_min(1e-6)))


@torch.no_grad()
def view_sampling_rates(
    means: torch.Tensor,  # [N, 3] world, metres
    T_cw: torch.Tensor,  # [4, 4] world-to-camera of a training view
    intrinsics: Intrinsics,
) -> torch.Tensor:  # [N] px/m, 0 where the view does not see the centre
    """Mip-Splatting's sampling rate of each centre in one training view (Yu et al., 2024, section 4.1):
    ``max(fx, fy) / z`` where the centre lies in front of the camera and projects into the image
    enlarged by 15 % of its size on every side (their visibility test), else 0."""
    points_c = transform_points(T_cw.to(means), means.detach())  # [N, 3]
    K = intrinsics.matrix(dtype=means.dtype, device=means.device)
    uv, z = project(points_c, K, min_depth=1e-6)
    margin_u, margin_v = 0.15 * intrinsics.width, 0.15 * intrinsics.height
    inside = ((z > 1e-6) & (uv[:, 0] >= -0.5 - margin_u) & (uv[:, 0] <= intrinsics.width - 0.5 + margin_u)
              & (uv[:, 1] >= -0.5 - margin_v) & (uv[:, 1] <= intrinsics.height - 0.5 + margin_v))
    rate = sampling_rate(K, z.clamp_min(1e-6))
    return torch.where(inside, rate, torch.zeros_like(rate))


@torch.no_grad()
def frustum_indices(
    means: torch.Tensor,  # [N, 3] world, metres
    scales: torch.Tensor,  # [N, 3] std-devs, metres
    T_cw: torch.Tensor,  # [4, 4] world-to-camera of the pose the view starts from
    intrinsics: Intrinsics,
    config: RenderConfig,
) -> torch.Tensor:  # [M] int64, increasing
    """Rows of the Gaussians that can be drawn from poses near ``T_cw`` (:data:`FRUSTUM_MARGIN`).

    A Gaussian is kept when its mean lies beyond half the near plane and its k-sigma disc (radius
    ``k_sigma * max scale * f / z`` px, plus a pixel) reaches the image enlarged by ``FRUSTUM_MARGIN``
    times its larger side on every side. One tracking or mapping call moves a pose by millimetres to
    centimetres, while a margin of 0.25 is about 16 degrees of a 70-degree view: a Gaussian left out is
    one no render of the view could draw, so images and gradients are those of the whole map, and the
    per-Gaussian projection scales with what the view sees, not with the size of the map.

    One pass of the compiled library where ``config.backend`` takes it and the map is CPU float32 (the test in
    float64: it decides as :func:`frustum_indices_reference` except within ~1e-5 px of a limit, where the
    Gaussian is a quarter of the image outside it and no render draws it); the torch reference elsewhere.
    """
    library = compiled_library() if (config.backend != "torch" and means.is_cpu
                                     and means.dtype == torch.float32 == scales.dtype) else None
    if library is None:
        return frustum_indices_reference(means, scales, T_cw, intrinsics)
    T = T_cw.detach().to("cpu", torch.float64)
    view = tuple(T[:3, :3].reshape(-1).tolist()) + tuple(T[:3, 3].tolist()) + (
        intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
    near, pad = _frustum_limits(intrinsics)
    return library.frustum_rows(means, scales, view,
                                (intrinsics.width, intrinsics.height, near, RenderOptions.k_sigma, pad))


def _frustum_limits(intrinsics: Intrinsics) -> tuple[float, float]:
    """The frustum test's near limit (metres, half the near plane) and the pad (px) its discs reach beyond the
    image: FRUSTUM_MARGIN times the larger side, plus a pixel."""
    return 0.5 * RenderOptions.near_plane, FRUSTUM_MARGIN * max(intrinsics.width, intrinsics.height) + 1.0


@torch.no_grad()
def frustum_indices_reference(
    means: torch.Tensor,  # [N, 3] world, metres
    scales: torch.Tensor,  # [N, 3] std-devs, metres
    T_cw: torch.Tensor,  # [4, 4] world-to-camera
    intrinsics: Intrinsics,
) -> torch.Tensor:  # [M] int64, increasing
    """:func:`frustum_indices` in torch (any device and dtype): the readable reference the compiled test is
    checked against."""
    near, pad = _frustum_limits(intrinsics)
    points_c = transform_points(T_cw.to(means), means.detach())  # [N, 3] camera frame
    uv, z = project(points_c, intrinsics.matrix(dtype=means.dtype, device=means.device), min_depth=near)  # [N, 2] px
    reach = RenderOptions.k_sigma * scales.detach().amax(dim=-1) * max(intrinsics.fx, intrinsics.fy) / z.clamp_min(near)
    reach = reach + pad  # [N] px
    u, v = uv[:, 0], uv[:, 1]
    keep = ((z > near) & (u + reach > -0.5) & (u - reach < intrinsics.width - 0.5)
            & (v + reach > -0.5) & (v - reach < intrinsics.height - 0.5))
    return torch.nonzero(keep).squeeze(1)


def frustum_subset(gaussians: ActivatedGaussians, T_cw: torch.Tensor, intrinsics: Intrinsics,
                   config: RenderConfig) -> ActivatedGaussians:
    """The detached rows of a frozen map that :func:`frustum_indices` keeps (tracking)."""
    index = frustum_indices(gaussians.means, gaussians.scales, T_cw, intrinsics, config)
    return gaussians.detached().rows(index)
