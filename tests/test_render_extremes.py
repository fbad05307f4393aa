"""Numerical extremes give finite images and finite gradients, never NaN or Inf, on every backend.

Each test runs on the pure-PyTorch reference backend and on the compiled cpu backend (skipped where it
cannot be built); the cpu backend's images must also match the reference's.
"""
from __future__ import annotations

import pytest
import torch

from mipslam.render import MODES, rasterize
from mipslam.render import cpu as cpu_backend

NAN, INF = float("nan"), float("inf")


@pytest.fixture(params=["torch", "cpu"])
def backend(request) -> str:
    if request.param == "cpu" and not cpu_backend.is_available():
        pytest.skip(f"the cpu backend cannot be built here: {cpu_backend.unavailable_reason()}")
    return request.param


def extreme_scene():
    """Normal Gaussians plus every numerical extreme, one per row."""
    rows = [  # mean xyz, quat wxyz, scales xyz, opacity
        ((0.0, 0.0, 2.0), (1, 0, 0, 0), (0.05, 0.05, 0.05), 0.7),  # ordinary
        ((0.1, -0.1, 3.0), (0.9, 0.1, 0.2, 0.3), (0.2, 0.01, 0.1), 0.5),  # ordinary, elongated
        ((0.0, 0.0, -1.0), (1, 0, 0, 0), (0.1, 0.1, 0.1), 0.9),  # behind the camera
        ((0.0, 0.0, 0.01), (1, 0, 0, 0), (0.1, 0.1, 0.1), 0.9),  # on the near plane
        ((0.0, 0.0, 0.0100001), (1, 0, 0, 0), (0.1, 0.1, 0.1), 0.9),  # just in front of it
        ((0.0, 0.0, 1e-6), (1, 0, 0, 0), (0.1, 0.1, 0.1), 0.9),  # depth 1e-6
        ((1e5, 0.0, 1e6), (1, 0, 0, 0), (1.0, 1.0, 1.0), 0.9),  # depth 1e6
        ((0.0, 0.1, 1.0), (1, 0, 0, 0), (1e-8, 1e-8, 1e-8), 1.0),  # scale 1e-8
        ((0.0, 0.0, 5.0), (1, 0, 0, 0), (1e3, 1e3, 1e3), 0.3),  # scale 1e3
        ((0.05, 0.0, 2.0), (0.8, 0.3, -0.2, 0.4), (1e-3, 1e3, 1.0), 0.6),  # anisotropy 1e6
        ((0.02, 0.02, 2.0), (0.7, 0.1, 0.7, 0.1), (1e-6, 1.0, 0.1), 0.8),  # anisotropy 1e6, other axes
        ((-0.1, 0.05, 2.0), (1, 0, 0, 0), (0.05, 0.05, 0.05), 0.0),  # opacity 0
        ((0.1, 0.05, 2.5), (1, 0, 0, 0), (0.05, 0.05, 0.05), 1.0),  # opacity 1
        ((0.0, 0.0, 2.0), (0, 0, 0, 0), (0.05, 0.05, 0.05), 0.9),  # zero quaternion
        ((3.0, 0.0, 2.0), (1, 0, 0, 0), (0.05, 0.05, 0.05), 0.9),  # far outside the image
        ((NAN, 0.0, 2.0), (1, 0, 0, 0), (0.05, 0.05, 0.05), 0.9),  # NaN mean
        ((0.0, INF, 2.0), (1, 0, 0, 0), (0.05, 0.05, 0.05), 0.9),  # Inf mean
        ((0.0, 0.0, 2.0), (NAN, 0, 0, 0), (0.05, 0.05, 0.05), 0.9),  # NaN quat
        ((0.0, 0.0, 2.0), (1, 0, 0, 0), (INF, 0.05, 0.05), 0.9),  # Inf scale
        ((0.0, 0.0, 2.0), (1, 0, 0, 0), (0.05, 0.05, 0.05), NAN),  # NaN opacity
        ((1e30, 1e30, 1e30), (1, 0, 0, 0), (1e30, 1e30, 1e30), 0.9),  # huge but finite
    ]
    means = torch.tensor([r[0] for r in rows])
    quats = torch.tensor([r[1] for r in rows], dtype=torch.float32)
    scales = torch.tensor([r[2] for r in rows])
    opacities = torch.tensor([r[3] for r in rows])
    colors = torch.rand(len(rows), 3, generator=torch.Generator().manual_seed(0))
    colors[1, 2] = NAN  # NaN colour: that Gaussian is dropped too
    return means, quats, scales, opacities, colors


def camera(width, height, focal):
    K = torch.tensor([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return torch.eye(4), K


def render_and_backward(scene, width, height, focal, mode, backend, **options):
    """Render ``scene`` on ``backend`` and back-propagate; the cpu backend's image must match the reference's."""
    inputs = [t.clone().requires_grad_() for t in scene]
    viewmat, K = camera(width, height, focal)
    viewmat.requires_grad_()
    out = rasterize(*inputs, viewmat, K, width, height, mode=mode, backend=backend, **options)
    (out.color.sum() + out.depth.sum() + out.alpha.sum()).backward()
    if backend != "torch":
        reference = rasterize(*scene, torch.eye(4), K, width, height, mode=mode, backend="torch", **options)
        assert (out.color.detach() - reference.color).abs().max() <= 1e-4
    return out, inputs + [viewmat]


def assert_finite(out, inputs):
    for name in ("color", "depth", "alpha"):
        image = getattr(out, name)
        assert torch.isfinite(image).all(), f"{name} not finite"
    assert (out.alpha >= 0).all() and (out.alpha <= 1 + 1e-6).all()
    for i, t in enumerate(inputs):
        assert torch.isfinite(t.grad).all(), f"gradient of input {i} not finite"


@pytest.mark.parametrize("mode", MODES)
def test_extreme_gaussians_give_finite_images_and_gradients(mode, backend):
    scene = extreme_scene()
    out, inputs = render_and_backward(scene, 16, 12, 10.0, mode, backend, exact_order=6)
    assert_finite(out, inputs)
    dropped = [2, 3, 5, 11, 13, 15, 16, 17, 18, 19, 1]  # behind, on near plane, too close, opacity 0, bad rows
    assert not out.visible[dropped].any()
    assert out.visible[[0, 4, 8, 12]].all()
    assert out.alpha.max() > 0.5


@pytest.mark.parametrize("focal", [1.0, 1e5])
@pytest.mark.parametrize("mode", ["point", "eaa"])
def test_extreme_focal_lengths(focal, mode, backend):
    out, inputs = render_and_backward(extreme_scene(), 20, 10, focal, mode, backend)
    assert_finite(out, inputs)


@pytest.mark.parametrize("size", [(1, 1), (1, 7), (9, 1), (1920, 1080)])
def test_image_sizes_from_one_pixel_to_full_hd(size, backend):
    width, height = size
    scene = [t[:3] for t in extreme_scene()]  # few Gaussians keep 1080p cheap
    out, inputs = render_and_backward(scene, width, height, max(width, height) / 2 + 20, "eaa", backend)
    assert out.color.shape == (height, width, 3)
    assert_finite(out, inputs)
    assert out.alpha.max() > 0


@pytest.mark.parametrize("n", [0, 1])
def test_zero_and_one_gaussian(n, backend):
    scene = [t[:n] for t in extreme_scene()]
    out, inputs = render_and_backward(scene, 8, 6, 5.0, "eaa", backend)
    assert_finite(out, inputs)
    assert out.n_visible == n
    assert (out.alpha.sum() > 0) == (n == 1)
