"""float64 gradcheck of the torch backend on tiny scenes, every mode, viewmat included."""
from __future__ import annotations

import functools

import pytest
import torch

from mipslam.geometry import se3_exp
from mipslam.render import rasterize as rasterize_any_backend

WIDTH, HEIGHT = 4, 3

# These tests check the pure-PyTorch reference backend (the compiled one has its own tests).
rasterize = functools.partial(rasterize_any_backend, backend="torch")


def tiny_scene():
    dtype = torch.float64
    means = torch.tensor([[0.031, -0.017, 2.0], [-0.043, 0.052, 2.6], [0.12, 0.07, 2.3]], dtype=dtype)
    quats = torch.tensor([[0.9, 0.2, -0.1, 0.3], [0.7, -0.3, 0.4, 0.1], [1.0, 0.05, 0.02, -0.1]], dtype=dtype)
    scales = torch.tensor([[0.06, 0.02, 0.04], [0.05, 0.09, 0.03], [0.015, 0.01, 0.012]], dtype=dtype)
    opacities = torch.tensor([0.7, 0.55, 0.8], dtype=dtype)
    colors = torch.tensor([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.4, 0.4, 0.9]], dtype=dtype)
    viewmat = se3_exp(torch.tensor([0.01, -0.02, 0.03, 0.02, -0.01, 0.015], dtype=dtype))
    K = torch.tensor([[8.0, 0, 1.5], [0, 7.5, 1.0], [0, 0, 1]], dtype=dtype)
    return means, quats, scales, opacities, colors, viewmat, K


@pytest.mark.parametrize("mode", ["point", "mip", "ewa", "eaa", "exact"])
def test_gradcheck_every_mode_including_the_pose(mode):
    means, quats, scales, opacities, colors, viewmat, K = tiny_scene()
    options = {"exact_order": 4} if mode == "exact" else {}

    def render(m, q, s, o, c, v):
        out = rasterize(m, q, s, o, c, v, K, WIDTH, HEIGHT, mode=mode, tile_size=2, **options)
        return torch.cat([out.color.reshape(-1), out.depth.reshape(-1), out.alpha.reshape(-1)])

    inputs = tuple(t.clone().requires_grad_() for t in (means, quats, scales, opacities, colors, viewmat))
    value = render(*inputs)
    assert value.abs().sum() > 0.1  # the scene is actually drawn
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-3)


def test_eaa_gradcheck_with_many_nodes_and_boundary_emphasis():
    means, quats, scales, opacities, colors, viewmat, K = tiny_scene()
    scales = scales * torch.tensor([3.0, 0.2, 1.0], dtype=scales.dtype)  # elongated: several rows

    def render(m, s, v):
        out = rasterize(m, quats, s, opacities, colors, v, K, WIDTH, HEIGHT, mode="eaa", eaa_max_nodes=8,
                        eaa_gamma=2.0, eaa_eta=1.5, eaa_tau=0.3)
        return torch.cat([out.color.reshape(-1), out.alpha.reshape(-1)])

    inputs = tuple(t.clone().requires_grad_() for t in (means, scales, viewmat))
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)
