"""Photometric/depth L1 loss, masks, exposure model and regularisers (mipslam.losses)."""
from __future__ import annotations

import math

import pytest
import torch

from mipslam.losses.photometric import (
    AffineExposure,
    apply_affine_exposure,
    coverage_loss,
    image_gradient_magnitude,
    image_gradient_mask,
    depth_inlier_mask,
    masked_l1,
    normalised_depth,
    rgbd_l1_loss,
    rgbd_l1_loss_and_gradients,
    rgbd_masks,
)
from mipslam.losses.regularizers import isotropy_loss, scale_cap_loss


def _frame(height: int = 12, width: int = 16, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    color = torch.rand(height, width, 3, generator=generator)
    depth = 1.0 + torch.rand(height, width, generator=generator)
    return color, depth


def test_loss_value_matches_the_formula_by_hand():
    color_gt, depth_gt = _frame()
    color = color_gt + 0.1  # |dI| = 0.1 everywhere
    depth = depth_gt.clone()
    depth_gt[0, :] = 0.0  # one row without measurement: 16 of 192 pixels
    depth[1:, :] += 0.25  # |dD| = 0.25 on the 176 valid pixels
    result = rgbd_l1_loss(color, depth, color_gt, depth_gt, alpha_color=0.7)
    assert result.num_color_pixels == 12 * 16
    assert result.num_depth_pixels == 11 * 16
    assert result.color.item() == pytest.approx(0.1, abs=1e-6)
    assert result.depth.item() == pytest.approx(0.25, abs=1e-6)
    assert result.total.item() == pytest.approx(0.7 * 0.1 + 0.3 * 0.25, abs=1e-6)


def test_depth_mask_ignores_invalid_and_transparent_pixels_even_if_nan():
    color_gt, depth_gt = _frame()
    depth_gt[2, 6] = float("nan")
    depth_gt[4, 5] = float("inf")
    alpha = torch.ones(12, 16)
    alpha[:, :4] = 0.5  # 48 transparent pixels
    color = color_gt.clone().requires_grad_(True)
    depth = (depth_gt.nan_to_num(0.0, posinf=0.0) + 0.5).requires_grad_(True)
    result = rgbd_l1_loss(color, depth, color_gt, depth_gt, alpha_color=0.5, alpha=alpha, opacity_threshold=0.95)
    assert result.num_depth_pixels == 12 * 12 - 2
    assert result.num_color_pixels == 12 * 12
    assert result.depth.item() == pytest.approx(0.5, abs=1e-6)
    result.total.backward()
    assert torch.isfinite(depth.grad).all() and torch.isfinite(color.grad).all()
    assert depth.grad[:, :4].abs().max() == 0.0  # transparent pixels get no gradient
    assert depth.grad[2, 6] == 0.0 and depth.grad[4, 5] == 0.0
    # each valid pixel's gradient is (1 - alpha_c) * sign / count
    assert depth.grad[6, 10].item() == pytest.approx(0.5 / (12 * 12 - 2), rel=1e-5)


def test_empty_masks_give_zero_with_a_gradient_path_and_zero_counts():
    color_gt, _ = _frame()
    depth_gt = torch.zeros(12, 16)  # no depth anywhere
    color = torch.rand(12, 16, 3, requires_grad=True)
    depth = torch.rand(12, 16, requires_grad=True)
    alpha = torch.zeros(12, 16)  # nothing rendered
    result = rgbd_l1_loss(color, depth, color_gt, depth_gt, alpha_color=0.5, alpha=alpha, opacity_threshold=0.5)
    assert result.num_color_pixels == 0 and result.num_depth_pixels == 0
    assert result.total.item() == 0.0
    assert result.total.requires_grad
    result.total.backward()
    assert torch.equal(color.grad, torch.zeros_like(color)) and torch.equal(depth.grad, torch.zeros_like(depth))


def test_masked_l1_excludes_nan_in_rendered_outside_mask():
    prediction = torch.tensor([[1.0, float("nan")], [3.0, 4.0]], requires_grad=True)
    target = torch.tensor([[0.0, 0.0], [1.0, float("nan")]])
    mask = torch.tensor([[True, False], [True, False]])
    value, count = masked_l1(prediction, target, mask)
    assert count == 2 and value.item() == pytest.approx(1.5)
    value.backward()
    assert torch.equal(prediction.grad, torch.tensor([[0.5, 0.0], [0.5, 0.0]]))


@pytest.mark.parametrize("shape", [(9, 7, 3), (9, 7)])
def test_masked_l1_equals_the_autograd_expression(shape):
    """masked_l1's written-out backward against autograd through where/abs/sum: value and gradients with
    respect to both inputs, including pixels where prediction equals target (sign 0, as abs' gradient)."""
    generator = torch.Generator().manual_seed(len(shape))
    prediction = torch.rand(*shape, generator=generator, dtype=torch.float64, requires_grad=True)
    target = torch.rand(*shape, generator=generator, dtype=torch.float64)
    target[0, :3] = prediction.detach()[0, :3]  # ties
    target.requires_grad_(True)
    mask = torch.rand(shape[:2], generator=generator) > 0.3
    value, count = masked_l1(prediction, target, mask)
    pixel_mask = mask if len(shape) == 2 else mask[..., None]
    channels = 1 if len(shape) == 2 else shape[2]
    expected = torch.where(pixel_mask, prediction - target, 0.0).abs().sum() / (int(mask.sum()) * channels)
    assert count == int(mask.sum()) and value.item() == pytest.approx(expected.item(), rel=1e-15)
    got = torch.autograd.grad(value, (prediction, target))
    want = torch.autograd.grad(expected, (prediction, target))
    for g, w in zip(got, want):
        assert torch.equal(g, w)
    torch.autograd.gradcheck(lambda p: masked_l1(p, target.detach(), mask)[0], (prediction,))


def test_gradient_mask_keeps_edges_above_percentile():
    image = torch.zeros(20, 20, 3)
    image[:, 10:] = 1.0  # vertical step edge between columns 9 and 10
    magnitude = image_gradient_magnitude(image)
    # Sobel with 1/8 normalisation: a unit step gives 0.5 on both columns next to it, 0 elsewhere
    assert magnitude[5, 9].item() == pytest.approx(0.5) and magnitude[5, 10].item() == pytest.approx(0.5)
    assert magnitude[:, :9].abs().max() == 0 and magnitude[:, 11:].abs().max() == 0
    mask = image_gradient_mask(image, 50.0)
    assert mask.sum().item() == 40  # exactly the two edge columns
    assert mask[:, 9].all() and mask[:, 10].all()
    assert image_gradient_mask(image, 0.0).all()
    assert not image_gradient_mask(torch.full((8, 8, 3), 0.3), 10.0).any()  # flat: no information


def test_unit_ramp_has_unit_gradient():
    ramp = torch.arange(10.0)[None, :].repeat(8, 1) * 0.05  # 0.05 per pixel along x
    magnitude = image_gradient_magnitude(ramp)
    assert magnitude[3, 1:-1].allclose(torch.full((8,), 0.05))


def test_gradient_percentile_in_loss_uses_target_gradients():
    color_gt, depth_gt = _frame(20, 20)
    masks = rgbd_masks(color_gt, depth_gt, gradient_percentile=75.0)
    # strictly above the 75th percentile of 400 distinct magnitudes: 100 pixels (quantile interpolates)
    assert 99 <= int(masks.color.sum()) <= 100
    assert masks.depth.all()
    with_depth = rgbd_masks(color_gt, depth_gt * 0, gradient_percentile=75.0, color_needs_valid_depth=True)
    assert not with_depth.color.any()


def test_exposure_identity_at_init_and_recovers_gain_and_bias():
    torch.manual_seed(0)
    observed, depth_gt = _frame(16, 16, seed=3)
    true_log_gain, true_bias = math.log(1.3), -0.05
    rendered = (observed - true_bias) / math.exp(true_log_gain)  # so exp(a) * rendered + b = observed
    exposure = AffineExposure()
    assert torch.equal(exposure(rendered), rendered)
    optimizer = torch.optim.Adam(exposure.parameters(), lr=0.02)
    for _ in range(400):
        optimizer.zero_grad()
        loss = rgbd_l1_loss(rendered, depth_gt, observed, depth_gt, alpha_color=1.0, exposure=exposure).total
        loss.backward()
        optimizer.step()
    assert exposure.log_gain.item() == pytest.approx(true_log_gain, abs=0.01)
    assert exposure.bias.item() == pytest.approx(true_bias, abs=0.01)


def test_per_channel_exposure_broadcasts_over_channels():
    image = torch.full((2, 2, 3), 0.5)
    out = apply_affine_exposure(image, torch.tensor([0.0, math.log(2.0), 0.0]), torch.tensor([0.1, 0.0, -0.1]))
    assert torch.allclose(out[0, 0], torch.tensor([0.6, 1.0, 0.4]))
    assert AffineExposure(3).log_gain.shape == (3,)


def test_loss_gradient_descent_reduces_loss():
    color_gt, depth_gt = _frame()
    color, depth = _frame(seed=1)
    color.requires_grad_(True)
    depth.requires_grad_(True)
    first = rgbd_l1_loss(color, depth, color_gt, depth_gt, alpha_color=0.5)
    first.total.backward()
    with torch.no_grad():
        color2 = color - 0.01 * color.grad / color.grad.abs().max()
        depth2 = depth - 0.01 * depth.grad / depth.grad.abs().max()
    second = rgbd_l1_loss(color2, depth2, color_gt, depth_gt, alpha_color=0.5)
    assert second.total.item() < first.total.item()


def test_isotropy_loss_values():
    spheres = torch.tensor([[0.1, 0.1, 0.1], [2.0, 2.0, 2.0]])
    assert isotropy_loss(spheres).item() == 0.0
    needle = torch.tensor([[0.3, 0.0, 0.0]])  # mean 0.1; deviations 0.2, 0.1, 0.1
    assert isotropy_loss(needle).item() == pytest.approx(0.4 / 3)
    assert isotropy_loss(needle, relative=True).item() == pytest.approx(4.0 / 3)
    assert isotropy_loss(needle * 10, relative=True).item() == pytest.approx(4.0 / 3)  # unit free


def test_isotropy_gradient_makes_gaussians_rounder():
    log_scales = torch.log(torch.tensor([[0.5, 0.05, 0.05], [0.2, 0.2, 0.01]])).requires_grad_(True)
    before = isotropy_loss(log_scales.exp())
    before.backward()
    with torch.no_grad():
        stepped = log_scales - 0.1 * log_scales.grad / log_scales.grad.abs().max()
    assert isotropy_loss(stepped.exp()).item() < before.item()


def test_scale_cap_and_empty_maps():
    scales = torch.tensor([[0.1, 0.2, 0.5], [1.0, 0.0, 0.0]], requires_grad=True)
    value = scale_cap_loss(scales, max_scale=0.3)  # excesses 0.2 and 0.7
    assert value.item() == pytest.approx((0.2**2 + 0.7**2) / 6)
    value.backward()
    assert scales.grad[0, 0] == 0.0 and scales.grad[1, 0].item() == pytest.approx(2 * 0.7 / 6)
    empty = torch.zeros(0, 3, requires_grad=True)
    for loss in (isotropy_loss(empty), scale_cap_loss(empty, 1.0)):
        assert loss.item() == 0.0 and loss.requires_grad


def test_bad_shapes_raise():
    with pytest.raises(ValueError):
        isotropy_loss(torch.zeros(3))
    with pytest.raises(ValueError):
        rgbd_l1_loss(torch.zeros(4, 4, 3), torch.zeros(4, 4), torch.zeros(4, 5, 3), torch.zeros(4, 5), alpha_color=0.5)
    with pytest.raises(ValueError):
        image_gradient_mask(torch.zeros(4, 4), 100.0)


def test_target_masks_then_the_opacity_test_equal_the_masks_built_with_the_opacity():
    generator = torch.Generator().manual_seed(3)
    color = torch.rand(12, 16, 3, generator=generator)
    color[2, 3, 1] = float("nan")
    depth = torch.rand(12, 16, generator=generator) + 0.5
    depth[5, :4] = 0.0
    alpha = torch.rand(12, 16, generator=generator)
    for threshold in (0.0, 0.5, 0.95):
        at_once = rgbd_masks(color, depth, alpha, opacity_threshold=threshold, gradient_percentile=40.0)
        in_two = rgbd_masks(color, depth, gradient_percentile=40.0).where_opaque(alpha, threshold)
        assert torch.equal(at_once.color, in_two.color) and torch.equal(at_once.depth, in_two.depth)
    assert not in_two.color[2, 3] and not in_two.depth[5, 0]
    with pytest.raises(ValueError, match="opacity"):
        rgbd_masks(color, depth).where_opaque(alpha[:-1], 0.5)


def test_normalised_depth_recovers_the_surface_depth_and_keeps_opacity_out_of_its_gradient():
    depth_surface = torch.full((4, 5), 2.0)
    alpha = torch.tensor([0.3, 0.5, 0.8, 1.0, 0.0]).expand(4, 5).clone().requires_grad_(True)
    rendered = (alpha * depth_surface).detach().requires_grad_(True)  # D = A z for a surface at z = 2 m
    normalised = normalised_depth(rendered, alpha, floor=0.5)
    # Above the floor the surface depth comes back whatever the opacity; below it D / floor (a thin map).
    assert torch.allclose(normalised[:, 1:4], torch.full((4, 3), 2.0))
    assert torch.allclose(normalised[:, 0], torch.full((4,), 0.3 * 2.0 / 0.5))
    assert torch.allclose(normalised[:, 4], torch.zeros(4))
    normalised.sum().backward()
    assert alpha.grad is None or not alpha.grad.any()  # stop-gradient: opacity is the colour term's
    assert torch.allclose(rendered.grad[:, 2], torch.full((4,), 1 / 0.8))
    with pytest.raises(ValueError):
        normalised_depth(rendered, alpha, floor=0.0)


def test_max_depth_leaves_far_observations_out_of_the_depth_term():
    color_gt, depth_gt = _frame()  # depths in [1, 2) m
    masks = rgbd_masks(color_gt, depth_gt, max_depth=1.5)
    assert torch.equal(masks.depth, depth_gt <= 1.5)
    assert masks.color.all()  # colour does not need valid depth unless asked
    assert torch.equal(rgbd_masks(color_gt, depth_gt).depth, depth_gt > 0)


def _translucent_plane(opacity: float, z: float = 1.0, half_width: float = 0.8, spacing: float = 0.02):
    """A grid of flat Gaussians on the plane ``z`` (world = camera frame at the identity pose), each of opacity
    ``opacity``: the rendered opacity stays below 1 while every Gaussian sits exactly at ``z`` metres."""
    from mipslam.gaussians import ActivatedGaussians

    ticks = torch.arange(-half_width, half_width + 1e-6, spacing)
    x, y = torch.meshgrid(ticks, ticks, indexing="xy")
    means = torch.stack([x.reshape(-1), y.reshape(-1), torch.full((x.numel(),), z)], dim=-1)
    n = means.shape[0]
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).clone()
    scales = torch.tensor([spacing * 0.6, spacing * 0.6, 1e-4]).expand(n, 3).clone()
    return ActivatedGaussians(means, quats, scales, torch.full((n,), opacity), torch.full((n, 3), 0.5))


@pytest.mark.parametrize("normalise", [False, True])
def test_a_translucent_map_pulls_the_camera_along_its_axis_only_with_the_raw_depth_term(normalise):
    # A plane at 1 m observed at 1 m, mapped with opacity below 1 (A ~ 0.71): the raw depth D = A z reads short,
    # and the depth term drives the camera back towards 1 / A = 1.4 m (Adam's 60 steps of 2 mm reach 12 cm);
    # the alpha-normalised term leaves it at the truth.
    from mipslam.geometry.se3 import se3_exp
    from mipslam.render import rasterize
    from mipslam.types import Intrinsics

    plane = _translucent_plane(opacity=0.5)
    intrinsics = Intrinsics(fx=40.0, fy=40.0, cx=15.5, cy=11.5, width=32, height=24)
    K = intrinsics.matrix(torch.float32, torch.device("cpu"))
    depth_gt = torch.ones(24, 32)
    color_gt = torch.full((24, 32, 3), 0.5)
    rho = torch.zeros(3, requires_grad=True)
    optimizer = torch.optim.Adam([rho], lr=2e-3)
    for _ in range(60):
        T_cw = se3_exp(torch.cat([rho, torch.zeros(3)]))
        out = rasterize(plane.means, plane.quats, plane.scales, plane.opacities, plane.colors, T_cw, K, 32, 24,
                        mode="mip", pose_only=True)
        loss = rgbd_l1_loss(out.color, out.depth, color_gt, depth_gt, alpha_color=0.0,
                            depth_alpha=out.alpha if normalise else None)
        optimizer.zero_grad()
        loss.total.backward()
        optimizer.step()
    opacity = float(out.alpha.detach().mean())
    assert 0.6 < opacity < 0.8, opacity  # the map is translucent
    # T_cw = exp(rho): the camera sits at -rho, so a camera moved back (away from the plane) has rho_z > 0.
    rho = rho.detach()
    if normalise:
        assert abs(float(rho[2])) < 3e-3, rho
    else:
        assert float(rho[2]) > 0.1, (rho, opacity)


def test_depth_outliers_leave_the_depth_term():
    color_gt, depth_gt = _frame()
    depth = depth_gt + 0.01  # 1 cm everywhere ...
    depth[0, :4] += 0.5  # ... and a disocclusion: 4 pixels 51 cm off
    mask = depth_gt > 0
    inliers = depth_inlier_mask(depth, depth_gt, mask, ratio=10.0)
    assert int((~inliers).sum()) == 4 and not inliers[0, :4].any()
    kept = rgbd_l1_loss(color_gt, depth, color_gt, depth_gt, alpha_color=0.0, depth_outlier_ratio=10.0)
    assert kept.num_depth_pixels == 12 * 16 - 4
    assert kept.depth.item() == pytest.approx(0.01, abs=1e-5)
    assert rgbd_l1_loss(color_gt, depth, color_gt, depth_gt, alpha_color=0.0).depth.item() > 0.015


def test_coverage_loss_is_the_missing_opacity_where_the_sensor_saw_a_surface():
    alpha = torch.tensor([[1.0, 0.5], [0.25, 0.0]], requires_grad=True)
    measured = torch.tensor([[True, True], [True, False]])  # no depth at the last pixel: no surface to cover
    value = coverage_loss(alpha, measured)
    assert value.item() == pytest.approx((0.0 + 0.5 + 0.75) / 3)
    value.backward()
    assert torch.allclose(alpha.grad, torch.tensor([[0.0, -1 / 3], [-1 / 3, 0.0]]))


@pytest.mark.parametrize("exposure,depth_normalise,outlier_ratio,alpha_color", [
    (False, False, 0.0, 0.5), (True, False, 0.0, 0.5), (True, True, 3.0, 0.8), (False, True, 0.0, 0.0),
])
def test_loss_and_gradients_are_bit_equal_to_autograd(exposure, depth_normalise, outlier_ratio, alpha_color):
    """Tracking's compiled step takes the loss's gradients from rgbd_l1_loss_and_gradients: they must be
    autograd's through rgbd_l1_loss (and the exposure model), bit for bit, or tracking would change."""
    color_gt, depth_gt = _frame(24, 32, seed=3)
    generator = torch.Generator().manual_seed(4)
    color0 = (color_gt + 0.1 * torch.randn(color_gt.shape, generator=generator)).clamp(0, 1)
    depth0 = depth_gt + 0.05 * torch.randn(depth_gt.shape, generator=generator)
    alpha = torch.rand(depth_gt.shape, generator=generator)
    depth_gt[0, :5] = 0.0
    masks = rgbd_masks(color_gt, depth_gt, extra_color_mask=image_gradient_mask(color_gt, 50.0)).where_opaque(alpha, 0.3)
    params = torch.tensor([0.07, -0.02], requires_grad=True)
    color, depth = color0.clone().requires_grad_(True), depth0.clone().requires_grad_(True)
    rendered = apply_affine_exposure(color, params[0], params[1]) if exposure else color
    reference = rgbd_l1_loss(rendered, depth, color_gt, depth_gt, alpha_color=alpha_color, masks=masks,
                             depth_alpha=alpha if depth_normalise else None, depth_outlier_ratio=outlier_ratio)
    reference.total.backward()
    loss, grads = rgbd_l1_loss_and_gradients(
        color0, depth0, color_gt, depth_gt, alpha_color=alpha_color, masks=masks,
        exposure=tuple(params.detach().unbind()) if exposure else None,
        depth_alpha=alpha if depth_normalise else None, depth_outlier_ratio=outlier_ratio)
    assert torch.equal(loss.total, reference.total.detach())
    assert (loss.num_color_pixels, loss.num_depth_pixels) == (reference.num_color_pixels, reference.num_depth_pixels)
    assert torch.equal(grads.color, color.grad) and torch.equal(grads.depth, depth.grad)
    if exposure:
        assert torch.equal(torch.stack([grads.log_gain, grads.bias]), params.grad)
    else:
        assert grads.log_gain is None and grads.bias is None


def test_loss_and_gradients_with_empty_masks_are_zero_not_nan():
    color_gt, depth_gt = _frame()
    empty = rgbd_masks(color_gt, depth_gt).where_opaque(torch.zeros_like(depth_gt), 0.5)
    loss, grads = rgbd_l1_loss_and_gradients(color_gt + 0.2, depth_gt + 1.0, color_gt, depth_gt, alpha_color=0.5,
                                             masks=empty, exposure=(torch.tensor(0.1), torch.tensor(0.0)))
    assert loss.total.item() == 0.0 and loss.num_color_pixels == 0 and loss.num_depth_pixels == 0
    for grad in (grads.color, grads.depth, grads.log_gain, grads.bias):
        assert torch.equal(grad, torch.zeros_like(grad))
    with pytest.raises(ValueError, match="scalar exposure model"):
        rgbd_l1_loss_and_gradients(color_gt, depth_gt, color_gt, depth_gt, alpha_color=0.5, masks=empty,
                                   exposure=(torch.zeros(3), torch.zeros(3)))
