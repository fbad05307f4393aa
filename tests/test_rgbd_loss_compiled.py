"""The compiled tracking loss (mipslam/render/cpu/rgbd_loss.h) against its torch reference,
:func:`mipslam.losses.photometric.rgbd_l1_loss_and_gradients`: gradient images bit for bit, the loss and the
exposure's gradient sums to rounding, the same pixel counts; and the dispatch of :func:`mipslam.render.rgbd_loss_and_gradients`."""
from __future__ import annotations

import pytest
import torch

from mipslam import render
from mipslam.losses.photometric import image_gradient_mask, rgbd_l1_loss_and_gradients, rgbd_masks
from mipslam.render import cpu as cpu_backend


@pytest.fixture
def compiled():
    if not cpu_backend.is_available():
        pytest.skip(f"the compiled CPU library is not available: {cpu_backend.unavailable_reason()}")
    return cpu_backend.rgbd_l1_loss_and_gradients


def _images(height: int, width: int, channels: int, seed: int):
    """A target and a render near it: colour [H, W, C] in [0, 1], depth [H, W] metres with holes, opacity [H, W];
    a tenth of the rendered values equal the target's (exact zero residuals)."""
    generator = torch.Generator().manual_seed(seed)
    color_gt = torch.rand(height, width, channels, generator=generator)
    depth_gt = 0.5 + 3.0 * torch.rand(height, width, generator=generator)
    depth_gt[torch.rand(height, width, generator=generator) < 0.15] = 0.0
    color = (color_gt + 0.1 * torch.randn(color_gt.shape, generator=generator)).clamp(0, 1)
    depth = depth_gt + 0.05 * torch.randn(depth_gt.shape, generator=generator)
    alpha = torch.rand(height, width, generator=generator)
    same = torch.rand(height, width, generator=generator) < 0.1
    color[same], depth[same] = color_gt[same], depth_gt[same]
    return color, depth, alpha, color_gt, depth_gt


@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("exposure,depth_normalise,outlier_ratio,alpha_color", [
    (False, False, 0.0, 0.5), (True, False, 0.0, 0.95), (True, True, 3.0, 0.8), (False, True, 0.0, 0.0),
    (True, False, 0.0, 1.0),
])
def test_compiled_loss_has_the_references_gradients_bit_for_bit(compiled, channels, exposure, depth_normalise,
                                                                 outlier_ratio, alpha_color):
    # 37 x 29 pixels: neither the pixel count nor the value count is a multiple of the library's 8 lanes
    color, depth, alpha, color_gt, depth_gt = _images(37, 29, channels, seed=channels)
    masks = rgbd_masks(color_gt, depth_gt, extra_color_mask=image_gradient_mask(color_gt, 30.0)).where_opaque(alpha, 0.2)
    terms = dict(alpha_color=alpha_color, masks=masks,
                 exposure=(torch.tensor(0.07), torch.tensor(-0.02)) if exposure else None,
                 depth_alpha=alpha if depth_normalise else None, depth_outlier_ratio=outlier_ratio)
    reference, reference_grads = rgbd_l1_loss_and_gradients(color, depth, color_gt, depth_gt, **terms)
    loss, grads = compiled(color, depth, color_gt, depth_gt, **terms)
    assert (loss.num_color_pixels, loss.num_depth_pixels) == (reference.num_color_pixels, reference.num_depth_pixels)
    assert 0 < loss.num_color_pixels < 37 * 29 and 0 < loss.num_depth_pixels < 37 * 29
    assert torch.equal(grads.color, reference_grads.color) and torch.equal(grads.depth, reference_grads.depth)
    for name in ("total", "color", "depth"):
        assert float(getattr(loss, name)) == pytest.approx(float(getattr(reference, name)), rel=1e-6, abs=1e-9)
    if exposure:
        assert float(grads.log_gain) == pytest.approx(float(reference_grads.log_gain), rel=1e-5, abs=1e-8)
        assert float(grads.bias) == pytest.approx(float(reference_grads.bias), rel=1e-5, abs=1e-8)
    else:
        assert grads.log_gain is None and grads.bias is None
    alone, none = compiled(color, depth, color_gt, depth_gt, gradients=False, **terms)
    assert none is None and torch.equal(alone.total, loss.total)


def test_compiled_loss_of_empty_masks_is_zero_and_a_non_finite_render_is_not_hidden(compiled):
    color, depth, alpha, color_gt, depth_gt = _images(16, 24, 3, seed=7)
    empty = rgbd_masks(color_gt, depth_gt).where_opaque(torch.zeros_like(alpha), 0.5)
    loss, grads = compiled(color, depth, color_gt, depth_gt, alpha_color=0.5, masks=empty,
                           exposure=(torch.tensor(0.1), torch.tensor(0.0)))
    assert loss.total.item() == 0.0 and loss.num_color_pixels == 0 and loss.num_depth_pixels == 0
    for grad in (grads.color, grads.depth, grads.log_gain, grads.bias):
        assert torch.equal(grad, torch.zeros_like(grad))
    masks = rgbd_masks(color_gt, depth_gt)
    depth[depth_gt > 0] = float("nan")  # a broken render where the depth term looks
    loss, _ = compiled(color, depth, color_gt, depth_gt, alpha_color=0.5, masks=masks)
    assert not torch.isfinite(loss.total)


def test_compiled_loss_refuses_what_the_reference_refuses(compiled):
    color, depth, alpha, color_gt, depth_gt = _images(8, 8, 3, seed=1)
    masks = rgbd_masks(color_gt, depth_gt)
    with pytest.raises(ValueError, match="do not match"):
        compiled(color[:4], depth, color_gt, depth_gt, alpha_color=0.5, masks=masks)
    with pytest.raises(ValueError, match="alpha_color"):
        compiled(color, depth, color_gt, depth_gt, alpha_color=1.5, masks=masks)
    with pytest.raises(ValueError, match="scalar exposure model"):
        compiled(color, depth, color_gt, depth_gt, alpha_color=0.5, masks=masks,
                 exposure=(torch.zeros(2), torch.tensor(0.0)))
    with pytest.raises(ValueError, match="floor"):
        compiled(color, depth, color_gt, depth_gt, alpha_color=0.5, masks=masks, depth_alpha=alpha,
                 depth_alpha_floor=0.0)


@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_the_dispatch_takes_the_library_only_where_it_may(backend, monkeypatch):
    color, depth, alpha, color_gt, depth_gt = _images(12, 10, 3, seed=2)
    masks = rgbd_masks(color_gt, depth_gt)
    calls = []
    if cpu_backend.is_available():
        original = cpu_backend.rgbd_l1_loss_and_gradients
        monkeypatch.setattr(cpu_backend, "rgbd_l1_loss_and_gradients",
                            lambda *args, **kwargs: calls.append(1) or original(*args, **kwargs))
    loss, grads = render.rgbd_loss_and_gradients(backend, color, depth, color_gt, depth_gt, alpha_color=0.5,
                                                 masks=masks)
    reference, reference_grads = rgbd_l1_loss_and_gradients(color, depth, color_gt, depth_gt, alpha_color=0.5,
                                                            masks=masks)
    assert torch.equal(grads.color, reference_grads.color)
    assert float(loss.total) == pytest.approx(float(reference.total), rel=1e-6)
    assert len(calls) == (1 if backend == "auto" and cpu_backend.is_available() else 0)
    # float64 images never go to the float32 library
    loss64, _ = render.rgbd_loss_and_gradients(backend, color.double(), depth.double(), color_gt.double(),
                                               depth_gt.double(), alpha_color=0.5, masks=masks)
    assert loss64.total.dtype == torch.float64 and len(calls) <= 1
    # nor do colour channel counts the library is not compiled for
    two = rgbd_masks(color_gt[..., :2], depth_gt)
    render.rgbd_loss_and_gradients(backend, color[..., :2].contiguous(), depth, color_gt[..., :2].contiguous(),
                                   depth_gt, alpha_color=0.5, masks=two)
    assert len(calls) <= 1
    _, none = render.rgbd_loss_and_gradients(backend, color, depth, color_gt, depth_gt, alpha_color=0.5, masks=masks,
                                             gradients=False)
    assert none is None
