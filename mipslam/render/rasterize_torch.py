"""Pure-PyTorch tile rasterizer: the reference backend, device-agnostic and differentiable.

Layout (the same as the 3DGS/gsplat CUDA rasterizers, expressed with tensor ops):

1. the visible Gaussians are sorted by depth (stable);
2. each Gaussian is binned into the ``tile_size x tile_size`` tiles (8 by default: on pixel-sized
   splats that evaluates 2.5x fewer padded pairs than 16 at the cost of 1.7x more list entries) its k-sigma box (grown by half
   a pixel for the box-integral modes) touches, giving (tile, Gaussian) pairs; a stable sort by tile
   keeps each tile's list in depth order;
3. tiles are processed in batches whose padded work ``tiles x pixels x list length x nodes`` stays
   under ``pair_budget``: per batch the per-pixel opacities ``[B, tile pixels, L]`` are evaluated by
   :mod:`mipslam.render.footprint` and composited by :mod:`mipslam.render.composite`;
4. tile images are assembled with out-of-place ``index_copy`` (autograd-friendly) and cropped.

With ``checkpoint=True`` each batch runs under ``torch.utils.checkpoint`` so the backward pass
recomputes it instead of storing it: memory is then bounded by one batch.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch.utils.checkpoint import checkpoint as torch_checkpoint

from mipslam.render import footprint
from mipslam.render.composite import blend_weights, clamp_alpha, composite_weighted
from mipslam.render.projection import ProjectedGaussians


#: Padded (pixel, Gaussian, node) evaluations above which ``checkpoint=None`` recomputes in backward.
CHECKPOINT_WORK = 1 << 24


@dataclass(frozen=True)
class FootprintSettings:
    """What the per-pixel stage needs to know (plain numbers, shared by all batches)."""

    mode: str
    k_sigma: float
    max_nodes: int
    gamma: float
    eta: float
    tau: float
    single_node_sigma: float
    exact_order: int


@dataclass(frozen=True)
class TiledImage:
    """Raw rasterizer output.  color [H, W, C], depth [H, W], alpha [H, W]; color_appearance [H, W, C] or None
    (``appearance``: the colour again, composited with the blending weights detached)"""

    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    color_appearance: torch.Tensor | None = None


def bin_gaussians(means2d: torch.Tensor, ext_x: torch.Tensor, ext_y: torch.Tensor, tiles_x: int, tiles_y: int,
                  tile_size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(tile, Gaussian) pairs, sorted by tile and, within a tile, by the input order.

    means2d [M, 2] px, ext_x/ext_y [M] half extents px (the Gaussians' order is kept in each tile)
    -> (pair_tile [P] int64, pair_gaussian [P] int64).
    """
    device = means2d.device
    with torch.no_grad():
        # Continuous x in [t * ts - 0.5, (t + 1) * ts - 0.5) belongs to tile t.
        x0 = torch.floor((means2d[:, 0] - ext_x + 0.5) / tile_size).clamp(0, tiles_x - 1).long()
        x1 = torch.floor((means2d[:, 0] + ext_x + 0.5) / tile_size).clamp(0, tiles_x - 1).long()
        y0 = torch.floor((means2d[:, 1] - ext_y + 0.5) / tile_size).clamp(0, tiles_y - 1).long()
        y1 = torch.floor((means2d[:, 1] + ext_y + 0.5) / tile_size).clamp(0, tiles_y - 1).long()
        span_x = x1 - x0 + 1
        counts = span_x * (y1 - y0 + 1)  # [M]
        total = int(counts.sum())
        ends = torch.cumsum(counts, 0)
        # Owner of each pair (a repeat_interleave; searchsorted avoids its fixed cost on small inputs).
        gaussian = torch.searchsorted(ends, torch.arange(total, device=device), right=True)  # [P]
        first = ends - counts
        local = torch.arange(total, device=device) - first[gaussian]
        tile = (y0[gaussian] + local // span_x[gaussian]) * tiles_x + x0[gaussian] + local % span_x[gaussian]
        tile, order = torch.sort(tile, stable=True)
        return tile, gaussian[order]


def _plan_batches(tile_counts: torch.Tensor, pixels_per_tile: int, work_per_pair: int, pair_budget: int):
    """Group non-empty tiles into batches of similar list length.  tile_counts [T] -> list of [B] tile ids"""
    tiles = torch.nonzero(tile_counts > 0).squeeze(1)
    if tiles.numel() == 0:
        return []
    order = torch.argsort(tile_counts[tiles], descending=True)
    tiles = tiles[order].tolist()
    lengths = [int(c) for c in tile_counts[tiles].tolist()]
    batches, current, current_max = [], [], 0
    for tile, length in zip(tiles, lengths):
        new_max = max(current_max, length)
        if current and (len(current) + 1) * new_max * pixels_per_tile * work_per_pair > pair_budget:
            batches.append(current)
            current, new_max = [], length
        current.append(tile)
        current_max = new_max
    if current:
        batches.append(current)
    return batches


def batch_pixel_opacity(settings: FootprintSettings, pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy,
                        cov_det, opacity, node_counts) -> torch.Tensor:
    """Per-pixel opacity of a batch: pix_* [B, P, 1], per-Gaussian [B, 1, L] -> [B, P, L].

    Centre-sample modes are evaluated densely (one exp per pair). For ``eaa`` and ``exact`` the costly
    rule runs only on the pairs inside the Gaussian's support box (outside it the value is 0 by
    definition) and, for ``eaa``, only for Gaussians with 2 or more nodes; the 1-node Gaussians take
    the dense centre sample. The sparse values are placed with an out-of-place ``index_put``.
    """
    if settings.mode not in ("eaa", "exact"):
        return footprint.pixel_opacity(settings.mode, pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy,
                                       cov_det, opacity, k_sigma=settings.k_sigma)
    if settings.mode == "eaa":
        dense = footprint.centre_sample_opacity(pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det,
                                                opacity, settings.k_sigma)
        dense = torch.where(node_counts <= 1, dense, torch.zeros_like(dense))
        k = settings.k_sigma
    else:
        dense = torch.zeros(torch.broadcast_shapes(pix_x.shape, mean_x.shape), dtype=pix_x.dtype,
                            device=pix_x.device)
        k = footprint.EXACT_K_SIGMA
    with torch.no_grad():
        need = ((pix_x - mean_x).abs() <= k * torch.sqrt(cov_xx) + 0.5) \
            & ((pix_y - mean_y).abs() <= k * torch.sqrt(cov_yy) + 0.5)
        if settings.mode == "eaa":
            need &= node_counts >= 2
        b, p, l = torch.nonzero(need, as_tuple=True)
    if b.numel() == 0:
        return dense
    zero = torch.zeros_like(b)
    pix = (b, p, zero)
    gauss = (b, zero, l)
    args = (pix_x[pix], pix_y[pix], mean_x[gauss], mean_y[gauss], cov_xx[gauss], cov_xy[gauss], cov_yy[gauss],
            cov_det[gauss], opacity[gauss])
    if settings.mode == "eaa":
        values = footprint.eaa_pixel_opacity(*args, node_counts[gauss], row_capacity=settings.max_nodes,
                                             k_sigma=settings.k_sigma, eta=settings.eta, tau=settings.tau)
    else:
        values = footprint.exact_pixel_opacity(*args, order=settings.exact_order)
    return dense.index_put((b, p, l), values)


def _render_batch(settings: FootprintSettings, appearance: bool, pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy,
                  cov_yy, cov_det, opacity, depth, colors, node_counts):
    """One batch of tiles: pix_* [B, P, 1]; per-Gaussian [B, 1, L]; colors [B, L, C] -> [B, P, C+2], and with
    ``appearance`` C more channels: the colour composited with detached weights (its gradient reaches the colours
    only)."""
    a = batch_pixel_opacity(settings, pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det, opacity,
                            node_counts)  # [B, P, L]
    weights = blend_weights(clamp_alpha(a))  # [B, P, L]
    color, depth_img, alpha = composite_weighted(weights, colors.unsqueeze(1), depth)
    parts = [color, depth_img.unsqueeze(-1), alpha.unsqueeze(-1)]
    if appearance:
        parts.append((weights.detach().unsqueeze(-1) * colors.unsqueeze(1)).sum(-2))
    return torch.cat(parts, -1)


def rasterize_projected(proj: ProjectedGaussians, width: int, height: int, settings: FootprintSettings, *,
                        tile_size: int = 8, pair_budget: int = 1 << 20,
                        checkpoint: bool | None = None, appearance: bool = False) -> TiledImage:
    """Rasterize projected Gaussians (those with ``proj.visible``) into an image.

    ``appearance``: also the colour image whose gradient reaches ``proj.colors`` alone (:class:`TiledImage`).

    ``checkpoint=None`` turns checkpointing on when autograd records and the padded work of all batches
    exceeds ``CHECKPOINT_WORK`` evaluations (about a gigabyte of saved tensors); memory then stays
    bounded by one batch, at the price of a second forward pass in backward.
    """
    dtype, device = proj.means2d.dtype, proj.means2d.device
    channels = proj.colors.shape[-1]
    planes = 2 * channels + 2 if appearance else channels + 2  # colour, depth, alpha (, appearance colour)
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    num_tiles = tiles_x * tiles_y
    pixels_per_tile = tile_size * tile_size

    ids = torch.nonzero(proj.visible).squeeze(1)
    ids = ids[torch.argsort(proj.depths[ids], stable=True)]  # front to back
    mean = proj.means2d[ids]
    cov_xx, cov_xy, cov_yy = proj.cov2d[ids].unbind(-1)
    cov_det = proj.cov_det[ids]
    cov_xx, cov_xy, cov_yy, cov_det, opacity, node_counts = footprint.mode_footprint(
        settings.mode, cov_xx, cov_xy, cov_yy, cov_det, proj.opacities[ids], max_nodes=settings.max_nodes,
        gamma=settings.gamma, single_node_sigma=settings.single_node_sigma)
    if settings.mode == "eaa":
        row_capacity = int(node_counts.max()) if node_counts.numel() else 1
        work = max(1, row_capacity)  # rows run on the support pairs only (a fraction of the dense pairs)
    else:
        row_capacity = 1
        work = max(1, settings.exact_order ** 2 // 4) if settings.mode == "exact" else 1
    settings_batch = FootprintSettings(**{**settings.__dict__, "max_nodes": max(1, row_capacity)})

    box_modes = ("eaa", "exact")
    extent_sigma = footprint.EXACT_K_SIGMA if settings.mode == "exact" else settings.k_sigma
    pad = 0.5 if settings.mode in box_modes else 0.0
    ext_x = extent_sigma * torch.sqrt(cov_xx.detach()) + pad
    ext_y = extent_sigma * torch.sqrt(cov_yy.detach()) + pad
    pair_tile, pair_gauss = bin_gaussians(mean.detach(), ext_x, ext_y, tiles_x, tiles_y, tile_size)
    tile_counts = torch.bincount(pair_tile, minlength=num_tiles)
    tile_start = torch.cumsum(tile_counts, 0) - tile_counts

    # Per-Gaussian rows with a trailing dummy (opacity 0) that pads short tile lists.
    def padded(x, fill):
        return torch.cat([x, torch.full((1,) + tuple(x.shape[1:]), fill, dtype=x.dtype, device=x.device)])

    g_mean_x, g_mean_y = padded(mean[:, 0], -1e6), padded(mean[:, 1], -1e6)
    g_xx, g_xy, g_yy, g_det = padded(cov_xx, 1.0), padded(cov_xy, 0.0), padded(cov_yy, 1.0), padded(cov_det, 1.0)
    g_opacity = padded(opacity, 0.0)
    g_depth = padded(proj.depths[ids], 0.0)
    g_colors = padded(proj.colors[ids], 0.0)
    g_nodes = padded(node_counts, 1)
    dummy = ids.numel()

    local = torch.arange(pixels_per_tile, device=device)
    local_x = (local % tile_size).to(dtype)
    local_y = (local // tile_size).to(dtype)
    results, done_tiles = [], []
    batches = _plan_batches(tile_counts, pixels_per_tile, work, pair_budget)
    if checkpoint is None:
        total_work = sum(len(b) * int(tile_counts[b].max()) for b in batches) * pixels_per_tile * work
        checkpoint = total_work > CHECKPOINT_WORK
    for batch in batches:
        tiles = torch.tensor(batch, device=device)
        length = int(tile_counts[tiles].max())
        slot = torch.arange(length, device=device)
        in_list = slot[None, :] < tile_counts[tiles][:, None]  # [B, L]
        pair = (tile_start[tiles][:, None] + slot[None, :]).clamp(max=max(pair_gauss.numel() - 1, 0))
        g = torch.where(in_list, pair_gauss[pair], torch.full_like(pair, dummy))  # [B, L]
        pix_x = ((tiles % tiles_x) * tile_size).to(dtype)[:, None, None] + local_x[None, :, None]  # [B, P, 1]
        pix_y = ((tiles // tiles_x) * tile_size).to(dtype)[:, None, None] + local_y[None, :, None]
        args = (pix_x, pix_y, g_mean_x[g][:, None], g_mean_y[g][:, None], g_xx[g][:, None], g_xy[g][:, None],
                g_yy[g][:, None], g_det[g][:, None], g_opacity[g][:, None], g_depth[g][:, None], g_colors[g],
                g_nodes[g][:, None])
        batch_settings = settings_batch
        if settings.mode == "eaa":  # evaluate only as many rows as this batch's Gaussians need
            batch_settings = FootprintSettings(**{**settings_batch.__dict__, "max_nodes": int(g_nodes[g].max())})
        if checkpoint and torch.is_grad_enabled():
            out = torch_checkpoint(_render_batch, batch_settings, appearance, *args, use_reentrant=False)
        else:
            out = _render_batch(batch_settings, appearance, *args)
        results.append(out)
        done_tiles.append(tiles)

    canvas = torch.zeros(num_tiles, pixels_per_tile, planes, dtype=dtype, device=device)
    if results:
        canvas = canvas.index_copy(0, torch.cat(done_tiles), torch.cat(results))
    elif torch.is_grad_enabled():
        # Nothing drawn: keep the (black) image attached to the inputs so a loss on it still has a
        # graph and the inputs receive zero gradients instead of an autograd error.
        anchor = proj.means2d.sum() + proj.cov2d.sum() + proj.cov_det.sum() + proj.opacities.sum() \
            + proj.colors.sum() + proj.depths.sum()
        canvas = canvas + 0.0 * anchor
    image = canvas.view(tiles_y, tiles_x, tile_size, tile_size, planes).permute(0, 2, 1, 3, 4)
    image = image.reshape(tiles_y * tile_size, tiles_x * tile_size, planes)[:height, :width]
    return TiledImage(color=image[..., :channels], depth=image[..., channels], alpha=image[..., channels + 1],
                      color_appearance=image[..., channels + 2:] if appearance else None)
