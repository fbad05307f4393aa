"""Loop detection: global descriptors, candidate selection and Open3D RGB-D verification.

The views are ray-cast here from an analytic scene (a textured room with three boxes), so depth
and relative poses are exact and nothing depends on other modules' synthetic data.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mipslam.geometry import hat, rotation_angle, se3_exp, se3_from_rt, se3_inverse, so3_exp
from mipslam.loop.descriptors import (
    CandidateOptions,
    DescriptorOptions,
    descriptor_similarity,
    global_descriptor,
    select_loop_candidates,
)
from mipslam.loop.pose_graph import PoseGraph
from mipslam.types import Intrinsics

F64 = torch.float64
ROOM_LO, ROOM_HI = np.array([-3.0, -1.5, -3.0]), np.array([3.0, 1.5, 3.0])
BOXES = [  # (min corner, max corner, colour)
    (np.array([0.6, 0.3, 1.6]), np.array([1.4, 1.5, 2.4]), (0.9, 0.2, 0.2)),
    (np.array([-1.6, 0.7, -2.0]), np.array([-0.8, 1.5, -1.2]), (0.2, 0.3, 0.9)),
    (np.array([-2.0, -0.5, 1.0]), np.array([-1.4, 0.1, 1.6]), (0.9, 0.9, 0.2)),
]
WALLS = {  # (axis, wall at the max side?) -> colour, stripe frequencies along the other two axes
    (0, False): ((0.8, 0.5, 0.3), 1.3, 0.7), (0, True): ((0.3, 0.7, 0.4), 0.9, 1.7),
    (1, False): ((0.9, 0.9, 0.9), 0.5, 0.5), (1, True): ((0.5, 0.4, 0.3), 2.1, 2.1),
    (2, False): ((0.2, 0.4, 0.8), 1.7, 0.4), (2, True): ((0.9, 0.8, 0.3), 0.6, 1.1),
}
SMALL = Intrinsics(fx=60.0, fy=60.0, cx=39.5, cy=29.5, width=80, height=60)
LARGE = Intrinsics(fx=120.0, fy=120.0, cx=79.5, cy=59.5, width=160, height=120)


def camera_pose(position, yaw_deg: float, pitch_deg: float = 0.0) -> torch.Tensor:
    """T_wc of a camera at ``position`` whose optical axis is +z turned by yaw about the world y axis."""
    R = so3_exp(torch.tensor([0.0, math.radians(yaw_deg), 0.0], dtype=F64)) @ so3_exp(
        torch.tensor([math.radians(pitch_deg), 0.0, 0.0], dtype=F64))
    return se3_from_rt(R, torch.tensor(position, dtype=F64))


def render_view(T_wc: torch.Tensor, intr: Intrinsics) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact ray casting: colour [H, W, 3] in [0, 1] and depth [H, W] (camera z, metres)."""
    T = T_wc.numpy()
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1) @ T[:3, :3].T
    origin = T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        exits = np.where(rays > 0, (ROOM_HI - origin) / rays, np.where(rays < 0, (ROOM_LO - origin) / rays, np.inf))
    axis = np.argmin(exits, -1)
    t = np.take_along_axis(exits, axis[..., None], -1)[..., 0]
    at_max = np.take_along_axis(rays, axis[..., None], -1)[..., 0] > 0
    hit = origin + t[..., None] * rays
    color = np.zeros(t.shape + (3,))
    for (ax, side), (base, f1, f2) in WALLS.items():
        mask = (axis == ax) & (at_max == side)
        a, b = [k for k in range(3) if k != ax]
        pattern = 0.5 + 0.5 * np.sin(2 * np.pi * f1 * hit[..., a]) * np.sin(2 * np.pi * f2 * hit[..., b] + 0.3)
        color[mask] = np.array(base) * (0.5 + 0.5 * pattern[mask, None])
    for lo, hi, base in BOXES:
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - origin) / rays, (hi - origin) / rays
        enter, leave = np.nanmax(np.minimum(t1, t2), -1), np.nanmin(np.maximum(t1, t2), -1)
        inside = (enter <= leave) & (enter > 0) & (enter < t)
        t = np.where(inside, enter, t)
        q = origin + enter[..., None] * rays
        pattern = 0.5 + 0.5 * np.sin(9 * q[..., 0] + 7 * q[..., 1] + 5 * q[..., 2])
        color[inside] = np.array(base) * (0.6 + 0.4 * pattern[inside, None])
    return torch.as_tensor(color, dtype=torch.float32), torch.as_tensor(t, dtype=torch.float32)


def test_scene_renderer_is_consistent():
    """Guard of the fixture itself: the forward wall at z = 3 seen from z = -1 is 4 m away at the centre."""
    color, depth = render_view(camera_pose([0.0, 0.0, -1.0], 0.0), SMALL)
    assert depth.shape == (60, 80) and color.shape == (60, 80, 3)
    assert float(depth[29:31, 39:41].mean()) == pytest.approx(4.0, abs=1e-5)
    assert float(color.min()) >= 0 and float(color.max()) <= 1


# ----------------------------------------------------------------------------- descriptors
def test_descriptor_shape_norm_and_self_similarity():
    color, _ = render_view(camera_pose([0.0, 0.0, -1.0], 0.0), SMALL)
    options = DescriptorOptions()
    d = global_descriptor(color, options)
    assert d.shape == (options.dimension,) and d.dtype == torch.float32
    assert float(d.norm()) == pytest.approx(1.0, abs=1e-5)
    assert float(descriptor_similarity(d, d)) == pytest.approx(1.0, abs=1e-5)
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        global_descriptor(color[..., 0], options)


def test_descriptor_ranks_a_revisited_view_above_an_unrelated_one():
    query = global_descriptor(render_view(camera_pose([0.0, 0.0, -1.0], 0.0), SMALL)[0])
    revisit = global_descriptor(render_view(camera_pose([0.15, 0.05, -0.8], 6.0), SMALL)[0])
    behind = global_descriptor(render_view(camera_pose([0.0, 0.0, 1.0], 180.0), SMALL)[0])
    side = global_descriptor(render_view(camera_pose([0.0, 0.0, 0.0], 90.0), SMALL)[0])
    s_revisit = float(descriptor_similarity(query, revisit))
    assert s_revisit > 0.8
    assert s_revisit > float(descriptor_similarity(query, behind)) + 0.4
    assert s_revisit > float(descriptor_similarity(query, side)) + 0.4


def test_descriptor_tolerates_a_small_image_shift_through_its_fft_magnitude():
    color, _ = render_view(camera_pose([0.0, 0.0, -1.0], 0.0), SMALL)
    shifted = torch.roll(color, shifts=(2, 3), dims=(0, 1))
    only_fft = DescriptorOptions(weight_frequency=1.0, weight_gradient=0.0, weight_colour=0.0)
    other, _ = render_view(camera_pose([0.0, 0.0, 1.0], 180.0), SMALL)
    same = float(descriptor_similarity(global_descriptor(color, only_fft), global_descriptor(shifted, only_fft)))
    different = float(descriptor_similarity(global_descriptor(color, only_fft), global_descriptor(other, only_fft)))
    assert same > 0.9 > different


def test_candidate_selection_finds_the_revisit_and_skips_recent_keyframes():
    # a turn on the spot through 15 headings, then back near the first place and heading
    poses = [camera_pose([0.05 * k, 0.0, -1.0 + 0.02 * k], 24.0 * k) for k in range(15)]
    poses.append(camera_pose([0.1, 0.0, -0.9], 4.0))
    poses_t = torch.stack(poses)
    descriptors = torch.stack([global_descriptor(render_view(T, SMALL)[0]) for T in poses])
    options = CandidateOptions(min_gap=5, max_distance_m=2.0, max_view_angle_deg=45.0, min_similarity=0.3)
    candidates = select_loop_candidates(15, descriptors, poses_t, options)
    assert candidates and candidates[0].keyframe == 0
    assert all(c.keyframe <= 15 - options.min_gap for c in candidates)
    assert all(c.view_angle_deg <= 45.0 and c.distance_m <= 2.0 for c in candidates)
    assert list(c.similarity for c in candidates) == sorted((c.similarity for c in candidates), reverse=True)
    # too early in the run for any candidate; and a pose far away vetoes the look-alike
    assert select_loop_candidates(4, descriptors, poses_t, options) == ()
    far = poses_t.clone()
    far[0, :3, 3] += torch.tensor([5.0, 0.0, 0.0], dtype=F64)
    assert all(c.keyframe != 0 for c in select_loop_candidates(15, descriptors, far, options))


# ----------------------------------------------------------------------------- registration
open3d = pytest.importorskip("open3d", reason="Open3D (open3d-cpu + libusb-1.0) is needed for ICP verification")
from mipslam.loop.registration import (  # noqa: E402
    RegistrationOptions,
    information_from_open3d,
    register_rgbd_pair,
)

ICP = RegistrationOptions(voxel_sizes=(0.08, 0.04, 0.02), iterations=(30, 30, 30), pixel_stride=1)


def _pose_error(T_est: torch.Tensor, T_true: torch.Tensor) -> tuple[float, float]:
    E = se3_inverse(T_true) @ T_est
    return float(E[:3, 3].norm()), math.degrees(float(rotation_angle(E[:3, :3])))


@pytest.mark.parametrize("options", [ICP, RegistrationOptions(method="direct"), RegistrationOptions(method="rgbd_odometry")],
                         ids=["point_to_plane", "direct", "rgbd_odometry"])
def test_registration_recovers_a_known_relative_pose(options):
    T_wi, T_wj = camera_pose([0.0, 0.0, -1.0], 0.0), camera_pose([0.15, 0.05, -0.8], 6.0, 2.0)
    color_i, depth_i = render_view(T_wi, LARGE)
    color_j, depth_j = render_view(T_wj, LARGE)
    T_ij_true = se3_inverse(T_wi) @ T_wj
    guess = T_ij_true @ se3_exp(torch.tensor([0.08, -0.05, 0.04, 0.03, -0.05, 0.02], dtype=F64))  # ~8 cm, ~3.5 deg off
    err_guess = _pose_error(guess, T_ij_true)
    result = register_rgbd_pair(color_i, depth_i, color_j, depth_j, LARGE, guess, options)
    assert result.accepted, result.reason
    err_t, err_deg = _pose_error(result.T_ij, T_ij_true)
    assert err_guess[0] > 0.08 and err_guess[1] > 3.0
    # sub-pixel: one pixel spans 2-3 cm at the 2-4 m depths of these 160 x 120 views
    assert err_t < 0.02 and err_deg < 0.5
    assert err_t < 0.2 * err_guess[0] and err_deg < 0.2 * err_guess[1]
    assert result.fitness > 0.6 and result.inlier_rmse_m < options.rmse_threshold
    # the information is symmetric positive definite and usable as a pose-graph edge as is
    info = result.information
    assert torch.allclose(info, info.T) and float(torch.linalg.eigvalsh(info).min()) > 0
    graph = PoseGraph.from_odometry(torch.stack([T_wi, T_wj]), torch.eye(6, dtype=F64)).add_edge(
        0, 1, result.T_ij, info, "loop")
    assert graph.num_edges == 2


def test_open3d_information_is_converted_to_the_residual_frame():
    """Direct check: for e_ij (right perturbation, camera j) each correspondence contributes
    G^T G with G = [I | -[q]x] at the source point q (camera-j coordinates)."""
    gen = torch.Generator().manual_seed(2)
    source = torch.randn(300, 3, generator=gen, dtype=F64) + torch.tensor([0.0, 0.0, 3.0], dtype=F64)
    T_ij = se3_exp(torch.tensor([0.4, -0.2, 0.3, 0.3, -0.5, 0.8], dtype=F64))
    target = source @ T_ij[:3, :3].T + T_ij[:3, 3]
    clouds = [open3d.geometry.PointCloud(open3d.utility.Vector3dVector(p.numpy())) for p in (source, target)]
    info_o3d = open3d.pipelines.registration.get_information_matrix_from_point_clouds(
        clouds[0], clouds[1], 0.01, T_ij.numpy())
    converted = information_from_open3d(torch.as_tensor(np.asarray(info_o3d)), T_ij)
    G = torch.cat([torch.eye(3, dtype=F64).expand(300, 3, 3), -hat(source)], -1)  # [300, 3, 6]
    expected = (G.transpose(1, 2) @ G).sum(0)
    assert torch.allclose(converted, expected, rtol=1e-9, atol=1e-6)


@pytest.mark.parametrize("method", ["point_to_plane", "direct"])
def test_registration_rejects_a_wrong_pair(method):
    T_wi = camera_pose([0.0, 0.0, -1.0], 0.0)
    T_wj = camera_pose([0.0, 0.0, 1.0], 180.0)  # looks at the opposite wall: no overlap
    color_i, depth_i = render_view(T_wi, SMALL)
    color_j, depth_j = render_view(T_wj, SMALL)
    claimed = torch.eye(4, dtype=F64)  # a wrong "loop" claiming both views coincide
    result = register_rgbd_pair(color_i, depth_i, color_j, depth_j, SMALL, claimed,
                                RegistrationOptions(method=method, voxel_sizes=(0.1, 0.05), iterations=(30, 30)))
    assert not result.accepted
    assert result.reason
    assert float(result.information.abs().max()) == 0.0


@pytest.mark.parametrize("method", ["point_to_plane", "direct"])
def test_registration_rejects_frames_without_depth(method):
    color, depth = render_view(camera_pose([0.0, 0.0, -1.0], 0.0), SMALL)
    result = register_rgbd_pair(color, torch.zeros_like(depth), color, depth, SMALL, torch.eye(4, dtype=F64),
                                RegistrationOptions(method=method))
    assert not result.accepted and "too few" in result.reason
