"""The pure-PyTorch backend end to end, and the :class:`RenderOutput` that every backend returns.

:func:`rasterize_torch` is the reference backend of :func:`mipslam.render.rasterize` (projection, the per-pixel
stage, the bookkeeping); the compiled CPU backend (:mod:`mipslam.render.cpu.backend`) shares it with its own
per-pixel stage. Both import it from here, so the package's front (``mipslam.render``) and its compiled backend do
not import each other (docs/design.md "Import layers").
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from mipslam.errors import RenderError
from mipslam.render.footprint import EXACT_K_SIGMA, MODE_DILATION
from mipslam.render.projection import project_gaussians
from mipslam.render.rasterize_torch import FootprintSettings, rasterize_projected

if TYPE_CHECKING:
    from mipslam.render import RenderOptions


@dataclass(frozen=True)
class RenderOutput:
    """Rendered images and per-Gaussian bookkeeping.

    color            [H, W, C]  composited colour on black
    depth            [H, W]     sum of T * alpha * z (metres)
    alpha            [H, W]     accumulated opacity 1 - T
    depth_normalized [H, W]     depth / alpha where alpha > 1e-6, else 0 (None unless asked)
    means2d          [N, 2] px  projected centres, part of the graph (``retain_grad()`` it before backward
                                for the 3DGS view-space gradient used by densification)
    radii            [N] px     k-sigma half extent (max of x and y) of the footprint, 0 where not visible
    visible          [N] bool   drawn (finite, in front of the near plane, on screen, opacity > 0)
    n_visible        int
    depths           [N] metres camera-frame z (0 where not visible)
    mode, backend    str
    color_appearance [H, W, C]  the values of color; its gradient reaches the colours only, as if it were
                                rendered with the geometry and the camera held fixed (None unless asked)
    """

    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    depth_normalized: torch.Tensor | None
    means2d: torch.Tensor
    radii: torch.Tensor
    visible: torch.Tensor
    n_visible: int
    depths: torch.Tensor
    mode: str
    backend: str
    color_appearance: torch.Tensor | None = None


def check_camera_values(viewmat, K):
    """The camera's values (the cpu backend checks them in C++, without these tensor operations)."""
    if not (torch.isfinite(viewmat).all() and torch.isfinite(K).all()):
        raise RenderError("rasterize: viewmat and K must be finite (a NaN pose cannot be rendered; check the "
                          "tracking result that produced it)")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise RenderError(f"rasterize: focal lengths must be positive, got fx={float(K[0, 0])}, fy={float(K[1, 1])}")


def rasterize_torch(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, mode: str,
                    opts: RenderOptions, *, rasterizer=rasterize_projected) -> RenderOutput:
    """The pure-PyTorch backend (inputs already checked by :func:`rasterize`).

    ``rasterizer`` is the per-pixel stage (:func:`mipslam.render.rasterize_torch.rasterize_projected`
    signature: ``(proj, width, height, settings, *, tile_size, pair_budget, checkpoint)`` returning an
    object with ``color``, ``depth`` and ``alpha``); the compiled CPU backend passes its own, so the
    projection and the bookkeeping are shared code.
    """
    if opts.pose_only:
        means, quats, scales, opacities, colors = (t.detach() for t in (means, quats, scales, opacities, colors))
    box_mode = mode in ("eaa", "exact")
    proj = project_gaussians(
        means, quats, scales, opacities, colors, viewmat, K, width, height, near_plane=opts.near_plane,
        far_plane=opts.far_plane, extent_sigma=EXACT_K_SIGMA if mode == "exact" else opts.k_sigma,
        extent_pad=0.5 if box_mode else 0.0, extent_dilation=MODE_DILATION.get(mode, 0.0),
        filter_3d_scale=opts.filter_3d_scale,
        max_sampling_rate=opts.max_sampling_rate)
    settings = FootprintSettings(mode=mode, k_sigma=opts.k_sigma, max_nodes=int(opts.eaa_max_nodes),
                                 gamma=opts.eaa_gamma, eta=opts.eaa_eta, tau=opts.eaa_tau,
                                 single_node_sigma=opts.eaa_single_node_sigma, exact_order=opts.exact_order)
    image = rasterizer(proj, width, height, settings, tile_size=opts.tile_size, pair_budget=opts.pair_budget,
                       checkpoint=opts.checkpoint, appearance=opts.appearance_color)
    depth_normalized = None
    if opts.normalized_depth:
        has_alpha = image.alpha > 1e-6
        depth_normalized = torch.where(has_alpha, image.depth / image.alpha.clamp_min(1e-6),
                                       torch.zeros_like(image.depth))
    with torch.no_grad():
        dilation = MODE_DILATION.get(mode, 0.0)
        ext = opts.k_sigma * torch.sqrt(torch.maximum(proj.cov2d[:, 0], proj.cov2d[:, 2]) + dilation)
        radii = torch.where(proj.visible, ext + (0.5 if box_mode else 0.0), torch.zeros_like(ext))
    return RenderOutput(color=image.color, depth=image.depth, alpha=image.alpha, depth_normalized=depth_normalized,
                        means2d=proj.means2d, radii=radii, visible=proj.visible,
                        n_visible=int(proj.visible.sum()), depths=proj.depths, mode=mode, backend="torch",
                        color_appearance=image.color_appearance)
