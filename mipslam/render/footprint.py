"""Per-pixel opacity of one projected Gaussian: the footprint modes of the renderer.

Every function here is pure and elementwise with broadcasting: per-pair tensors have a shape
``[...]`` (for the rasterizer ``[tiles, pixels, gaussians]``); per-Gaussian tensors broadcast to it
(``[tiles, 1, gaussians]``); pixel coordinates broadcast too (``[tiles, pixels, 1]``). Pixel (u, v)
is the unit square ``[u-0.5, u+0.5] x [v-0.5, v+0.5]`` (docs/design.md conventions). The 2D covariance is
passed as its three entries ``cov_xx, cov_xy, cov_yy`` (px^2) plus its determinant ``cov_det`` (px^4),
which the projection computes without cancellation (Cauchy-Binet), so thin splats stay accurate.

Modes (docs/design.md "Renderer contract"; docs/renderer.md has the full EAA specification):

* ``point``  3DGS: centre sample of the Gaussian dilated by 0.3 px^2 (peak opacity kept).
* ``mip``    Mip-Splatting 2D filter: ``Sigma + 0.1 I``, opacity times ``sqrt(det Sigma / det(Sigma + 0.1 I))``.
* ``ewa``    EWA resampling filter (Zwicker et al. 2001): ``Sigma + I``, same energy-preserving factor.
* ``eaa``    Elliptical Adaptive Anti-aliasing: the box integral ``o * int_pixel G`` by adaptive,
             geometry-aligned, importance-weighted quadrature (:func:`eaa_pixel_opacity`); a splat
             at least a pixel wide takes one node moment-matched to the box (``Sigma + I / 12``).
* ``exact``  the same box integral by dense Gauss-Legendre quadrature (:func:`exact_pixel_opacity`).

The centre-sample modes are cut at the k-sigma ellipse (Mahalanobis distance > k gives 0), so an
image never depends on how the rasterizer tiles it.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch

MODES = ("point", "mip", "ewa", "eaa", "exact")
#: Dilation (px^2) added to the 2D covariance by the centre-sample modes.
MODE_DILATION = {"point": 0.3, "mip": 0.1, "ewa": 1.0}
#: Modes whose dilation comes with the energy-preserving opacity factor sqrt(det S / det(S + dI)).
ENERGY_PRESERVING = ("mip", "ewa")
#: Variance (px^2) of the unit pixel box along each axis: EAA's single node adds it (moment matching).
EAA_BOX_VARIANCE = 1.0 / 12.0
#: Order of the Gauss-Legendre rule per axis in ``exact`` mode and its clipping bound in sigmas.
#: GL-20 on [-6, 6] integrates a unit Gaussian to 3e-8 relative; the mass beyond 6 sigma is 2e-9.
EXACT_ORDER = 20
EXACT_K_SIGMA = 6.0

_SQRT_2PI = math.sqrt(2.0 * math.pi)
_INV_SQRT2 = 1.0 / math.sqrt(2.0)


# ----------------------------------------------------------------------------------------------
# Shared small pieces
# ----------------------------------------------------------------------------------------------
def normal_cdf_difference(upper: torch.Tensor, lower: torch.Tensor) -> torch.Tensor:
    """``Phi(upper) - Phi(lower)`` of the standard normal, ``upper >= lower``.  [...] -> [...]"""
    return 0.5 * (torch.erf(upper * _INV_SQRT2) - torch.erf(lower * _INV_SQRT2))


def mahalanobis_sq(dx: torch.Tensor, dy: torch.Tensor, cov_xx, cov_xy, cov_yy, cov_det) -> torch.Tensor:
    """``d^T Sigma^-1 d`` for the offset d = (dx, dy) px and Sigma = [[xx, xy], [xy, yy]].  [...] -> [...]"""
    return (cov_yy * dx * dx - 2.0 * cov_xy * dx * dy + cov_xx * dy * dy) / cov_det


def dilate_covariance(cov_xx, cov_xy, cov_yy, cov_det, dilation: float):
    """``Sigma + dilation * I`` with its exact determinant.  [N] each -> (xx, xy, yy, det) [N] each"""
    if dilation == 0.0:
        return cov_xx, cov_xy, cov_yy, cov_det
    det = cov_det + dilation * (cov_xx + cov_yy) + dilation * dilation
    return cov_xx + dilation, cov_xy, cov_yy + dilation, det


def footprint_parameters(mode: str, cov_xx, cov_xy, cov_yy, cov_det, opacity):
    """Covariance and opacity a mode samples with (per Gaussian).

    ``point``: ``Sigma + 0.3 I``, opacity unchanged; ``mip``/``ewa``: ``Sigma + d I`` and opacity times
    ``sqrt(det Sigma / det(Sigma + d I))``; ``eaa``/``exact``: the raw covariance and opacity.
    All inputs [N] -> (xx, xy, yy, det, opacity) [N] each.
    """
    if mode not in MODE_DILATION:
        return cov_xx, cov_xy, cov_yy, cov_det, opacity
    xx, xy, yy, det = dilate_covariance(cov_xx, cov_xy, cov_yy, cov_det, MODE_DILATION[mode])
    if mode in ENERGY_PRESERVING:
        opacity = opacity * torch.sqrt(cov_det / det)
    return xx, xy, yy, det, opacity


def centre_sample_opacity(pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det, opacity,
                          k_sigma: float) -> torch.Tensor:
    """``o * G(pixel centre)`` cut to 0 beyond the k-sigma ellipse (point/mip/ewa, and EAA's 1 node).

    pix_* [...] pixel-centre coordinates; mean_*, cov_*, opacity broadcast [...]; returns [...].
    """
    maha = mahalanobis_sq(pix_x - mean_x, pix_y - mean_y, cov_xx, cov_xy, cov_yy, cov_det)
    inside = maha <= k_sigma * k_sigma
    return torch.where(inside, opacity * torch.exp(-0.5 * maha.clamp(max=k_sigma * k_sigma)), torch.zeros_like(maha))


def sheared_frame(pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det):
    """The Gaussian in the row frame that EAA and exact integrate in (docs/renderer.md, "Row frame").

    The *outer* axis is the pixel axis with the larger marginal variance (y when ``cov_yy >= cov_xx``),
    the *inner* axis the other one. Along a line "outer = y" the Gaussian is a 1D Gaussian in the
    inner coordinate with mean ``mu_i + slope * (y - mu_o)`` (the ellipse's conjugate diameter) and
    standard deviation ``cond_std = sqrt(det / var_o)``, so
    ``G(x) = exp(-(y - mu_o)^2 / (2 var_o)) * exp(-(x_i - mu_i - slope (y - mu_o))^2 / (2 cond_std^2))``.

    Returns (p_o, p_i, mu_o, mu_i, sigma_o, slope, cond_std), each broadcast to [...].
    """
    outer_is_y = cov_yy >= cov_xx
    p_o = torch.where(outer_is_y, pix_y, pix_x)
    p_i = torch.where(outer_is_y, pix_x, pix_y)
    mu_o = torch.where(outer_is_y, mean_y, mean_x)
    mu_i = torch.where(outer_is_y, mean_x, mean_y)
    var_o = torch.where(outer_is_y, cov_yy, cov_xx)
    sigma_o = torch.sqrt(var_o)
    slope = cov_xy / var_o
    cond_std = torch.sqrt(cov_det / var_o)
    return p_o, p_i, mu_o, mu_i, sigma_o, slope, cond_std


def _outer_band(p_o, mu_o, sigma_o, k_sigma: float):
    """The pixel's extent along the outer axis clipped to the k-sigma band: (lo, hi), hi >= lo.  [...]"""
    lo = torch.maximum(p_o - 0.5, mu_o - k_sigma * sigma_o)
    hi = torch.maximum(torch.minimum(p_o + 0.5, mu_o + k_sigma * sigma_o), lo)
    return lo, hi


# ----------------------------------------------------------------------------------------------
# EAA
# ----------------------------------------------------------------------------------------------
def eaa_node_counts(cov_xx, cov_xy, cov_yy, cov_det, *, max_nodes: int, gamma: float,
                    single_node_sigma: float) -> torch.Tensor:
    """Adaptive EAA node count per Gaussian (integer, no gradient).  [N] each -> [N] int64

    With ``lambda_minor`` the smaller eigenvalue of Sigma (px^2) and ``kappa = sigma1 / sigma2``:
    ``n = 1`` where ``lambda_minor >= single_node_sigma^2`` (every pixel-axis marginal is then at least
    that wide, and one node moment-matched to the pixel box is within ~1e-3 of the integral:
    :func:`eaa_single_node_footprint`); elsewhere ``n = clamp(floor(2 (1 + gamma ln kappa) + 1/2), 1,
    max_nodes)``: a sub-pixel splat takes 2 rows, more as it stretches.
    """
    with torch.no_grad():
        half_trace = 0.5 * (cov_xx + cov_yy)
        radius = torch.sqrt((0.5 * (cov_xx - cov_yy)) ** 2 + cov_xy * cov_xy)
        lambda_major = half_trace + radius
        lambda_minor = cov_det / lambda_major  # accurate for thin splats, unlike half_trace - radius
        kappa = torch.sqrt(lambda_major / lambda_minor).clamp_min(1.0)
        n = torch.floor(2.0 * (1.0 + gamma * torch.log(kappa)) + 0.5)
        n = torch.nan_to_num(n, nan=float(max_nodes), posinf=float(max_nodes))
        n = torch.where(lambda_minor >= single_node_sigma * single_node_sigma, torch.ones_like(n), n)
        return n.clamp(1, max_nodes).to(torch.int64)


def eaa_single_node_footprint(cov_xx, cov_xy, cov_yy, cov_det, opacity, node_counts):
    """Covariance and opacity EAA samples with: 1-node Gaussians moment-matched to the pixel box.

    The box integral ``o int_pixel G`` is ``o 2 pi sqrt(det Sigma)`` times the density of ``G * box`` at
    the pixel centre. The unit box has covariance ``I / 12``, so to second order that density is a
    Gaussian's with ``Sigma + I / 12``: a single node samples ``Sigma' = Sigma + I / 12`` with opacity
    ``o sqrt(det Sigma / det Sigma')`` (the error is the box's fourth cumulant, O(1 / (120 sigma^4))
    relative: below 1e-3 from sigma ~ 1 px on, and the value tends to the point value as sigma grows).
    Gaussians with 2 or more nodes keep the raw covariance and opacity (the rows integrate the box).
    [N] each -> (xx, xy, yy, det, opacity) [N] each.
    """
    xx, xy, yy, det = dilate_covariance(cov_xx, cov_xy, cov_yy, cov_det, EAA_BOX_VARIANCE)
    single = node_counts <= 1
    matched = opacity * torch.sqrt(cov_det / det)
    return (torch.where(single, xx, cov_xx), cov_xy, torch.where(single, yy, cov_yy),
            torch.where(single, det, cov_det), torch.where(single, matched, opacity))


def mode_footprint(mode: str, cov_xx, cov_xy, cov_yy, cov_det, opacity, *, max_nodes: int = 1,
                   gamma: float = 0.0, single_node_sigma: float = 1.0):
    """What a mode samples with, per Gaussian: covariance, opacity and node count.

    :func:`footprint_parameters` for every mode, then for ``eaa`` the node counts of the raw covariance
    (:func:`eaa_node_counts`) and the moment-matched single node (:func:`eaa_single_node_footprint`);
    node counts are 1 for the other modes. [N] each -> (xx, xy, yy, det, opacity) [N] each, nodes [N] int64.
    """
    xx, xy, yy, det, opacity = footprint_parameters(mode, cov_xx, cov_xy, cov_yy, cov_det, opacity)
    if mode != "eaa":
        return xx, xy, yy, det, opacity, torch.ones(xx.shape, dtype=torch.int64, device=xx.device)
    nodes = eaa_node_counts(xx, xy, yy, det, max_nodes=max_nodes, gamma=gamma, single_node_sigma=single_node_sigma)
    return (*eaa_single_node_footprint(xx, xy, yy, det, opacity, nodes), nodes)


def eaa_pixel_opacity(pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det, opacity,
                      node_counts, *, row_capacity: int, k_sigma: float, eta: float, tau: float) -> torch.Tensor:
    """EAA estimate of ``o * int_pixel G(x) dx`` (docs/renderer.md, "EAA").

    * ``node_counts == 1``: the centre sample ``o * G(p)`` of the given covariance (cut at the k-sigma
      ellipse); callers pass the moment-matched one (:func:`eaa_single_node_footprint`).
    * ``node_counts = n >= 2``: n rows (nodes) along the outer axis at the midpoints of n equal strata of
      the pixel's outer extent clipped to ``mu_o +- k sigma_o``; on each row the inner integral of the
      conditional Gaussian over the pixel is closed form (``R_j``, a difference of two normal CDFs);
      rows are averaged with importance weights ``w_j = phi_j * b(d_j)`` (``phi_j`` the outer marginal
      at the row, ``b(d) = 1 + eta exp(-d / tau)`` the boundary emphasis, d the distance of the row's
      ridge point to the nearest inner pixel edge), and the average is scaled by the exact outer mass
      of the band, so the estimate is exact whenever ``R`` is constant across rows (any axis-aligned
      Gaussian, and any Gaussian wholly inside the pixel):
      ``a = o * M_o * sqrt(2 pi) cond_std * sum_j w_j R_j / sum_j w_j``.

    pix_*: [...] pixel centres; mean_*, cov_*, opacity, node_counts broadcast to [...];
    ``row_capacity`` >= max(node_counts) rows are evaluated (those beyond a Gaussian's count are masked).
    Returns [...] opacity in [0, o].
    """
    point = centre_sample_opacity(pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det, opacity, k_sigma)
    if row_capacity <= 1:
        return point
    p_o, p_i, mu_o, mu_i, sigma_o, slope, cond_std = sheared_frame(
        pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det)
    lo, hi = _outer_band(p_o, mu_o, sigma_o, k_sigma)
    outer_mass = _SQRT_2PI * sigma_o * normal_cdf_difference((hi - mu_o) / sigma_o, (lo - mu_o) / sigma_o)

    rows = torch.arange(row_capacity, dtype=pix_x.dtype, device=pix_x.device)  # [R]
    counts = node_counts.unsqueeze(-1).to(pix_x.dtype)  # [..., 1]
    active = rows < counts  # [..., R]
    fraction = (rows + 0.5) / counts  # [..., R] stratum midpoints in [0, 1]
    y = lo.unsqueeze(-1) + fraction * (hi - lo).unsqueeze(-1)  # [..., R] outer coordinate of each row
    dy = y - mu_o.unsqueeze(-1)
    phi = torch.exp(-0.5 * (dy / sigma_o.unsqueeze(-1)) ** 2)  # outer marginal at the row, <= 1
    ridge = mu_i.unsqueeze(-1) + slope.unsqueeze(-1) * dy  # [..., R] conditional mean of the inner axis
    offset = ridge - p_i.unsqueeze(-1)
    s = cond_std.unsqueeze(-1)
    row_fraction = normal_cdf_difference((0.5 - offset) / s, (-0.5 - offset) / s)  # R_j in [0, 1]
    weight = phi * boundary_emphasis((0.5 - offset.abs()).abs(), eta, tau)
    weight = torch.where(active, weight, torch.zeros_like(weight))
    weight_sum = weight.sum(-1)
    average = (weight * row_fraction).sum(-1) / weight_sum.clamp_min(torch.finfo(weight.dtype).tiny)
    analytic = opacity * outer_mass * (_SQRT_2PI * cond_std) * average
    # k-sigma clipping along the inner axis too: no pixel outside the Gaussian's k-sigma box (grown by
    # half a pixel) receives anything, so the image does not depend on how the rasterizer tiles it.
    var_i = torch.where(cov_yy >= cov_xx, cov_xx, cov_yy)
    inside = (p_i - mu_i).abs() <= k_sigma * torch.sqrt(var_i) + 0.5
    analytic = torch.where(inside, analytic, torch.zeros_like(analytic))
    return torch.where(node_counts <= 1, point, analytic)


def boundary_emphasis(distance: torch.Tensor, eta: float, tau: float) -> torch.Tensor:
    """``b(d) = 1 + eta * exp(-d / tau)``, d >= 0 in pixels.  [...] -> [...]"""
    if eta == 0.0:
        return torch.ones_like(distance)
    return 1.0 + eta * torch.exp(-distance / tau)


# ----------------------------------------------------------------------------------------------
# Exact (dense Gauss-Legendre)
# ----------------------------------------------------------------------------------------------
@lru_cache(maxsize=8)
def _gauss_legendre(order: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    nodes, weights = np.polynomial.legendre.leggauss(order)
    return tuple(float(x) for x in nodes), tuple(float(w) for w in weights)


def gauss_legendre(order: int, dtype: torch.dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss-Legendre nodes and weights on [-1, 1].  -> ([order], [order])"""
    nodes, weights = _gauss_legendre(int(order))
    return (torch.tensor(nodes, dtype=dtype, device=device), torch.tensor(weights, dtype=dtype, device=device))


def exact_pixel_opacity(pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det, opacity, *,
                        order: int = EXACT_ORDER, k_sigma: float = EXACT_K_SIGMA) -> torch.Tensor:
    """``o * int_pixel G(x) dx`` by dense Gauss-Legendre quadrature (tests and benchmarks).

    In the row frame of :func:`sheared_frame`: ``order`` GL rows over the pixel's outer extent clipped
    to ``mu_o +- k sigma_o``, and on each row ``order`` GL nodes over the pixel's inner extent clipped to
    ``ridge +- k cond_std``; G is evaluated at every node (no closed forms, so this checks EAA's).
    Shapes as :func:`eaa_pixel_opacity`; memory is ``order^2`` times the pair count.
    """
    gl_x, gl_w = gauss_legendre(order, pix_x.dtype, pix_x.device)  # [Q], [Q]
    p_o, p_i, mu_o, mu_i, sigma_o, slope, cond_std = sheared_frame(
        pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det)
    lo, hi = _outer_band(p_o, mu_o, sigma_o, k_sigma)
    half_o = (0.5 * (hi - lo)).unsqueeze(-1)  # [..., 1]
    y = (0.5 * (hi + lo)).unsqueeze(-1) + half_o * gl_x  # [..., Q]
    dy = y - mu_o.unsqueeze(-1)
    outer = gl_w * half_o * torch.exp(-0.5 * (dy / sigma_o.unsqueeze(-1)) ** 2)  # [..., Q]
    ridge = mu_i.unsqueeze(-1) + slope.unsqueeze(-1) * dy  # [..., Q]
    s = cond_std.unsqueeze(-1)
    p_i_ = p_i.unsqueeze(-1)
    lo_i = torch.maximum(p_i_ - 0.5, ridge - k_sigma * s)
    hi_i = torch.maximum(torch.minimum(p_i_ + 0.5, ridge + k_sigma * s), lo_i)
    half_i = (0.5 * (hi_i - lo_i)).unsqueeze(-1)  # [..., Q, 1]
    x = (0.5 * (hi_i + lo_i)).unsqueeze(-1) + half_i * gl_x  # [..., Q, Q]
    inner = (gl_w * half_i * torch.exp(-0.5 * ((x - ridge.unsqueeze(-1)) / s.unsqueeze(-1)) ** 2)).sum(-1)
    value = opacity * (outer * inner).sum(-1)
    # The same support box as the tiling (k sigma + half a pixel per axis); beyond it G < exp(-k^2 / 2).
    var_i = torch.where(cov_yy >= cov_xx, cov_xx, cov_yy)
    inside = (p_i - mu_i).abs() <= k_sigma * torch.sqrt(var_i) + 0.5
    return torch.where(inside, value, torch.zeros_like(value))


def pixel_opacity(mode: str, pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det, opacity,
                  node_counts=None, *, k_sigma: float, row_capacity: int = 1, eta: float = 0.0,
                  tau: float = 1.0, exact_order: int = EXACT_ORDER) -> torch.Tensor:
    """Dispatch to a mode. The covariance/opacity must already be :func:`footprint_parameters` of it.

    Shapes as :func:`eaa_pixel_opacity`; returns [...] opacity before the 0.99 clamp.
    """
    if mode == "eaa":
        return eaa_pixel_opacity(pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det, opacity,
                                 node_counts, row_capacity=row_capacity, k_sigma=k_sigma, eta=eta, tau=tau)
    if mode == "exact":
        return exact_pixel_opacity(pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det, opacity,
                                   order=exact_order)
    return centre_sample_opacity(pix_x, pix_y, mean_x, mean_y, cov_xx, cov_xy, cov_yy, cov_det, opacity, k_sigma)
