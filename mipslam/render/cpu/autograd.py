"""The torch.autograd.Functions of the compiled backend: the fused projection (:class:`ProjectFootprints`,
projection.h) and the tile rasterizer (:class:`RasterizeProjected`), each with the library's hand-written
backward, and the projection settings of each mode as the torch reference uses them."""
from __future__ import annotations

import functools

import torch

from mipslam.render import footprint, projection
from mipslam.render.cpu.library import load_extension

# Order of the parameter vector of projection.h (enum ProjectionParam).
_PROJECTION_PARAM_NAMES = (
    "near", "far", "extent_sigma", "extent_pad", "extent_dilation", "filter_scale", "dilation", "dilation_sq",
    "energy", "eaa", "max_nodes", "gamma", "single_node_sigma", "box_variance", "radius_sigma", "radius_pad",
    "cov_floor", "cov_floor_sq", "fov_margin", "max_sigma_px", "max_tangent")


@functools.lru_cache(maxsize=64)
def _projection_params(mode: str, near_plane: float, far_plane: float, k_sigma: float, filter_3d_scale: float,
                       max_nodes: int, gamma: float, single_node_sigma: float) -> tuple[float, ...]:
    """The settings of the fused projection for one mode and option set, exactly as
    :func:`mipslam.render.rasterize_torch` passes them to the torch reference (cached per option set)."""
    box_mode = mode in ("eaa", "exact")
    dilation = footprint.MODE_DILATION.get(mode, 0.0)
    values = {
        "near": near_plane, "far": far_plane,
        "extent_sigma": footprint.EXACT_K_SIGMA if mode == "exact" else k_sigma,
        "extent_pad": 0.5 if box_mode else 0.0, "extent_dilation": dilation,
        "filter_scale": float(filter_3d_scale or 0.0),
        "dilation": dilation, "dilation_sq": dilation * dilation,
        "energy": 1.0 if mode in footprint.ENERGY_PRESERVING else 0.0, "eaa": 1.0 if mode == "eaa" else 0.0,
        "max_nodes": float(max_nodes), "gamma": gamma, "single_node_sigma": single_node_sigma,
        "box_variance": footprint.EAA_BOX_VARIANCE,
        "radius_sigma": k_sigma, "radius_pad": 0.5 if box_mode else 0.0,
        "cov_floor": projection.COV_FLOOR, "cov_floor_sq": projection.COV_FLOOR * projection.COV_FLOOR,
        "fov_margin": projection.FOV_MARGIN, "max_sigma_px": projection.MAX_SIGMA_PX,
        "max_tangent": projection.MAX_TANGENT,
    }
    return tuple(float(values[name]) for name in _PROJECTION_PARAM_NAMES)


def _params_for(mode: str, options) -> tuple[float, ...]:
    return _projection_params(mode, float(options.near_plane), float(options.far_plane), float(options.k_sigma),
                              float(options.filter_3d_scale or 0.0), int(options.eaa_max_nodes),
                              float(options.eaa_gamma), float(options.eaa_single_node_sigma))


def _opacity_has_pose_gradient(params: tuple[float, ...]) -> bool:
    """Whether the mode's opacity depends on the geometry (an energy factor: mip, ewa, EAA's single node; or the
    3D filter), so that a geometry or viewmat gradient flows through it as well."""
    return (params[_PROJECTION_PARAM_NAMES.index("energy")] != 0.0
            or params[_PROJECTION_PARAM_NAMES.index("eaa")] != 0.0
            or params[_PROJECTION_PARAM_NAMES.index("filter_scale")] != 0.0)


class ProjectFootprints(torch.autograd.Function):
    """Fused projection + footprint parameters + EAA node counts + radii (projection.h), with a hand-written
    backward to means, quats, scales, opacities and the viewmat (K and the sampling rate are constants).

    Inputs: means [N, 3], quats [N, 4], scales [N, 3], opacities [N], viewmat [4, 4], colors [N, C] (only their
    finiteness matters here), K [3, 3], max_sampling_rate [N] or None, then plain settings. Outputs: means2d
    [N, 2] px, depths [N] m, cov [N, 4] (the mode's xx, xy, yy px^2 and det px^4), opacity [N] (the mode's),
    node_counts [N] int32, visible [N] bool, radii [N] px (the last three without gradient), and the number of
    visible Gaussians (int).
    """

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, colors, K, rate, width: int, height: int,
                params: tuple, threads: int):
        means2d, depths, cov, opacity, node_counts, visible, radii, n_visible = load_extension().project_forward(
            means, quats, scales, opacities, colors, viewmat, K, rate, width, height, params, threads)
        ctx.save_for_backward(means, quats, scales, opacities, viewmat, colors, K, rate, visible)
        ctx.settings = (width, height, params, threads)
        ctx.set_materialize_grads(False)
        ctx.mark_non_differentiable(node_counts, visible, radii)
        # The mode's opacity depends on the geometry only through an energy factor (mip, ewa, EAA's single
        # node) or the 3D filter; without them and without an opacity gradient it is a constant, so the
        # rasterizer skips its opacity sums.
        needs = ctx.needs_input_grad
        if not (needs[3] or (_opacity_has_pose_gradient(params) and (any(needs[:3]) or needs[4]))):
            ctx.mark_non_differentiable(opacity)
        return means2d, depths, cov, opacity, node_counts, visible, radii, n_visible

    @staticmethod
    def backward(ctx, g_means2d, g_depths, g_cov, g_opacity, _g_nodes, _g_visible, _g_radii, _g_count):
        means, quats, scales, opacities, viewmat, colors, K, rate, visible = ctx.saved_tensors
        width, height, params, threads = ctx.settings
        needs = ctx.needs_input_grad
        need_params = any(needs[:4])
        g_means, g_quats, g_scales, g_opacities, g_viewmat = load_extension().project_backward(
            means, quats, scales, opacities, colors, viewmat, K, rate, width, height, params, visible, g_means2d,
            g_depths, g_cov, g_opacity, need_params, bool(needs[4]), threads)
        return (g_means if needs[0] else None, g_quats if needs[1] else None, g_scales if needs[2] else None,
                g_opacities if needs[3] else None, g_viewmat if needs[4] else None) + (None,) * 7


@functools.lru_cache(maxsize=8)
def _gauss_legendre_f32(order: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss-Legendre nodes and weights (float32, CPU), built once per order."""
    return footprint.gauss_legendre(order, torch.float32, "cpu")


class RasterizeProjected(torch.autograd.Function):
    """Per-pixel part of the renderer in C++: projected Gaussians -> (color, depth, alpha, stats).

    Inputs (float32, contiguous): means2d [N, 2] px, cov [N, 4] (xx, xy, yy, det) of the mode's sampling
    covariance, opacity [N] (the mode's), depth [N] metres, colors [N, C]; node_counts [N] int32; then
    plain settings. Outputs color [H, W, C], depth [H, W], alpha [H, W], stats [2] int64 (footprint
    lanes evaluated, (tile, Gaussian) pairs) and, with ``appearance``, color_appearance [H, W, C]: the same
    values as color, whose gradient reaches ``colors`` alone (an appearance loss that must not move the
    geometry; None without ``appearance``). The backward is the extension's hand-written one; it skips
    the colour sums when ``colors`` needs no gradient and the opacity sums when ``opacity`` needs none
    (pose-only tracking).
    """

    @staticmethod
    def forward(ctx, means2d, cov, opacity, depth, colors, node_counts, mode_id: int, width: int, height: int,
                k_sigma: float, eta: float, tau: float, gl_nodes, gl_weights, threads: int, appearance: bool = False):
        ext = load_extension()
        (color, depth_img, alpha_img, order, tile_offsets, isect_ids, pair_offsets, isect_pos, last,
         stats) = ext.rasterize_forward(means2d, cov, opacity, depth, colors, node_counts, mode_id, width, height,
                                        k_sigma, eta, tau, gl_nodes, gl_weights, threads)
        ctx.settings = (mode_id, width, height, k_sigma, eta, tau, threads)
        ctx.save_for_backward(means2d, cov, opacity, depth, colors, node_counts, gl_nodes, gl_weights, order,
                              tile_offsets, isect_ids, pair_offsets, isect_pos, last, color, depth_img, alpha_img)
        ctx.mark_non_differentiable(stats)
        return color, depth_img, alpha_img, stats, color.clone() if appearance else None

    @staticmethod
    def backward(ctx, grad_color, grad_depth, grad_alpha, _grad_stats, grad_color_appearance=None):
        (means2d, cov, opacity, depth, colors, node_counts, gl_nodes, gl_weights, order, tile_offsets, isect_ids,
         pair_offsets, isect_pos, last, color, depth_img, alpha_img) = ctx.saved_tensors
        mode_id, width, height, k_sigma, eta, tau, threads = ctx.settings

        def dense(grad, like):
            return torch.zeros_like(like) if grad is None else grad.contiguous().to(torch.float32)

        need = ctx.needs_input_grad
        g_means2d, g_cov, g_opacity, g_depth, g_colors = load_extension().rasterize_backward(
            means2d, cov, opacity, depth, colors, node_counts, mode_id, width, height, k_sigma, eta, tau, gl_nodes,
            gl_weights, order, tile_offsets, isect_ids, pair_offsets, isect_pos, last, color, depth_img, alpha_img,
            dense(grad_color, color), dense(grad_depth, depth_img), dense(grad_alpha, alpha_img), bool(need[4]),
            bool(need[2]), threads,
            None if grad_color_appearance is None else grad_color_appearance.contiguous().to(torch.float32))
        return (g_means2d if need[0] else None, g_cov if need[1] else None, g_opacity if need[2] else None,
                g_depth if need[3] else None, g_colors if need[4] else None) + (None,) * 11
