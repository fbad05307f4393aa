"""Entry points of the compiled backend: :func:`rasterize` (what :func:`mipslam.render.rasterize` calls for
backend "cpu"/"auto"), the per-pixel stage alone (:func:`rasterize_projected`, a drop-in for the torch
backend's), the fused projection (:func:`project_footprints`) and its torch reference, and which calls the
backend cannot take (:func:`unsupported_reason`)."""
from __future__ import annotations

import dataclasses

import torch

from mipslam.errors import BackendUnavailableError, RenderError
from mipslam.geometry import direct as direct_reference
from mipslam.geometry.se3 import _SERIES_ANGLE_SQ
from mipslam.losses import photometric
from mipslam.render import footprint, projection
from mipslam.render.cpu.autograd import (ProjectFootprints, RasterizeProjected, _gauss_legendre_f32,
                                         _opacity_has_pose_gradient, _params_for)
from mipslam.render.cpu.library import load_extension
from mipslam.render.torch_backend import RenderOutput, check_camera_values, rasterize_torch

#: Footprint kernels of the library: point/mip/ewa are all a centre sample of the mode's covariance.
MODE_IDS = {"point": 0, "mip": 0, "ewa": 0, "eaa": 1, "exact": 2}
#: Colour channel counts the library is compiled for (template parameter, not a runtime loop bound).
SUPPORTED_CHANNELS = (1, 3, 4)
#: Cap of EAA nodes and of the exact-mode Gauss-Legendre order (MAX_ROWS in footprint_simd.h).
MAX_ROWS = 64


def unsupported_reason(means: torch.Tensor, colors: torch.Tensor, mode: str, options) -> str | None:
    """Why this call cannot run on the cpu backend (None if it can): device, dtype, channels, caps."""
    if means.device.type != "cpu":
        return f"the cpu backend needs CPU tensors, got {means.device}"
    if means.dtype != torch.float32:
        return f"the cpu backend computes in float32, got {means.dtype} (use backend='torch' for float64 checks)"
    if colors.dim() != 2 or colors.shape[1] not in SUPPORTED_CHANNELS:
        return f"the cpu backend renders {SUPPORTED_CHANNELS} colour channels, got colors of shape {list(colors.shape)}"
    if mode == "eaa" and int(options.eaa_max_nodes) > MAX_ROWS:
        return f"the cpu backend supports eaa_max_nodes <= {MAX_ROWS}, got {options.eaa_max_nodes}"
    if mode == "exact" and int(options.exact_order) > MAX_ROWS:
        return f"the cpu backend supports exact_order <= {MAX_ROWS}, got {options.exact_order}"
    return None


@dataclasses.dataclass(frozen=True)
class FootprintProjection:
    """Per-Gaussian output of the fused projection (aligned with the input order).

    means2d    [N, 2] px    projected centre (-1e6 where not visible)
    depths     [N]    m     camera-frame z (0 where not visible)
    cov        [N, 4]       the mode's sampling covariance (xx, xy, yy) px^2 and its determinant px^4
    opacities  [N]          the mode's opacity (3D filter and energy factor applied; 0 where not visible)
    node_counts[N]    int32 EAA node count (1 in the other modes)
    visible    [N]    bool  finite, in front of the near plane, on screen, opacity > 0
    radii      [N]    px    k-sigma half extent as RenderOutput.radii
    n_visible  int
    """

    means2d: torch.Tensor
    depths: torch.Tensor
    cov: torch.Tensor
    opacities: torch.Tensor
    node_counts: torch.Tensor
    visible: torch.Tensor
    radii: torch.Tensor
    n_visible: int


def project_footprints(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *, mode: str,
                       options) -> FootprintProjection:
    """The fused projection (float32 or float64 CPU tensors; differentiable with respect to means, quats,
    scales, opacities and viewmat). Equals :func:`reference_footprints` (the torch reference) to rounding.
    ``options``: :class:`mipslam.render.RenderOptions`.
    """
    rate = options.max_sampling_rate
    out = ProjectFootprints.apply(means, quats, scales, opacities, viewmat, colors, K, rate, int(width), int(height),
                                  _params_for(mode, options), torch.get_num_threads())
    return FootprintProjection(*out)


def _torch_footprints(proj, mode: str, max_nodes: int, gamma: float, single_node_sigma: float):
    """The torch footprint parameters of projected Gaussians and their EAA node counts (1 outside eaa).

    -> xx, xy, yy, det [N] (the mode's sampling covariance), opacity [N], node counts [N] int64
    """
    return footprint.mode_footprint(mode, *proj.cov2d.unbind(-1), proj.cov_det, proj.opacities,
                                    max_nodes=int(max_nodes), gamma=gamma, single_node_sigma=single_node_sigma)


def reference_footprints(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *, mode: str,
                         options) -> FootprintProjection:
    """What :func:`project_footprints` computes, in torch (the readable reference):
    :func:`~mipslam.render.projection.project_gaussians` with the mode's extent, then
    :func:`~mipslam.render.footprint.mode_footprint`
    and the radii of :func:`mipslam.render.rasterize_torch`."""
    box_mode = mode in ("eaa", "exact")
    dilation = footprint.MODE_DILATION.get(mode, 0.0)
    proj = projection.project_gaussians(
        means, quats, scales, opacities, colors, viewmat, K, width, height, near_plane=options.near_plane,
        far_plane=options.far_plane, extent_sigma=footprint.EXACT_K_SIGMA if mode == "exact" else options.k_sigma,
        extent_pad=0.5 if box_mode else 0.0, extent_dilation=dilation, filter_3d_scale=options.filter_3d_scale,
        max_sampling_rate=options.max_sampling_rate)
    xx, xy, yy, det, opacity, nodes = _torch_footprints(proj, mode, options.eaa_max_nodes, options.eaa_gamma,
                                                        options.eaa_single_node_sigma)
    with torch.no_grad():
        ext = options.k_sigma * torch.sqrt(torch.maximum(proj.cov2d[:, 0], proj.cov2d[:, 2]) + dilation)
        radii = torch.where(proj.visible, ext + (0.5 if box_mode else 0.0), torch.zeros_like(ext))
    return FootprintProjection(means2d=proj.means2d, depths=proj.depths, cov=torch.stack([xx, xy, yy, det], -1),
                               opacities=opacity, node_counts=nodes.to(torch.int32), visible=proj.visible,
                               radii=radii, n_visible=int(proj.visible.sum()))


@dataclasses.dataclass(frozen=True)
class CpuImage:
    """Raw output of :func:`rasterize_projected`.  color [H, W, C], depth [H, W], alpha [H, W]

    ``lanes_evaluated``: footprint evaluations the kernel made (8-pixel row segments x 8), ``pairs``:
    (tile, Gaussian) pairs after binning; ``color_appearance`` [H, W, C] or None: as
    :class:`~mipslam.render.rasterize_torch.TiledImage`'s.
    """

    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    lanes_evaluated: int
    pairs: int
    color_appearance: torch.Tensor | None = None


def rasterize_projected(proj, width: int, height: int, settings, *, appearance: bool = False,
                        **_unused) -> CpuImage:
    """Drop-in for :func:`mipslam.render.rasterize_torch.rasterize_projected` on the compiled backend.

    ``proj``: :class:`~mipslam.render.projection.ProjectedGaussians` (float32, CPU); ``settings``:
    :class:`~mipslam.render.rasterize_torch.FootprintSettings`. Tiling options of the torch backend
    (tile_size, pair_budget, checkpoint) do not apply (the extension uses 16x16 tiles and O(pairs) memory).
    """
    mode = settings.mode
    if mode not in MODE_IDS:
        raise RenderError(f"rasterize (cpu backend): unknown mode '{mode}'")
    xx, xy, yy, det, opacity, node_counts = _torch_footprints(proj, mode, settings.max_nodes, settings.gamma,
                                                              settings.single_node_sigma)
    gl_nodes, gl_weights = _gauss_legendre_f32(settings.exact_order if mode == "exact" else 1)
    cov = torch.stack([xx, xy, yy, det], -1)
    color, depth, alpha, stats, color_appearance = RasterizeProjected.apply(
        proj.means2d.contiguous(), cov.contiguous(), opacity.contiguous(), proj.depths.contiguous(),
        proj.colors.contiguous(), node_counts.to(torch.int32).contiguous(), MODE_IDS[mode], int(width), int(height),
        float(settings.k_sigma), float(settings.eta), float(settings.tau), gl_nodes, gl_weights,
        torch.get_num_threads(), appearance)
    return CpuImage(color=color, depth=depth, alpha=alpha, lanes_evaluated=int(stats[0]), pairs=int(stats[1]),
                    color_appearance=color_appearance)


def _fused_projection_applies(means, K, options) -> bool:
    """The fused projection treats K and the 3D filter's sampling rate as constants; when either needs a
    gradient (or the rate is not a plain [N] tensor of the means' dtype) the torch projection is used."""
    if K.requires_grad:
        return False
    rate = options.max_sampling_rate
    return rate is None or (not rate.requires_grad and rate.dtype == means.dtype and rate.device == means.device
                            and tuple(rate.shape) == (means.shape[0],))


def rasterize(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *, mode: str, options):
    """:func:`mipslam.render.rasterize` on the compiled backend (shapes and dtypes already checked by it; the
    camera's values are checked here, in C++).

    Two C++ stages, each an autograd function with a hand-written backward: the fused projection
    (:class:`ProjectFootprints`) and the tile rasterizer (:class:`RasterizeProjected`).
    """
    reason = unsupported_reason(means, colors, mode, options)
    if reason is not None:
        raise BackendUnavailableError(f"rasterize: {reason}")
    load_extension()
    if not _fused_projection_applies(means, K, options):
        return rasterize_unfused(means, quats, scales, opacities, colors, viewmat, K, width, height, mode=mode,
                                 options=options)
    if options.pose_only:
        means, quats, scales, opacities, colors = (t.detach() for t in (means, quats, scales, opacities, colors))
    threads = torch.get_num_threads()
    # a bad camera raises RenderError from the library's checks (projection.h)
    means2d, depths, cov, opacity, node_counts, visible, radii, n_visible = ProjectFootprints.apply(
        means, quats, scales, opacities, viewmat, colors, K, options.max_sampling_rate, width, height,
        _params_for(mode, options), threads)
    gl_nodes, gl_weights = _gauss_legendre_f32(options.exact_order if mode == "exact" else 1)
    color, depth, alpha, _stats, color_appearance = RasterizeProjected.apply(
        means2d, cov, opacity, depths, colors.contiguous(), node_counts, MODE_IDS[mode], width, height,
        float(options.k_sigma), float(options.eaa_eta), float(options.eaa_tau), gl_nodes, gl_weights, threads,
        options.appearance_color)
    depth_normalized = None
    if options.normalized_depth:
        depth_normalized = torch.where(alpha > 1e-6, depth / alpha.clamp_min(1e-6), torch.zeros_like(depth))
    return RenderOutput(color=color, depth=depth, alpha=alpha, depth_normalized=depth_normalized, means2d=means2d,
                        radii=radii, visible=visible, n_visible=n_visible, depths=depths, mode=mode,
                        backend="cpu", color_appearance=color_appearance)


@dataclasses.dataclass(frozen=True)
class PoseOnlyRender:
    """A pose-only render on the compiled backend with its backward to the viewmat written out (no autograd):
    :func:`rasterize_pose_only`'s result.

    color [H, W, C], depth [H, W] (the composited sum(T a z), metres), alpha [H, W]: the images of
    :func:`rasterize` with ``pose_only``, bit for bit; :meth:`viewmat_gradient` gives what autograd's backward
    through that render would give the viewmat.
    """

    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    _saved: tuple = dataclasses.field(repr=False)

    def viewmat_gradient(self, grad_color: torch.Tensor, grad_depth: torch.Tensor) -> torch.Tensor:
        """dL/dviewmat [4, 4] (the viewmat's dtype) from dL/dcolor [H, W, C] and dL/ddepth [H, W]; the opacity
        image carries no gradient. The library calls of :class:`RasterizeProjected` and
        :class:`ProjectFootprints`' backwards with the flags a pose-only render sets."""
        (ext, projection_inputs, width, height, params, threads, opacity_differentiable, raster_inputs,
         raster_settings, raster_state, visible) = self._saved
        g_means2d, g_cov, g_opacity, g_depths, _ = ext.rasterize_backward(
            *raster_inputs, *raster_settings, *raster_state, self.color, self.depth, self.alpha,
            grad_color.contiguous().to(torch.float32), grad_depth.contiguous().to(torch.float32),
            torch.zeros_like(self.alpha), False, opacity_differentiable, threads)
        return ext.project_backward(
            *projection_inputs, width, height, params, visible, g_means2d, g_depths, g_cov,
            g_opacity if opacity_differentiable else None, False, True, threads)[4]


def pose_only_unsupported_reason(means: torch.Tensor, colors: torch.Tensor, K: torch.Tensor, mode: str,
                                 options) -> str | None:
    """Why :func:`rasterize_pose_only` cannot take this call (None if it can): :func:`unsupported_reason`, or a K
    or 3D-filter sampling rate that the fused projection cannot treat as a constant."""
    reason = unsupported_reason(means, colors, mode, options)
    if reason is None and not _fused_projection_applies(means, K, options):
        reason = "K and the 3D filter's sampling rate must be constants (no gradient, the means' dtype and device)"
    return reason


def rasterize_pose_only(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *, mode: str,
                        options) -> PoseOnlyRender:
    """:func:`rasterize` with ``options.pose_only`` (tracking's render: gradients for the viewmat alone) without
    autograd: the same library calls, so the same images, and a backward that skips autograd's graph and engine
    (:meth:`PoseOnlyRender.viewmat_gradient`). Inputs as :func:`rasterize` (checked by
    :func:`mipslam.render.rasterize_pose_only`); K and ``options.max_sampling_rate`` must need no gradient."""
    reason = pose_only_unsupported_reason(means, colors, K, mode, options)
    if reason is not None:
        raise BackendUnavailableError(f"rasterize_pose_only: {reason}")
    ext = load_extension()
    means, quats, scales, opacities, colors, viewmat = (
        t.detach() for t in (means, quats, scales, opacities, colors, viewmat))
    threads = torch.get_num_threads()
    params = _params_for(mode, options)
    projection_inputs = (means, quats, scales, opacities, colors, viewmat, K, options.max_sampling_rate)
    means2d, depths, cov, opacity, node_counts, visible, _radii, _n_visible = ext.project_forward(
        *projection_inputs, width, height, params, threads)
    gl_nodes, gl_weights = _gauss_legendre_f32(options.exact_order if mode == "exact" else 1)
    raster_inputs = (means2d, cov, opacity, depths, colors.contiguous(), node_counts)
    raster_settings = (MODE_IDS[mode], width, height, float(options.k_sigma), float(options.eaa_eta),
                       float(options.eaa_tau), gl_nodes, gl_weights)
    color, depth, alpha, *raster_state, _stats = ext.rasterize_forward(*raster_inputs, *raster_settings, threads)
    saved = (ext, projection_inputs, width, height, params, threads, _opacity_has_pose_gradient(params),
             raster_inputs, raster_settings, tuple(raster_state), visible)
    return PoseOnlyRender(color=color, depth=depth, alpha=alpha, _saved=saved)


def rasterize_unfused(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *, mode: str,
                      options):
    """The cpu backend with the torch projection (autograd through ~100 tensor operations) in front of the
    C++ rasterizer: the path before the fused projection, kept for gradients with respect to K or the 3D
    filter's sampling rate, and as the benchmark's baseline."""
    check_camera_values(viewmat, K)
    out = rasterize_torch(means, quats, scales, opacities, colors, viewmat, K, width, height, mode, options,
                          rasterizer=rasterize_projected)
    return dataclasses.replace(out, backend="cpu")


#: The constants of the direct alignment, in the order of direct_align.h's Constant enum: one source, the
#: reference's (the enum's last, DEPTH_NOISE_POWER, is align_direct's argument).
_DIRECT_CONSTANTS = (direct_reference.HUBER_K, direct_reference.MAD_TO_SIGMA, direct_reference.MIN_SCALE_INTENSITY,
                     direct_reference.MIN_SCALE_DEPTH, float(direct_reference.MAX_HALVINGS),
                     float(direct_reference.MIN_POINTS), _SERIES_ANGLE_SQ[torch.float64])


def align_direct(references, targets, T_init: torch.Tensor, *, iterations: int, alpha_color: float,
                 convergence: float = 1e-5, depth_noise_power: float = 0.0):
    """:func:`mipslam.geometry.direct.align_direct` in C++ (direct_align.h): the same arguments, objective and
    step control, float64 normal equations; CPU float32 references and targets. Equals the reference to
    rounding (tests/test_direct_alignment.py), whatever the thread count. -> :class:`~mipslam.geometry.direct.DirectResult`"""
    if len(references) != len(targets):
        raise ValueError(f"align_direct: {len(references)} reference levels against {len(targets)} target levels")
    levels = []
    for reference, target in zip(references, targets):
        K = target.K.detach().to(torch.float32).cpu()
        levels.append((reference.points.contiguous(), reference.intensity.contiguous(), target.channels[0],
                       (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))))
    T, steps, points, ran = load_extension().direct_align(levels, T_init, iterations, alpha_color, convergence,
                                                          (*_DIRECT_CONSTANTS, float(depth_noise_power)),
                                                          torch.get_num_threads())
    return direct_reference.DirectResult(T=T, iterations=steps, points=points,
                                         ok=ran and bool(torch.isfinite(T).all()))


def rgbd_l1_loss_and_gradients(color: torch.Tensor, depth: torch.Tensor, color_gt: torch.Tensor,
                               depth_gt: torch.Tensor, *, alpha_color: float, masks: "photometric.RGBDMasks",
                               exposure: tuple[torch.Tensor, torch.Tensor] | None = None,
                               depth_alpha: torch.Tensor | None = None,
                               depth_alpha_floor: float = photometric.DEFAULT_DEPTH_ALPHA_FLOOR,
                               depth_outlier_ratio: float = 0.0, gradients: bool = True,
                               ) -> tuple["photometric.RGBDLoss", "photometric.RGBDLossGradients | None"]:
    """:func:`mipslam.losses.photometric.rgbd_l1_loss_and_gradients` in one pass of the compiled library
    (rgbd_loss.h): the same arguments (CPU float32 images: colour [H, W, C], depth and ``depth_alpha`` [H, W]
    metres and opacity, masks [H, W] bool); ``gradients=False`` computes the loss alone (None in its place).

    The gradient images are the reference's bit for bit; the loss and the exposure's gradients are sums in a fixed
    order of the library's own, equal to the reference's to rounding (tests/test_rgbd_loss_compiled.py). About
    thirty tensor operations become one library call: 0.17 against 0.47 ms per 160x120 render, a dozen of which
    tracking evaluates per frame."""
    photometric.check_rgbd_loss_inputs("rgbd_l1_loss_and_gradients", color, depth, color_gt, depth_gt, alpha_color)
    if depth_alpha is not None:
        photometric.check_depth_alpha(depth, depth_alpha, depth_alpha_floor)
    depth_mask = masks.depth
    if depth_outlier_ratio > 0:  # the median-based inlier test stays in torch, on the depth the term compares
        compared = depth if depth_alpha is None else photometric.normalised_depth(depth, depth_alpha, depth_alpha_floor)
        depth_mask = photometric.depth_inlier_mask(compared, depth_gt, depth_mask, depth_outlier_ratio)
    affine = None
    if exposure is not None:
        log_gain, bias = exposure
        if log_gain.dim() != 0 or bias.dim() != 0:
            raise ValueError("rgbd_l1_loss_and_gradients: a scalar exposure model (log_gain [] and bias []) only")
        affine = (float(torch.exp(log_gain.detach())), float(bias.detach()))
    out, counts, grad_color, grad_depth = load_extension().rgbd_l1(
        color.detach().contiguous(), depth.detach().contiguous(),
        None if depth_alpha is None else depth_alpha.detach().contiguous(), color_gt.contiguous(),
        depth_gt.contiguous(), masks.color.to(torch.bool).contiguous(), depth_mask.to(torch.bool).contiguous(),
        alpha_color=alpha_color, exposure=affine, depth_normalise=depth_alpha is not None,
        depth_alpha_floor=depth_alpha_floor, gradients=gradients)
    num_color, num_depth = counts.tolist()
    loss = photometric.RGBDLoss(total=out[0], color=out[1], depth=out[2], num_color_pixels=num_color,
                                num_depth_pixels=num_depth)
    if not gradients:
        return loss, None
    return loss, photometric.RGBDLossGradients(color=grad_color, depth=grad_depth,
                                               log_gain=None if affine is None else out[3],
                                               bias=None if affine is None else out[4])
