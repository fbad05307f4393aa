"""GaussianMap: activations, add/remove with Adam state, anchor motion, state dicts, init and policy."""
from __future__ import annotations

import pytest
import torch

from mipslam.errors import MipslamError
from mipslam.gaussians import (
    ActivatedGaussians,
    GaussianMap,
    GaussianOptimizer,
    GaussianParameters,
    cap_count_mask,
    cap_pixel_mask,
    densify_pixel_mask,
    distances_to_camera,
    far_from_existing,
    gaussians_from_rgbd,
    prune_mask,
    quat_multiply_wxyz,
)
from mipslam.geometry.se3 import quat_wxyz_to_rotmat, se3_exp

LRS = {"means": 1e-2, "quats_wxyz": 5e-3, "log_scales": 2e-2, "opacity_logits": 5e-2, "colors_raw": 3e-2}


def random_params(n: int, seed: int = 0, anchor_count: int = 3) -> GaussianParameters:
    g = torch.Generator().manual_seed(seed)
    return GaussianParameters(
        means=torch.randn(n, 3, generator=g),
        quats_wxyz=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3,
        opacity_logits=torch.randn(n, generator=g),
        colors_raw=torch.randn(n, 3, generator=g),
        anchor_keyframe=torch.randint(0, anchor_count, (n,), generator=g),
        created_frame=torch.randint(0, 100, (n,), generator=g),
    )


def separable_loss(gmap: GaussianMap) -> torch.Tensor:
    """A loss that is a sum of per-Gaussian terms: each row's gradient depends on that row only,
    so training a subset alone equals training it inside a larger map."""
    act = gmap.activated()
    targets = torch.linspace(-1, 1, 3)
    return ((act.means - targets) ** 2).sum() + (act.scales - 0.05).pow(2).sum() + (act.opacities - 0.8).pow(2).sum() \
        + (act.colors - 0.3).pow(2).sum() + (act.quats[:, 1:] ** 2).sum() + (act.means[:, 0] * act.colors[:, 1]).sum()


def train(gmap: GaussianMap, opt: GaussianOptimizer, steps: int) -> None:
    for _ in range(steps):
        opt.zero_grad()
        separable_loss(gmap).backward()
        opt.step()


def test_activated_values_are_in_range_and_differentiable():
    params = random_params(50)
    extreme = GaussianParameters(
        means=torch.zeros(4, 3),
        quats_wxyz=torch.tensor([[0.0, 0, 0, 1e-3], [100.0, 0, 0, 0], [1, 1, 1, 1], [-2.0, 0.5, 0, 0]]),
        log_scales=torch.tensor([[-20.0] * 3, [5.0] * 3, [0.0] * 3, [-1.0, 0, 1]]),
        opacity_logits=torch.tensor([-30.0, 30.0, 0.0, 2.0]),
        colors_raw=torch.tensor([[-30.0] * 3, [30.0] * 3, [0.0] * 3, [1.0, -1, 0]]),
        anchor_keyframe=torch.zeros(4, dtype=torch.int64),
        created_frame=torch.zeros(4, dtype=torch.int64),
    )
    gmap = GaussianMap(GaussianParameters.concatenate([params, extreme]))
    act = gmap.activated()
    assert act.means.shape == (54, 3) and act.quats.shape == (54, 4) and act.scales.shape == (54, 3)
    assert act.opacities.shape == (54,) and act.colors.shape == (54, 3)
    torch.testing.assert_close(act.quats.norm(dim=-1), torch.ones(54))
    assert (act.scales > 0).all()
    assert ((act.opacities >= 0) & (act.opacities <= 1)).all()
    assert ((act.colors >= 0) & (act.colors <= 1)).all()
    assert act.opacities[-2].item() == pytest.approx(0.5) and act.colors[-2, 0].item() == pytest.approx(0.5)
    torch.testing.assert_close(act.scales[-1], torch.exp(torch.tensor([-1.0, 0, 1])))
    (act.colors.sum() + act.opacities.sum() + act.scales.sum() + act.quats.sum() + act.means.sum()).backward()
    for name, param in gmap.parameters().items():
        assert param.is_leaf and param.grad is not None and torch.isfinite(param.grad).all(), name


def test_remove_keeps_adam_state_aligned_with_parameters():
    params = random_params(12, seed=1)
    remove = torch.zeros(12, dtype=torch.bool)
    remove[[0, 3, 4, 11]] = True

    full = GaussianMap(params)
    opt = GaussianOptimizer(full, LRS)
    train(full, opt, 5)
    before = opt.state_dict()
    assert full.remove(remove, optimizer=opt) == 4
    after = opt.state_dict()
    for name in LRS:
        torch.testing.assert_close(after[f"{name}.exp_avg"], before[f"{name}.exp_avg"][~remove], rtol=0, atol=0)
        torch.testing.assert_close(after[f"{name}.exp_avg_sq"], before[f"{name}.exp_avg_sq"][~remove], rtol=0, atol=0)
        assert after[f"{name}.step"].item() == before[f"{name}.step"].item() == 5
    train(full, opt, 4)

    # the kept subset trained alone from the start takes exactly the same steps
    subset = GaussianMap(params.subset(~remove))
    train(subset, GaussianOptimizer(subset, LRS), 9)
    for name, value in subset.state_dict().items():
        torch.testing.assert_close(full.state_dict()[name], value, rtol=1e-6, atol=1e-7, msg=name)
    assert torch.equal(full.anchor_keyframe, params.anchor_keyframe[~remove])


def test_add_appends_zero_moments_and_leaves_old_rows_untouched():
    params = random_params(8, seed=2)
    extra = random_params(5, seed=3)
    grown = GaussianMap(params)
    opt = GaussianOptimizer(grown, LRS)
    train(grown, opt, 3)
    rows = grown.add(extra, optimizer=opt)
    assert rows == slice(8, 13) and len(grown) == 13
    state = opt.state_dict()
    for name in LRS:
        assert state[f"{name}.exp_avg"].shape[0] == 13
        assert (state[f"{name}.exp_avg"][8:] == 0).all() and (state[f"{name}.exp_avg_sq"][8:] == 0).all()
        assert (state[f"{name}.exp_avg"][:8] != 0).any()
    train(grown, opt, 3)

    alone = GaussianMap(params)
    train(alone, GaussianOptimizer(alone, LRS), 6)
    for name, value in alone.state_dict().items():
        torch.testing.assert_close(grown.state_dict()[name][:8], value, rtol=1e-6, atol=1e-7, msg=name)
    # the new rows were trained too
    assert not torch.equal(grown.means.detach()[8:], extra.means)
    assert torch.equal(grown.created_frame[8:], extra.created_frame)


def test_resize_without_optimizer_is_detected():
    gmap = GaussianMap(random_params(6))
    opt = GaussianOptimizer(gmap, LRS)
    train(gmap, opt, 1)
    gmap.remove(torch.tensor([True, False, False, False, False, False]))
    opt.zero_grad()
    separable_loss(gmap).backward()
    with pytest.raises(MipslamError, match="without its optimizer"):
        opt.step()


def test_remove_rejects_bad_mask_and_add_empty_is_noop():
    gmap = GaussianMap(random_params(4))
    with pytest.raises(ValueError):
        gmap.remove(torch.tensor([1, 0, 0, 0]))
    assert gmap.add(random_params(0)) == slice(4, 4) and len(gmap) == 4
    assert gmap.remove(torch.zeros(4, dtype=torch.bool)) == 0


def test_quat_multiply_matches_rotation_matrices():
    g = torch.Generator().manual_seed(5)
    q1, q2 = torch.randn(20, 4, generator=g, dtype=torch.float64), torch.randn(20, 4, generator=g, dtype=torch.float64)
    q1, q2 = q1 / q1.norm(dim=-1, keepdim=True), q2 / q2.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(quat_wxyz_to_rotmat(quat_multiply_wxyz(q1, q2)),
                               quat_wxyz_to_rotmat(q1) @ quat_wxyz_to_rotmat(q2))


def test_transform_by_anchor_moves_gaussians_rigidly_with_their_keyframe():
    params = random_params(30, seed=4, anchor_count=3)
    anchors = params.anchor_keyframe.clone()
    anchors[:2] = -1
    params = GaussianParameters(**{**params.__dict__, "anchor_keyframe": anchors})
    gmap = GaussianMap(params)
    opt = GaussianOptimizer(gmap, LRS)
    corrections = torch.stack([
        torch.eye(4),
        se3_exp(torch.tensor([0.3, -0.2, 0.1, 0.2, -0.4, 0.7])),
        se3_exp(torch.tensor([0.0, 1.0, 0.0, 0.0, 0.0, -1.2])),
    ])
    before = gmap.activated()
    before = type(before)(**{k: v.detach().clone() for k, v in before.__dict__.items()})
    covariance_before = _covariances(before.quats, before.scales)
    moved = gmap.transform_by_anchor(corrections)
    after = gmap.activated()
    assert moved == int((anchors >= 0).sum())
    for k in range(-1, 3):
        rows = anchors == k
        if k == -1:
            assert torch.equal(after.means[rows], before.means[rows])
            continue
        R, t = corrections[k, :3, :3], corrections[k, :3, 3]
        torch.testing.assert_close(after.means[rows], before.means[rows] @ R.T + t, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(_covariances(after.quats[rows], after.scales[rows]),
                                   R @ covariance_before[rows] @ R.T, rtol=1e-4, atol=1e-6)
    # same leaf tensors: the optimizer still holds the map's parameters
    opt.check_aligned()
    with pytest.raises(MipslamError, match="anchored to keyframe 2"):
        gmap.transform_by_anchor(corrections[:2])


def _covariances(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    R = quat_wxyz_to_rotmat(quats)
    return R @ torch.diag_embed(scales**2) @ R.transpose(-1, -2)


def test_state_dict_round_trip_continues_training_identically():
    gmap = GaussianMap(random_params(10, seed=6))
    opt = GaussianOptimizer(gmap, LRS)
    train(gmap, opt, 3)
    map_state, opt_state = gmap.state_dict(), opt.state_dict()
    assert all(isinstance(v, torch.Tensor) for v in {**map_state, **opt_state}.values())

    restored = GaussianMap.from_state_dict(map_state)
    restored_opt = GaussianOptimizer(restored, {name: 1.0 for name in LRS})
    restored_opt.load_state_dict(opt_state)
    assert restored_opt.learning_rates == pytest.approx(LRS)
    train(gmap, opt, 4)
    train(restored, restored_opt, 4)
    for name, value in gmap.state_dict().items():
        assert torch.equal(restored.state_dict()[name], value), name

    with pytest.raises(MipslamError, match="lacks"):
        GaussianMap.from_state_dict({k: v for k, v in map_state.items() if k != "colors_raw"})
    small = GaussianMap(random_params(4))
    with pytest.raises(MipslamError, match="same checkpoint"):
        GaussianOptimizer(small, LRS).load_state_dict(opt_state)


def test_map_follows_the_dtype_and_device_of_its_inputs():
    params = random_params(5)
    params64 = GaussianParameters(**{k: (v.double() if v.is_floating_point() else v) for k, v in params.__dict__.items()})
    gmap = GaussianMap(params64)
    assert gmap.dtype == torch.float64 and gmap.activated().scales.dtype == torch.float64
    assert GaussianMap.empty(dtype=torch.float64).dtype == torch.float64 and len(GaussianMap.empty()) == 0


def test_gaussians_from_rgbd_sizes_from_depth_and_footprint():
    height, width, fx, fy = 6, 8, 100.0, 100.0
    K = torch.tensor([[fx, 0, 3.5], [0, fy, 2.5], [0, 0, 1.0]])
    depth = torch.full((height, width), 2.0)
    depth[0, 0] = 0.0  # no measurement
    depth[1, 1] = float("nan")
    depth[5, 7] = 4.0
    color = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(0)) * 0.9 + 0.05
    mask = torch.ones(height, width, dtype=torch.bool)
    mask[2, :] = False
    T_wc = se3_exp(torch.tensor([1.0, 2.0, 3.0, 0.1, 0.2, -0.3]))
    new = gaussians_from_rgbd(color, depth, K, T_wc, mask, initial_opacity=0.3, anchor_keyframe=4, created_frame=17)
    assert len(new) == height * width - 2 - width  # minus invalid depth, minus the masked row
    gmap = GaussianMap(new)
    act = gmap.activated()
    # pixel (u=7, v=5) with z = 4: camera point ((7-3.5)/100*4, (5-2.5)/100*4, 4)
    corner = torch.tensor([0.14, 0.1, 4.0])
    expected = corner @ T_wc[:3, :3].T + T_wc[:3, 3]
    distances = (act.means - expected).norm(dim=-1)
    i = int(distances.argmin())
    assert distances[i] < 1e-5
    torch.testing.assert_close(act.scales[i], torch.full((3,), 4.0 / 100.0))
    torch.testing.assert_close(act.colors[i], color[5, 7], rtol=0, atol=1e-6)
    others = distances > 1e-3
    torch.testing.assert_close(act.scales[others], torch.full_like(act.scales[others], 0.02))
    torch.testing.assert_close(act.opacities, torch.full_like(act.opacities, 0.3))
    torch.testing.assert_close(act.quats, torch.tensor([1.0, 0, 0, 0]).expand_as(act.quats))
    assert (gmap.anchor_keyframe == 4).all() and (gmap.created_frame == 17).all()
    # all means lie at depth 2 (or 4) in the camera frame
    points_c = (act.means - T_wc[:3, 3]) @ T_wc[:3, :3]
    assert set(torch.round(points_c[:, 2], decimals=4).tolist()) == {2.0, 4.0}

    strided = gaussians_from_rgbd(color, depth, K, T_wc, None, pixel_stride=2)
    assert len(strided) == 3 * 4 - 1  # (0, 0) has no depth
    assert torch.allclose(strided.log_scales.exp(), torch.tensor(2 * 2.0 / 100.0))


def test_densify_mask_on_hand_built_rendering():
    depth = torch.full((4, 5), 2.0)
    depth[0, 0] = 0.0
    alpha = torch.ones(4, 5)
    alpha[1, :2] = 0.2  # not covered by the map
    alpha[0, 0] = 0.0  # not covered but no depth
    rendered = depth.clone() + 0.01 * torch.arange(20).reshape(4, 5) / 20  # small, varying errors
    rendered[3, 4] = 3.0  # map surface 1 m behind the measurement: something new in front
    rendered[2, 2] = 1.0  # map surface in front of the measurement: not densified
    mask = densify_pixel_mask(alpha, rendered, depth, opacity_threshold=0.5, depth_error_ratio=10.0)
    expected = torch.zeros(4, 5, dtype=torch.bool)
    expected[1, :2] = True
    expected[3, 4] = True
    assert torch.equal(mask, expected)
    # empty map: every pixel with depth
    empty = densify_pixel_mask(torch.zeros(4, 5), torch.zeros(4, 5), depth, opacity_threshold=0.5, depth_error_ratio=10.0)
    assert torch.equal(empty, depth > 0)


def test_cap_pixel_mask_keeps_budget_spread_evenly():
    mask = torch.ones(10, 10, dtype=torch.bool)
    capped = cap_pixel_mask(mask, 25)
    assert int(capped.sum()) == 25 and (capped <= mask).all()
    rows = capped.nonzero()[:, 0]
    assert rows.min() == 0 and rows.max() >= 8  # spread over the image, not the first rows
    assert torch.equal(cap_pixel_mask(mask, 1000), mask) and int(cap_pixel_mask(mask, 0).sum()) == 0


def test_prune_mask_drops_transparent_absurd_and_nonfinite_gaussians():
    opacities = torch.tensor([0.9, 0.001, 0.9, 0.9, 0.9, float("nan")])
    scales = torch.tensor([[0.01] * 3, [0.01] * 3, [0.01, 0.01, 2.0], [0.01] * 3, [0.01] * 3, [0.01] * 3])
    means = torch.tensor([[0.0, 0, 2]] * 4 + [[float("inf"), 0, 2], [0.0, 0, 2]])
    distances = distances_to_camera(means, torch.eye(4))
    assert distances[0].item() == pytest.approx(2.0)
    remove = prune_mask(opacities, scales, distances, focal_px=500.0, min_opacity=0.005, max_sigma_px=50.0, means=means)
    # 0.01 m at 2 m with f = 500 is 2.5 px (kept); 2 m at 2 m is 500 px (absurd)
    assert remove.tolist() == [False, True, True, False, True, True]


def test_cap_count_mask_removes_least_opaque_newest_first():
    opacities = torch.tensor([0.5, 0.1, 0.9, 0.1, 0.7, 0.1])
    remove = cap_count_mask(opacities, 4)
    assert remove.tolist() == [False, False, False, True, False, True]
    assert not cap_count_mask(opacities, 6).any() and cap_count_mask(opacities, 0).all()


def test_far_from_existing_keeps_only_gaussians_with_no_centre_within_ratio_sigma():
    existing = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    new = torch.tensor([[0.05, 0.0, 0.0], [0.5, 0.0, 0.0], [1.0, 0.0, 0.19], [3.0, 3.0, 3.0]])
    sigmas = torch.tensor([0.1, 0.1, 0.1, 0.1])
    # Within 2 sigma = 0.2 m: the first and third are near an existing centre.
    assert far_from_existing(new, sigmas, existing, 2.0).tolist() == [False, True, False, True]
    # Per-Gaussian radius: a 1 m sigma reaches the centre 0.5 m away.
    assert far_from_existing(new[1:2], torch.tensor([1.0]), existing, 2.0).tolist() == [False]
    assert far_from_existing(new, sigmas, existing, 0.0).all()  # off
    assert far_from_existing(new, sigmas, existing[:0], 2.0).all()  # empty map
    assert far_from_existing(new[:0], sigmas[:0], existing, 2.0).shape == (0,)


def test_detached_gaussians_keep_their_rates_and_leave_the_graph_and_rows_select_every_field():
    leaf = torch.ones(2, 3, requires_grad=True)
    gaussians = ActivatedGaussians(leaf * 1.0, torch.tensor([[1.0, 0, 0, 0]] * 2), leaf * 0.1, leaf[:, 0] * 0.5,
                                   leaf * 0.2, max_sampling_rate=torch.tensor([10.0, 0.0]))
    frozen = gaussians.detached()
    assert not any(t.requires_grad for t in (frozen.means, frozen.scales, frozen.opacities, frozen.colors))
    assert frozen.max_sampling_rate.tolist() == [10.0, 0.0]
    second = frozen.rows(torch.tensor([1]))
    assert len(second) == 1 and second.max_sampling_rate.tolist() == [0.0]
    assert torch.equal(second.opacities, frozen.opacities[1:]) and torch.equal(second.colors, frozen.colors[1:])
    assert ActivatedGaussians(*(t.detach() for t in (leaf, leaf, leaf, leaf[:, 0], leaf))).detached().max_sampling_rate is None
