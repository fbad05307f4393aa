"""The Mip-Splatting 3D smoothing filter belongs to the map (``render.filter_3d``).

Its size comes from each Gaussian's highest sampling rate among the keyframes that trained it
(``GaussianMap.max_sampling_rate``), so rendering the map at 1/8 of the mapping resolution must use
the same filter as at full resolution. Before the rates were stored, the renderer took them from the
camera that drew the image, so at 1/8 the filter was 64x wider in variance and the image went dark
(18 dB instead of 31.5 dB on data_synth, docs/evaluation.md).
"""
from __future__ import annotations

import math

import pytest
import torch

from mipslam.mapping import MappingOptions
from mipslam.config import RenderConfig
from mipslam.errors import DatasetError
from mipslam.gaussians import GaussianMap, gaussians_from_rgbd
from mipslam.gaussians.optimizer import GaussianOptimizer
from mipslam.geometry import se3_inverse
from mipslam.io.ply import read_map_ply, splats_from_map, write_map_ply, write_ply
from mipslam.mapping import Mapper, MappingView
from mipslam.rendering import filter_sampling_rates, render_view, view_sampling_rates
from mipslam.types import Intrinsics

INTRINSICS = Intrinsics(fx=40.0, fy=40.0, cx=23.5, cy=17.5, width=48, height=36)
FILTER_SCALE = 0.2


def textured_wall(depth_m: float = 2.0) -> tuple[torch.Tensor, torch.Tensor]:
    """A fronto-parallel wall with a fine checkerboard: colour [H, W, 3], depth [H, W]."""
    v, u = torch.meshgrid(torch.arange(INTRINSICS.height), torch.arange(INTRINSICS.width), indexing="ij")
    checker = ((u // 2 + v // 2) % 2).float()
    color = torch.stack([0.2 + 0.6 * checker, 0.5 * torch.ones_like(checker), 0.8 - 0.6 * checker], -1)
    return color, torch.full((INTRINSICS.height, INTRINSICS.width), depth_m)


def wall_map(T_wc: torch.Tensor) -> GaussianMap:
    color, depth = textured_wall()
    params = gaussians_from_rgbd(color, depth, INTRINSICS.matrix(), T_wc.float(), initial_opacity=0.9)
    return GaussianMap(params)


def baked(gmap: GaussianMap, path) -> GaussianMap:
    """The same map with its 3D filter folded into scales and opacities (what a viewer gets), read back."""
    write_map_ply(path, gmap, FILTER_SCALE / gmap.max_sampling_rate ** 2)
    return read_map_ply(path)


def test_new_gaussians_carry_the_sampling_rate_of_the_view_that_made_them():
    gmap = wall_map(torch.eye(4, dtype=torch.float64))
    assert torch.allclose(gmap.max_sampling_rate, torch.full((len(gmap),), 40.0 / 2.0))


@pytest.mark.parametrize("backend", ["torch", "auto"])  # auto: the compiled CPU kernels where they build
@pytest.mark.parametrize("mode", ["mip", "eaa", "point"])
@pytest.mark.parametrize("scale", [1.0, 0.25, 0.125])
def test_the_filter_is_the_map_s_at_every_render_resolution(mode, scale, backend, tmp_path):
    """filter_3d on == the filter baked into the map and rendered without it, at every scale."""
    T_wc = torch.eye(4, dtype=torch.float64)
    gmap = wall_map(T_wc)
    intrinsics = INTRINSICS.scaled(scale)
    T_cw = se3_inverse(T_wc).float()
    with torch.no_grad():
        with_filter = render_view(gmap.activated(), T_cw, intrinsics,
                                  RenderConfig(mode=mode, filter_3d=True, backend=backend))
        reference = render_view(baked(gmap, tmp_path / "baked.ply").activated(), T_cw, intrinsics,
                                RenderConfig(mode=mode, backend=backend))
    assert torch.allclose(with_filter.color, reference.color, atol=2e-3)
    assert torch.allclose(with_filter.alpha, reference.alpha, atol=2e-3)
    if scale < 1:  # an image of the wall, not a dark one: the filter did not grow with the smaller camera
        assert float(with_filter.alpha.mean()) > 0.85


def test_unknown_rates_fall_back_to_the_rendering_camera():
    """A map read from a plain 3DGS PLY has no rates: the camera's f / z sizes the filter, as before."""
    gmap = wall_map(torch.eye(4, dtype=torch.float64))
    unknown = GaussianMap(gmap.detached())
    unknown.max_sampling_rate = torch.zeros(len(gmap))
    cfg = RenderConfig(mode="mip", filter_3d=True, backend="torch")
    same = render_view(unknown.activated(), torch.eye(4), INTRINSICS, cfg)  # this camera is the creating one
    stored = render_view(gmap.activated(), torch.eye(4), INTRINSICS, cfg)
    assert torch.allclose(same.color, stored.color, atol=1e-5)


def test_a_map_with_some_rates_unknown_uses_the_camera_for_those_rows_only():
    gmap = wall_map(torch.eye(4, dtype=torch.float64))  # every centre at z = 2 m: the camera's rate is 20 px/m
    gmap.max_sampling_rate[::2] = 0.0
    gmap.max_sampling_rate[1::2] = 55.0
    K = INTRINSICS.matrix().float()
    rates = filter_sampling_rates(gmap.activated(), torch.eye(4), K)
    assert torch.allclose(rates[::2], torch.full_like(rates[::2], 20.0))
    assert torch.equal(rates[1::2], torch.full_like(rates[1::2], 55.0))
    gmap.max_sampling_rate.zero_()
    assert filter_sampling_rates(gmap.activated(), torch.eye(4), K) is None  # the renderer's own, as before


def test_view_sampling_rates_see_the_image_plus_a_margin():
    means = torch.tensor([[0.0, 0.0, 2.0],  # centre of the image
                          [0.0, 0.0, -2.0],  # behind the camera
                          [1.5, 0.0, 2.0],  # u = 23.5 + 30 = 53.5: inside the 15 % margin (47.5 + 7.2)
                          [4.0, 0.0, 2.0]])  # far outside
    rates = view_sampling_rates(means, torch.eye(4), INTRINSICS)
    assert rates.tolist() == pytest.approx([20.0, 0.0, 20.0, 0.0])


def test_mapping_keeps_the_highest_rate_of_the_views_that_train_a_gaussian():
    color, depth = textured_wall()
    far = torch.eye(4, dtype=torch.float64)
    near = torch.eye(4, dtype=torch.float64)
    near[2, 3] = 0.5  # half a metre closer to the wall: f / z = 40 / 1.5
    gmap = GaussianMap.empty()
    optimizer = GaussianOptimizer.from_config(gmap, MappingOptions())
    mapper = Mapper(MappingOptions(densify_pixel_stride=4), RenderConfig(backend="torch", filter_3d=True))
    views = [MappingView(1, color, depth, far, torch.zeros(2), INTRINSICS, False),
             MappingView(0, color, torch.full_like(depth, 1.5), near, torch.zeros(2), INTRINSICS, False)]
    mapper.map_keyframe(gmap, optimizer, views, iterations=2, generator=torch.Generator().manual_seed(0),
                        frame_index=1)
    assert len(gmap) > 0
    # every Gaussian was made by the far view and seen by the near one, which samples it more finely
    expected = torch.stack([view_sampling_rates(gmap.means, se3_inverse(v.T_wc).float(), INTRINSICS)
                            for v in views]).amax(0)
    assert torch.all(gmap.max_sampling_rate >= 40.0 / 2.0 - 1e-3)
    assert torch.allclose(gmap.max_sampling_rate, torch.maximum(expected, gmap.max_sampling_rate.new_tensor(0)),
                          rtol=0.05)
    assert float(gmap.max_sampling_rate.max()) > 40.0 / 2.0 + 1.0


def test_rates_survive_the_ply_and_the_checkpoint_state(tmp_path):
    gmap = wall_map(torch.eye(4, dtype=torch.float64))
    gmap.max_sampling_rate = torch.linspace(5.0, 50.0, len(gmap))
    write_map_ply(tmp_path / "map.ply", gmap)
    assert torch.equal(read_map_ply(tmp_path / "map.ply").max_sampling_rate, gmap.max_sampling_rate)
    # a baked filter must not be applied twice: the file then has no rates
    write_map_ply(tmp_path / "baked.ply", gmap, FILTER_SCALE / gmap.max_sampling_rate ** 2)
    assert torch.count_nonzero(read_map_ply(tmp_path / "baked.ply").max_sampling_rate) == 0
    state = gmap.state_dict()
    assert torch.equal(GaussianMap.from_state_dict(state).max_sampling_rate, gmap.max_sampling_rate)
    del state["max_sampling_rate"]  # a checkpoint from before the rates existed: unknown, not an error
    assert torch.count_nonzero(GaussianMap.from_state_dict(state).max_sampling_rate) == 0


def test_a_ply_with_corrupt_rates_is_rejected_by_name(tmp_path):
    gmap = wall_map(torch.eye(4, dtype=torch.float64))
    splats = splats_from_map(gmap)
    rates = splats.max_sampling_rate.clone()
    rates[3] = -1.0
    write_ply(tmp_path / "bad.ply", type(splats)(**{**splats.__dict__, "max_sampling_rate": rates}))
    with pytest.raises(DatasetError, match=r"bad\.ply.*vertex 3.*max_sampling_rate"):
        read_map_ply(tmp_path / "bad.ply")
    rates[3] = math.nan
    write_ply(tmp_path / "nan.ply", type(splats)(**{**splats.__dict__, "max_sampling_rate": rates}))
    with pytest.raises(DatasetError, match="vertex 3"):
        read_map_ply(tmp_path / "nan.ply")
