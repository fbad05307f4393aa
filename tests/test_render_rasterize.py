"""Rasterizer: compositing rules on hand-built cases, tiling against a brute-force reference, API."""
from __future__ import annotations

import functools
import math

import pytest
import torch

from mipslam.errors import BackendUnavailableError, RenderError
from mipslam.render import Camera, RenderOptions, render
from mipslam.render import rasterize as rasterize_any_backend
from mipslam.render import footprint as fp
from mipslam.render.composite import ALPHA_MIN, blend_weights, clamp_alpha, composite
from mipslam.render.projection import project_gaussians

# These tests check the pure-PyTorch reference backend (the compiled one has its own tests).
rasterize = functools.partial(rasterize_any_backend, backend="torch")


def camera(width=24, height=18, focal=20.0, dtype=torch.float32):
    K = torch.tensor([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]], dtype=dtype)
    return torch.eye(4, dtype=dtype), K


def random_scene(n, seed=0, dtype=torch.float32, scale=(0.02, 0.15)):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=dtype) * torch.tensor([1.6, 1.2, 1.0], dtype=dtype) \
        + torch.tensor([-0.8, -0.6, 1.5], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = scale[0] + (scale[1] - scale[0]) * torch.rand(n, 3, generator=g, dtype=dtype)
    opacities = 0.1 + 0.85 * torch.rand(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, quats, scales, opacities, colors


# --- compositing rules ---------------------------------------------------------------------------
def test_two_layers_blend_front_to_back():
    a = torch.tensor([0.5, 0.5])
    colors = torch.tensor([[1.0, 0, 0], [0, 1.0, 0]])
    color, depth, alpha = composite(a, colors, torch.tensor([2.0, 3.0]))
    assert torch.allclose(color, torch.tensor([0.5, 0.25, 0.0]))
    assert depth.item() == pytest.approx(0.5 * 2 + 0.25 * 3)
    assert alpha.item() == pytest.approx(0.75)


def test_alpha_is_clamped_to_099_and_tiny_alphas_are_skipped():
    assert clamp_alpha(torch.tensor([1.0, 5.0])).tolist() == pytest.approx([0.99, 0.99])
    below = ALPHA_MIN * 0.99
    w = blend_weights(clamp_alpha(torch.tensor([below, 0.5])))
    assert w.tolist() == pytest.approx([0.0, 0.5])  # the skipped one does not attenuate the next


def test_compositing_stops_once_transmittance_would_fall_below_1e4():
    # T: 1 -> 0.05 -> 0.0025 -> (0.000025 < 1e-4: stop); the fourth (T would stay 0.00225) must not count.
    w = blend_weights(clamp_alpha(torch.tensor([0.95, 0.95, 0.99, 0.1], dtype=torch.float64)))
    assert w.tolist() == pytest.approx([0.95, 0.05 * 0.95, 0.0, 0.0])


def test_depth_order_decides_not_input_order():
    viewmat, K = camera(9, 9, focal=10.0)
    means = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 2.0]])  # far one first in the input
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2)
    scales = torch.full((2, 3), 2.0)  # huge: G = 1 at the centre pixel
    opacities = torch.tensor([0.6, 0.3])
    colors = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    out = rasterize(means, quats, scales, opacities, colors, viewmat, K, 9, 9, mode="point")
    centre = out.color[4, 4]
    assert centre.tolist() == pytest.approx([0.3, 0.0, 0.7 * 0.6], abs=1e-6)
    assert out.depth[4, 4].item() == pytest.approx(0.3 * 2 + 0.7 * 0.6 * 3, abs=1e-5)
    assert out.alpha[4, 4].item() == pytest.approx(0.3 + 0.7 * 0.6, abs=1e-6)


def test_empty_scene_is_black():
    viewmat, K = camera()
    empty = torch.zeros(0, 3)
    out = rasterize(empty, torch.zeros(0, 4), empty, torch.zeros(0), empty, viewmat, K, 24, 18)
    assert out.color.shape == (18, 24, 3) and out.color.abs().sum() == 0 and out.alpha.sum() == 0
    assert out.n_visible == 0


# --- tiling against a brute-force reference --------------------------------------------------------
def brute_force(means, quats, scales, opacities, colors, viewmat, K, width, height, mode, k_sigma=3.0):
    """Every pixel against every visible Gaussian, no tiles."""
    proj = project_gaussians(means, quats, scales, opacities, colors, viewmat, K, width, height,
                             extent_sigma=fp.EXACT_K_SIGMA if mode == "exact" else k_sigma,
                             extent_pad=0.5 if mode in ("eaa", "exact") else 0.0,
                             extent_dilation=fp.MODE_DILATION.get(mode, 0.0))
    ids = torch.nonzero(proj.visible).squeeze(1)
    ids = ids[torch.argsort(proj.depths[ids], stable=True)]
    xx, xy, yy = proj.cov2d[ids].unbind(-1)
    d = RenderOptions()
    xx, xy, yy, det, o, nodes = fp.mode_footprint(mode, xx, xy, yy, proj.cov_det[ids], proj.opacities[ids],
                                                  max_nodes=d.eaa_max_nodes, gamma=d.eaa_gamma,
                                                  single_node_sigma=d.eaa_single_node_sigma)
    v, u = torch.meshgrid(torch.arange(height, dtype=means.dtype), torch.arange(width, dtype=means.dtype),
                          indexing="ij")
    a = fp.pixel_opacity(mode, u.reshape(-1, 1), v.reshape(-1, 1), proj.means2d[ids, 0], proj.means2d[ids, 1],
                         xx, xy, yy, det, o, nodes, k_sigma=k_sigma, row_capacity=d.eaa_max_nodes, exact_order=8)
    color, depth, alpha = composite(a, proj.colors[ids].unsqueeze(0), proj.depths[ids])
    return color.view(height, width, -1), depth.view(height, width), alpha.view(height, width)


@pytest.mark.parametrize("mode", ["point", "mip", "ewa", "eaa", "exact"])
def test_tiled_rasterizer_equals_brute_force(mode):
    scene = random_scene(60, seed=2)
    viewmat, K = camera(23, 17)
    # Small tiles and a tiny budget force many batches (and checkpointing).
    out = rasterize(*scene, viewmat, K, 23, 17, mode=mode, tile_size=5, pair_budget=3000, exact_order=8)
    color, depth, alpha = brute_force(*scene, viewmat, K, 23, 17, mode)
    assert out.alpha.max() > 0.5
    assert torch.allclose(out.color, color, atol=1e-5)
    assert torch.allclose(out.depth, depth, atol=1e-5)
    assert torch.allclose(out.alpha, alpha, atol=1e-5)


def test_a_single_gaussian_renders_its_pixel_integral_in_eaa_and_exact():
    means = torch.tensor([[0.013, -0.021, 2.0]])
    quats = torch.tensor([[0.9, 0.1, 0.3, 0.2]])
    scales = torch.tensor([[0.01, 0.003, 0.02]])  # ~0.1 .. 0.2 px: sub-pixel
    viewmat, K = camera(8, 8, focal=20.0)
    args = (means, quats, scales, torch.tensor([0.9]), torch.ones(1, 3), viewmat, K, 8, 8)
    exact = rasterize(*args, mode="exact").alpha
    eaa = rasterize(*args, mode="eaa").alpha
    point = rasterize(*args, mode="point").alpha
    proj = project_gaussians(*args)
    mass = 0.9 * 2 * math.pi * proj.cov_det.sqrt().item()
    assert exact.sum().item() == pytest.approx(mass, rel=1e-4)
    assert (eaa - exact).abs().max() < 0.1 * (point - exact).abs().max()


# --- options and API -------------------------------------------------------------------------------
def test_pose_only_gives_the_same_pose_gradient_and_no_gaussian_gradients():
    scene = [t.clone().requires_grad_() for t in random_scene(30, seed=4)]
    viewmat, K = camera()
    full_pose = viewmat.clone().requires_grad_()
    rasterize(*scene, full_pose, K, 24, 18).color.sum().backward()
    pose = viewmat.clone().requires_grad_()
    scene2 = [t.detach().clone().requires_grad_() for t in scene]
    rasterize(*scene2, pose, K, 24, 18, pose_only=True).color.sum().backward()
    assert torch.allclose(pose.grad, full_pose.grad, atol=1e-5)
    assert pose.grad.abs().sum() > 0
    assert all(t.grad is None for t in scene2)


def test_nan_and_inf_gaussians_are_dropped_not_propagated():
    scene = random_scene(20, seed=5)
    viewmat, K = camera()
    clean = rasterize(*scene, viewmat, K, 24, 18)
    bad = [torch.cat([t, t[:5].clone()]) for t in scene]
    bad[0][20, 0] = float("nan")
    bad[1][21, 2] = float("inf")
    bad[2][22, 1] = float("-inf")
    bad[3][23] = float("nan")
    bad[4][24, 0] = float("nan")
    bad = [t.requires_grad_() for t in bad]
    dirty = rasterize(*bad, viewmat, K, 24, 18)
    assert torch.equal(dirty.visible[20:], torch.zeros(5, dtype=torch.bool))
    assert torch.allclose(dirty.color, clean.color, atol=1e-6)
    dirty.color.sum().backward()
    assert all(torch.isfinite(t.grad).all() for t in bad)


def test_filter_3d_dims_small_gaussians_and_keeps_large_ones():
    viewmat, K = camera(16, 16, focal=40.0)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.0]])
    scales = torch.tensor([[0.002] * 3, [0.5] * 3])  # 0.04 px and 10 px
    args = (means, torch.tensor([[1.0, 0, 0, 0]] * 2), scales, torch.tensor([1.0, 1.0]), torch.ones(2, 3),
            viewmat, K, 16, 16)
    plain = project_gaussians(*args)
    filtered = project_gaussians(*args, filter_3d_scale=0.2)
    ratio = filtered.opacities / plain.opacities
    # s / nu^2 = 0.2 * (z / f)^2 m^2 per axis: the small one loses most of its opacity, the large one ~none
    expected_small = (0.002**2 / (0.002**2 + 0.2 * (2 / 40) ** 2)) ** 1.5
    assert ratio[0].item() == pytest.approx(expected_small, rel=1e-4)
    assert ratio[1].item() > 0.99
    # an explicit sampling rate is honoured
    rate = torch.tensor([40.0 / 1.0, 40.0 / 1.0])
    explicit = project_gaussians(*args, filter_3d_scale=0.2, max_sampling_rate=rate)
    assert explicit.opacities[0] > filtered.opacities[0]


def test_outputs_and_normalized_depth():
    scene = random_scene(40, seed=6)
    viewmat, K = camera()
    out = rasterize(*scene, viewmat, K, 24, 18, normalized_depth=True)
    covered = out.alpha > 0.5
    assert covered.any()
    assert torch.allclose(out.depth_normalized[covered] * out.alpha[covered], out.depth[covered], atol=1e-5)
    assert out.depth_normalized[covered].min() >= 1.5 - 1e-3  # scene depths are within [1.5, 2.5]
    assert out.radii.shape == (40,) and (out.radii[out.visible] > 0).all() and (out.radii[~out.visible] == 0).all()
    assert out.n_visible == int(out.visible.sum())
    assert out.means2d.shape == (40, 2)


def test_render_on_a_map_object_and_camera():
    class Map:
        means, quats, scales, opacities, colors = random_scene(10, seed=7)
    viewmat, K = camera()
    a = render(Map, Camera(viewmat, K, 24, 18), mode="mip", backend="torch")
    b = rasterize(*random_scene(10, seed=7), viewmat, K, 24, 18, mode="mip")
    assert torch.equal(a.color, b.color)


def test_bad_calls_raise_render_errors_that_say_what_to_do():
    scene = random_scene(3)
    viewmat, K = camera()
    with pytest.raises(RenderError, match="unknown mode"):
        rasterize(*scene, viewmat, K, 24, 18, mode="fancy")
    with pytest.raises(RenderError, match="unknown option"):
        rasterize(*scene, viewmat, K, 24, 18, eaa_nodes=3)
    with pytest.raises(RenderError, match="shape"):
        rasterize(scene[0][:, :2], *scene[1:], viewmat, K, 24, 18)
    with pytest.raises(RenderError, match="dtype"):
        rasterize(*scene, viewmat.double(), K, 24, 18)
    with pytest.raises(RenderError, match="finite"):
        rasterize(*scene, viewmat * float("nan"), K, 24, 18)
    with pytest.raises(RenderError, match="eaa_max_nodes"):
        rasterize(*scene, viewmat, K, 24, 18, eaa_max_nodes=0)


def test_cpu_backend_request_is_explicit_when_unavailable(monkeypatch):
    import mipslam.render as render_module
    monkeypatch.setattr(render_module, "_cpu_backend_module", lambda: None)  # as on a machine without a compiler
    scene = random_scene(3)
    viewmat, K = camera()
    with pytest.raises(BackendUnavailableError, match="backend='torch'"):
        rasterize_any_backend(*scene, viewmat, K, 24, 18, backend="cpu")
    assert rasterize_any_backend(*scene, viewmat, K, 24, 18, backend="auto").backend == "torch"
    assert render_module.available_backends() == ("torch",)
