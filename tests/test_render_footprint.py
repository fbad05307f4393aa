"""Footprint modes against the exact pixel integral."""
from __future__ import annotations

import math

import pytest
import torch

from mipslam.render import RenderOptions
from mipslam.render import footprint as fp

K_SIGMA = 3.0
DEFAULTS = RenderOptions()  # the EAA constants users get


def closed_form_box_integral(px, py, mx, my, sx, sy, opacity):
    """o * int over pixel (px, py) of an axis-aligned Gaussian, via erf."""
    def dphi(p, m, s):
        return 0.5 * (torch.erf((p + 0.5 - m) / (s * math.sqrt(2))) - torch.erf((p - 0.5 - m) / (s * math.sqrt(2))))
    return opacity * 2 * math.pi * sx * sy * dphi(px, mx, sx) * dphi(py, my, sy)


def rotated_covariance(sigma_major, kappa, theta):
    sigma_minor = sigma_major / kappa
    c, s = torch.cos(theta), torch.sin(theta)
    xx = c * c * sigma_major**2 + s * s * sigma_minor**2
    yy = s * s * sigma_major**2 + c * c * sigma_minor**2
    xy = c * s * (sigma_major**2 - sigma_minor**2)
    return xx, xy, yy, (sigma_major * sigma_minor) ** 2


def neighbourhood(radius, dtype):
    r = torch.arange(-radius, radius + 1, dtype=dtype)
    py, px = torch.meshgrid(r, r, indexing="ij")
    return px.reshape(-1, 1), py.reshape(-1, 1)  # [P, 1] each


def battery(dtype=torch.float32):
    """Single Gaussians: sub-pixel to large, anisotropy 1..100, rotated, centred / on an edge / on a corner."""
    sizes = [0.05, 0.15, 0.3, 0.6, 1.0, 2.0, 4.0, 8.0]
    kappas = [1.0, 2.0, 5.0, 20.0, 100.0]
    thetas = [0.0, 0.3, math.pi / 4, 1.1]
    offsets = [(0.0, 0.0), (0.5, 0.0), (0.5, 0.5), (0.23, -0.41)]
    rows = [(s, k, t, ox, oy) for s in sizes for k in kappas for t in thetas for ox, oy in offsets]
    data = torch.tensor(rows, dtype=dtype)
    xx, xy, yy, det = rotated_covariance(data[:, 0], data[:, 1], data[:, 2])
    opacity = torch.full_like(xx, 0.9)
    return data[:, 3], data[:, 4], xx, xy, yy, det, opacity


def mean_abs_error_against_exact(mode, dtype=torch.float32, **eaa):
    mx, my, xx, xy, yy, det, o = battery(dtype)
    px, py = neighbourhood(2, dtype)
    exact = fp.exact_pixel_opacity(px.double(), py.double(), mx.double(), my.double(), xx.double(), xy.double(),
                                   yy.double(), det.double(), o.double())
    cxx, cxy, cyy, cdet, co, nodes = fp.mode_footprint(
        mode, xx, xy, yy, det, o, max_nodes=eaa.get("max_nodes", DEFAULTS.eaa_max_nodes),
        gamma=eaa.get("gamma", DEFAULTS.eaa_gamma),
        single_node_sigma=eaa.get("single_node_sigma", DEFAULTS.eaa_single_node_sigma))
    value = fp.pixel_opacity(mode, px, py, mx, my, cxx, cxy, cyy, cdet, co, nodes, k_sigma=K_SIGMA,
                             row_capacity=eaa.get("max_nodes", DEFAULTS.eaa_max_nodes),
                             eta=eaa.get("eta", DEFAULTS.eaa_eta), tau=eaa.get("tau", DEFAULTS.eaa_tau))
    return (value.double() - exact).abs().mean().item()


def test_exact_equals_closed_form_erf_for_axis_aligned_gaussians():
    g = torch.Generator().manual_seed(1)
    n = 400
    dtype = torch.float64
    mx, my = torch.rand(n, generator=g, dtype=dtype) * 3 - 1.5, torch.rand(n, generator=g, dtype=dtype) * 3 - 1.5
    sx = 10 ** (torch.rand(n, generator=g, dtype=dtype) * 3 - 2)  # 0.01 .. 10 px
    sy = 10 ** (torch.rand(n, generator=g, dtype=dtype) * 3 - 2)
    o = torch.rand(n, generator=g, dtype=dtype)
    px, py = neighbourhood(2, dtype)
    exact = fp.exact_pixel_opacity(px, py, mx, my, sx**2, torch.zeros_like(sx), sy**2, (sx * sy) ** 2, o)
    reference = closed_form_box_integral(px, py, mx, my, sx, sy, o)
    assert (exact - reference).abs().max().item() < 1e-6


def test_exact_integrates_a_whole_gaussian_to_its_mass():
    # Summed over all pixels, the box integrals add up to the mass 2 pi sqrt(det) of a rotated Gaussian.
    dtype = torch.float64
    xx, xy, yy, det = rotated_covariance(torch.tensor(1.7, dtype=dtype), torch.tensor(6.0, dtype=dtype),
                                         torch.tensor(0.6, dtype=dtype))
    px, py = neighbourhood(9, dtype)
    total = fp.exact_pixel_opacity(px, py, torch.tensor(0.3, dtype=dtype), torch.tensor(-0.2, dtype=dtype),
                                   xx, xy, yy, det, torch.tensor(1.0, dtype=dtype)).sum()
    assert abs(total.item() - 2 * math.pi * math.sqrt(det.item())) < 1e-6


def test_eaa_beats_point_and_mip_on_the_single_gaussian_battery():
    err = {mode: mean_abs_error_against_exact(mode) for mode in ("point", "mip", "ewa", "eaa")}
    assert err["eaa"] <= 0.25 * err["point"], err
    assert err["eaa"] <= 0.5 * err["mip"], err
    assert err["eaa"] < err["ewa"], err


def test_eaa_is_exact_for_axis_aligned_and_enclosed_gaussians():
    # With n >= 2 rows the estimator is exact whenever each row's inner fraction is constant.
    dtype = torch.float64
    px, py = neighbourhood(2, dtype)
    g = torch.Generator().manual_seed(3)
    n = 200
    mx, my = torch.rand(n, generator=g, dtype=dtype) - 0.5, torch.rand(n, generator=g, dtype=dtype) - 0.5
    sx = 10 ** (torch.rand(n, generator=g, dtype=dtype) * 2 - 2)
    sy = 10 ** (torch.rand(n, generator=g, dtype=dtype) * 2 - 2)
    o = torch.ones(n, dtype=dtype)
    nodes = torch.full((n,), 2, dtype=torch.int64)
    eaa = fp.eaa_pixel_opacity(px, py, mx, my, sx**2, torch.zeros_like(sx), sy**2, (sx * sy) ** 2, o, nodes,
                               row_capacity=2, k_sigma=8.0, eta=0.0, tau=0.25)
    assert (eaa - closed_form_box_integral(px, py, mx, my, sx, sy, o)).abs().max().item() < 1e-9
    # A small rotated Gaussian at the pixel centre: the pixel holds all its mass.
    xx, xy, yy, det = rotated_covariance(torch.tensor(0.06, dtype=dtype), torch.tensor(3.0, dtype=dtype),
                                         torch.tensor(0.7, dtype=dtype))
    one = torch.tensor(1.0, dtype=dtype)
    value = fp.eaa_pixel_opacity(torch.zeros((), dtype=dtype), torch.zeros((), dtype=dtype), 0 * one, 0 * one,
                                 xx, xy, yy, det, one, torch.tensor(2), row_capacity=2, k_sigma=8.0, eta=0.0, tau=0.25)
    assert abs(value.item() - 2 * math.pi * math.sqrt(det.item())) < 1e-9


def eaa_values(px, py, mx, my, xx, xy, yy, det, o):
    cxx, cxy, cyy, cdet, co, nodes = fp.mode_footprint("eaa", xx, xy, yy, det, o, max_nodes=DEFAULTS.eaa_max_nodes,
                                                       gamma=DEFAULTS.eaa_gamma,
                                                       single_node_sigma=DEFAULTS.eaa_single_node_sigma)
    value = fp.eaa_pixel_opacity(px, py, mx, my, cxx, cxy, cyy, cdet, co, nodes, row_capacity=DEFAULTS.eaa_max_nodes,
                                 k_sigma=K_SIGMA, eta=DEFAULTS.eaa_eta, tau=DEFAULTS.eaa_tau)
    return value, nodes


def test_large_round_gaussians_use_one_node_and_equal_the_undilated_point_value():
    dtype = torch.float32
    sigma = torch.tensor([10.0, 12.0, 40.0, 100.0], dtype=dtype)
    xx, xy, yy = sigma**2 * 1.0, torch.zeros_like(sigma), sigma**2 * 1.2  # kappa ~ 1.1: round
    det = xx * yy
    mx, my = torch.tensor(0.37), torch.tensor(-1.2)
    px, py = neighbourhood(4, dtype)
    o = torch.full_like(sigma, 0.8)
    eaa, nodes = eaa_values(px, py, mx, my, xx, xy, yy, det, o)
    assert nodes.tolist() == [1, 1, 1, 1]
    dx, dy = px - mx, py - my
    point = o * torch.exp(-0.5 * (dx * dx / xx + dy * dy / yy))  # undilated centre sample, computed here
    assert (eaa - point).abs().max().item() < 1e-3
    # and from sigma ~ 12 px on, the point value is itself within 1e-3 of the true pixel integral
    exact = fp.exact_pixel_opacity(px, py, mx, my, xx, xy, yy, det, o)
    assert (eaa - exact)[:, 1:].abs().max().item() < 1e-3


def test_the_single_node_is_moment_matched_to_the_pixel_box():
    # From sigma ~ 1 px on, one node of Sigma + I/12 (energy kept) is closer to the pixel integral than the
    # point value, than mip's Sigma + 0.1 I, and than 2 or 4 rows of the row rule (docs/renderer.md).
    dtype = torch.float64
    g = torch.Generator().manual_seed(5)
    n = 300
    sigma_minor = 1.0 + 2.0 * torch.rand(n, generator=g, dtype=dtype)
    kappa = 1.0 + 3.0 * torch.rand(n, generator=g, dtype=dtype)
    theta = math.pi * torch.rand(n, generator=g, dtype=dtype)
    mx, my = torch.rand(n, generator=g, dtype=dtype) - 0.5, torch.rand(n, generator=g, dtype=dtype) - 0.5
    xx, xy, yy, det = rotated_covariance(sigma_minor * kappa, kappa, theta)
    o = torch.full_like(xx, 0.9)
    px, py = neighbourhood(6, dtype)
    wide = 8.0  # no k-sigma cut: the approximation error alone
    exact = fp.exact_pixel_opacity(px, py, mx, my, xx, xy, yy, det, o, k_sigma=wide)
    cxx, cxy, cyy, cdet, co, nodes = fp.mode_footprint("eaa", xx, xy, yy, det, o, max_nodes=4, gamma=0.5,
                                                       single_node_sigma=1.0)
    assert torch.all(nodes == 1)

    def error(value):  # summed over a splat's pixels, mean over the splats
        return (value - exact).abs().sum(0).mean().item()

    errors = {
        "single": error(fp.centre_sample_opacity(px, py, mx, my, cxx, cxy, cyy, cdet, co, wide)),
        "point": error(fp.centre_sample_opacity(px, py, mx, my, xx, xy, yy, det, o, wide)),  # undilated
        "mip": error(fp.centre_sample_opacity(px, py, mx, my, *fp.footprint_parameters("mip", xx, xy, yy, det, o),
                                              wide)),
    }
    for rows in (2, 4):
        errors[f"{rows} rows"] = error(fp.eaa_pixel_opacity(px, py, mx, my, xx, xy, yy, det, o, torch.full((n,), rows),
                                                            row_capacity=rows, k_sigma=wide, eta=0.0, tau=0.25))
    assert errors["single"] < 0.1 * errors["mip"], errors
    assert errors["single"] < 0.02 * errors["point"], errors
    assert errors["single"] < errors["2 rows"] and errors["single"] < errors["4 rows"], errors
    # and it keeps the mass: o' 2 pi sqrt(det') = o 2 pi sqrt(det)
    assert torch.allclose(co * torch.sqrt(cdet), o * torch.sqrt(det), rtol=1e-12)


def test_node_counts_grow_with_anisotropy_and_respect_the_cap():
    theta = torch.tensor(0.4)
    kappas = torch.tensor([1.0, 2.0, 5.0, 20.0, 100.0, 1000.0])
    xx, xy, yy, det = rotated_covariance(torch.full_like(kappas, 0.6), kappas, theta)
    counts = fp.eaa_node_counts(xx, xy, yy, det, max_nodes=8, gamma=1.0, single_node_sigma=1.0)
    # n = round(2 (1 + ln kappa)): 2, 3, 5, 8 (capped), 8, 8
    assert counts.tolist() == [2, 3, 5, 8, 8, 8]
    defaults = fp.eaa_node_counts(xx, xy, yy, det, max_nodes=DEFAULTS.eaa_max_nodes, gamma=DEFAULTS.eaa_gamma,
                                  single_node_sigma=DEFAULTS.eaa_single_node_sigma)
    assert defaults[0].item() == 2 and torch.all(defaults[1:] >= defaults[:-1])
    assert defaults.max().item() == DEFAULTS.eaa_max_nodes
    capped = fp.eaa_node_counts(xx, xy, yy, det, max_nodes=1, gamma=1.0, single_node_sigma=1.0)
    assert capped.tolist() == [1] * 6
    # a splat whose minor axis is at least single_node_sigma takes one node however elongated it is
    wide = fp.eaa_node_counts(*rotated_covariance(kappas * 1.5, kappas, theta), max_nodes=8, gamma=1.0,
                              single_node_sigma=1.0)
    assert wide.tolist() == [1] * 6


@pytest.mark.parametrize("mode", ["point", "mip", "ewa"])
def test_energy_preserving_filters_keep_the_mass(mode):
    dtype = torch.float64
    xx, xy, yy, det = rotated_covariance(torch.tensor(0.4, dtype=dtype), torch.tensor(3.0, dtype=dtype),
                                         torch.tensor(0.5, dtype=dtype))
    cxx, cxy, cyy, cdet, co = fp.footprint_parameters(mode, xx, xy, yy, det, torch.tensor(1.0, dtype=dtype))
    mass = co * 2 * math.pi * torch.sqrt(cdet)
    if mode == "point":  # 3DGS keeps the peak, so dilation adds mass
        assert mass.item() > 2 * math.pi * math.sqrt(det.item()) * 1.5
    else:
        assert abs(mass.item() - 2 * math.pi * math.sqrt(det.item())) < 1e-12
