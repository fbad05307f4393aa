"""Noisy synthetic pose graphs with exact ground truth (for tests and the pgo and scaling benchmark scenarios).

The camera runs ``laps`` times around a circle (radius ``radius`` m) with a gentle height and
pitch oscillation. Odometry edges join consecutive keyframes; their measurements are the true
relative poses perturbed on the right by ``Exp(n)``, ``n ~ N(0, diag(sigma_t^2 I3, sigma_r^2 I3))``.
In "noisy segments" (a fraction of the chain, in bursts) the noise is ``segment_noise_factor``
times larger while the stated information stays nominal: tracking quality that the tracker's
information does not reflect, which is the situation spectral edge weighting addresses. Loop
edges join keyframes at the same place on different laps (every ``loop_every`` keyframes), with
smaller noise; outlier loops join random far-apart keyframes with a wrong relative pose (the true
one times ``Exp(n)``, ``n ~ N(0, diag(outlier_translation_m^2 I3, outlier_rotation_rad^2 I3))``)
and the same information as correct loops. Initial poses are the odometry chain composed from the true
first pose, so the gauge node (0) is exact.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from mipslam.geometry import rotation_angle, se3_exp, se3_from_rt, se3_inverse, so3_exp
from mipslam.loop.pose_graph import PoseGraph


@dataclass(frozen=True)
class SyntheticPoseGraph:
    """graph: initial (drifted) poses and all edges; poses_true: ground truth T_wc [N, 4, 4];
    outlier_edges: indices of the wrong loop edges; noisy_nodes: first nodes of the noisy-segment edges."""

    graph: PoseGraph
    poses_true: torch.Tensor
    outlier_edges: tuple[int, ...]
    noisy_edges: tuple[int, ...]


def circle_trajectory(num_nodes: int, laps: float = 2.0, radius: float = 5.0) -> torch.Tensor:
    """Smooth ground-truth keyframe poses T_wc on a circle, camera looking along the tangent.  -> [N, 4, 4]"""
    angle = torch.arange(num_nodes, dtype=torch.float64) * (2 * math.pi * laps / num_nodes)
    position = torch.stack([radius * torch.cos(angle), radius * torch.sin(angle), 0.3 * torch.sin(3 * angle)], -1)
    # OpenCV camera: z forward along the tangent, y down (world -z), x = y cross z
    forward = torch.stack([-torch.sin(angle), torch.cos(angle), torch.zeros_like(angle)], -1)
    down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand_as(forward)
    right = torch.cross(down, forward, dim=-1)
    R = torch.stack([right, down, forward], -1)  # columns are the camera axes in world
    wobble = so3_exp(torch.stack([0.1 * torch.sin(5 * angle), 0.05 * torch.cos(7 * angle), torch.zeros_like(angle)], -1))
    return se3_from_rt(R @ wobble, position)


def make_synthetic_pose_graph(
    num_nodes: int = 100,
    laps: float = 2.0,
    radius: float = 5.0,
    sigma_translation: float = 0.01,
    sigma_rotation: float = 0.005,
    loop_sigma_translation: float = 0.005,
    loop_sigma_rotation: float = 0.002,
    loop_every: int = 5,
    num_outlier_loops: int = 0,
    outlier_translation_m: float = 1.0,
    outlier_rotation_rad: float = 0.3,
    noisy_fraction: float = 0.0,
    segment_noise_factor: float = 5.0,
    segment_length: int = 10,
    seed: int = 0,
) -> SyntheticPoseGraph:
    """A noisy chain with loop closures (and optional outliers / noisy segments); see the module docstring."""
    gen = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    truth = circle_trajectory(num_nodes, laps, radius)
    n_odo = num_nodes - 1

    factor = torch.ones(n_odo, dtype=torch.float64)
    noisy: list[int] = []
    if noisy_fraction > 0 and n_odo > segment_length:
        num_segments = max(1, int(round(noisy_fraction * n_odo / segment_length)))
        starts = rng.choice(np.arange(1, n_odo - segment_length), size=num_segments, replace=False)
        for s in starts:
            factor[s : s + segment_length] = segment_noise_factor
        noisy = sorted(int(k) for k in torch.nonzero(factor > 1).ravel())
    sigma = torch.tensor([sigma_translation] * 3 + [sigma_rotation] * 3, dtype=torch.float64)
    noise = torch.randn(n_odo, 6, generator=gen, dtype=torch.float64) * sigma * factor[:, None]
    Z_odo = se3_inverse(truth[:-1]) @ truth[1:] @ se3_exp(noise)
    info_odo = torch.diag(1.0 / sigma**2)

    poses = [truth[0]]
    for k in range(n_odo):
        poses.append(poses[-1] @ Z_odo[k])
    graph = PoseGraph.from_odometry(truth, info_odo).with_poses(torch.stack(poses))
    graph = PoseGraph(graph.poses, graph.edge_nodes, Z_odo, graph.information, graph.edge_is_loop)

    loop_sigma = torch.tensor([loop_sigma_translation] * 3 + [loop_sigma_rotation] * 3, dtype=torch.float64)
    info_loop = torch.diag(1.0 / loop_sigma**2)
    per_lap = num_nodes / laps
    pairs: list[tuple[int, int]] = []
    for j in range(num_nodes):
        lap = int(j // per_lap)
        if lap == 0 or j % loop_every:
            continue
        i = int(round(j - per_lap))  # same place, previous lap
        if i >= 0 and j - i >= 2:
            pairs.append((i, j))
    loop_noise = torch.randn(len(pairs), 6, generator=gen, dtype=torch.float64) * loop_sigma

    num_correct = len(pairs)
    for _ in range(num_outlier_loops):
        while True:
            i, j = sorted(int(v) for v in rng.choice(num_nodes, size=2, replace=False))
            if j - i > max(10, num_nodes // 10):
                break
        pairs.append((i, j))
    wrong = torch.cat([torch.randn(num_outlier_loops, 3, generator=gen, dtype=torch.float64) * outlier_translation_m,
                       torch.randn(num_outlier_loops, 3, generator=gen, dtype=torch.float64) * outlier_rotation_rad], -1)
    if pairs:
        ij = torch.tensor(pairs, dtype=torch.int64)
        Z = se3_inverse(truth[ij[:, 0]]) @ truth[ij[:, 1]] @ se3_exp(torch.cat([loop_noise, wrong]))
        graph = PoseGraph(
            graph.poses,
            torch.cat([graph.edge_nodes, ij]),
            torch.cat([graph.measurements, Z]),
            torch.cat([graph.information, info_loop.expand(len(pairs), 6, 6)]),
            torch.cat([graph.edge_is_loop, torch.ones(len(pairs), dtype=torch.bool)]),
        )
    outliers = tuple(range(n_odo + num_correct, n_odo + len(pairs)))
    return SyntheticPoseGraph(graph, truth, outliers, tuple(noisy))


@dataclass(frozen=True)
class TrajectoryErrors:
    """RMSE over nodes, without alignment (the gauge node is at the truth): metres and degrees."""

    translation_rmse_m: float
    rotation_rmse_deg: float


def trajectory_errors(poses: torch.Tensor, poses_true: torch.Tensor) -> TrajectoryErrors:
    """Per-node position and orientation error RMSE.  poses [N, 4, 4], poses_true [N, 4, 4]"""
    dt = poses[:, :3, 3] - poses_true[:, :3, 3]
    dR = poses_true[:, :3, :3].transpose(1, 2) @ poses[:, :3, :3]
    angle = rotation_angle(dR)
    return TrajectoryErrors(
        translation_rmse_m=float(dt.pow(2).sum(-1).mean().sqrt()),
        rotation_rmse_deg=float(torch.rad2deg(angle).pow(2).mean().sqrt()),
    )
