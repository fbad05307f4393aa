"""Geometric verification of a loop candidate: register two keyframes' RGB-D point clouds (Open3D).

``register_rgbd_pair`` back-projects both keyframes (camera frames, metres), down-samples them
on a voxel grid coarse to fine, and runs point-to-plane or coloured ICP (Park et al. 2017)
initialised from the current estimate of the relative pose. Conventions:

* keyframe i is the *target*, keyframe j the *source*; the result ``T_ij`` maps camera-j points
  into camera i (``p_i = T_ij p_j``), i.e. it measures ``T_i^-1 T_j`` - exactly the measurement
  :meth:`mipslam.loop.pose_graph.PoseGraph.add_edge` takes for edge (i, j);
* the information matrix is Open3D's ``get_information_matrix_from_point_clouds`` (sum over
  correspondences of ``G^T G``, ``G = [-[p]x | I]`` at the target points, rotation first, for a
  left perturbation in camera i), converted to this project's order ``[rho, phi]`` and to the
  residual's frame: ``Omega_e = Ad(T_ij)^T P Omega_o3d P^T Ad(T_ij)`` (``e = Ad(T_ij^-1) delta``).
  Open3D's matrix treats every correspondence as an independent unit-variance measurement; it is
  divided by ``point_sigma_m^2`` and scaled by ``min(1, max_independent_points / n)`` so that
  thousands of correlated correspondences do not claim sub-millimetre certainty.

A registration is accepted when fitness (fraction of source points with a correspondence)
reaches ``fitness_threshold``, the inlier RMSE stays below ``rmse_threshold``, and ICP did not
move the estimate further than ``max_correction_m`` / ``max_correction_deg`` from the initial
guess (a jump that large means it slid into another basin).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from mipslam.errors import MipslamError
from mipslam.geometry import rotation_angle, unproject_depth
from mipslam.loop.pose_graph import adjoint
from mipslam.types import Intrinsics

logger = logging.getLogger(__name__)

# Open3D orders a twist (rotation, translation); this project orders it (rho = translation, phi = rotation).
_O3D_TO_RHO_PHI = np.r_[3, 4, 5, 0, 1, 2]


def _open3d():
    """Import Open3D on first use, with a message that says how to fix a failed import."""
    try:
        import open3d as o3d
    except ImportError as err:  # open3d missing, or its system library libusb-1.0 missing
        raise MipslamError(
            f"geometric loop verification needs Open3D, which failed to import ({err}); install the "
            "'open3d-cpu' package and, on Debian/Ubuntu, the system library 'libusb-1.0-0'"
        ) from err
    return o3d


@dataclass(frozen=True)
class RegistrationOptions:
    """Settings of :func:`register_rgbd_pair` (lengths in metres)."""

    method: Literal["point_to_plane", "colored"] = "point_to_plane"
    voxel_sizes: tuple[float, ...] = (0.04, 0.02)  # coarse to fine
    iterations: tuple[int, ...] = (30, 20)  # ICP iterations per scale
    correspondence_factor: float = 2.0  # max correspondence distance = factor x voxel size
    pixel_stride: int = 2
    min_depth_m: float = 0.1
    max_depth_m: float = 5.0
    min_points: int = 200
    fitness_threshold: float = 0.3
    rmse_threshold: float = 0.05
    max_correction_m: float = 0.5
    max_correction_deg: float = 30.0
    point_sigma_m: float = 0.02
    max_independent_points: int = 500

    def __post_init__(self):
        if not self.voxel_sizes or len(self.voxel_sizes) != len(self.iterations):
            raise ValueError("RegistrationOptions: voxel_sizes and iterations need one entry per scale")
        if self.method not in ("point_to_plane", "colored"):
            raise ValueError(f"RegistrationOptions.method must be 'point_to_plane' or 'colored', got {self.method!r}")


@dataclass(frozen=True)
class RegistrationResult:
    """Outcome of verifying edge (i, j).

    T_ij: camera j -> camera i, the measurement for edge (i, j), float64          # [4, 4]
    information: information of e_ij in the order [rho, phi], float64            # [6, 6]
    fitness / inlier_rmse_m / num_correspondences: Open3D's, at the finest scale
    correction_m / correction_deg: how far ICP moved from the initial guess
    accepted: all thresholds passed; reason: why not (empty when accepted)
    """

    T_ij: torch.Tensor
    information: torch.Tensor
    fitness: float
    inlier_rmse_m: float
    num_correspondences: int
    correction_m: float
    correction_deg: float
    accepted: bool
    reason: str
    time_s: float


def rgbd_point_cloud(
    color: torch.Tensor,
    depth: torch.Tensor,
    intrinsics: Intrinsics,
    pixel_stride: int = 1,
    min_depth_m: float = 0.1,
    max_depth_m: float = 5.0,
):
    """Open3D point cloud of one RGB-D frame in its camera frame (points with valid depth only).

    color [H, W, 3] in [0, 1], depth [H, W] metres (0 = none) -> open3d.geometry.PointCloud
    """
    o3d = _open3d()
    if depth.dim() != 2 or color.shape[:2] != depth.shape or color.shape[-1] != 3:
        raise ValueError(f"rgbd_point_cloud expects color [H, W, 3] and depth [H, W], got {tuple(color.shape)} and {tuple(depth.shape)}")
    K = intrinsics.matrix(dtype=torch.float64, device=depth.device)
    points = unproject_depth(depth.to(torch.float64), K)[::pixel_stride, ::pixel_stride].reshape(-1, 3)
    colours = color[::pixel_stride, ::pixel_stride].reshape(-1, 3).to(torch.float64)
    z = points[:, 2]
    valid = (z > min_depth_m) & (z < max_depth_m) & torch.isfinite(z)
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(points[valid].cpu().numpy())
    cloud.colors = o3d.utility.Vector3dVector(colours[valid].clamp(0, 1).cpu().numpy())
    return cloud


def information_from_open3d(info_o3d: torch.Tensor, T_ij: torch.Tensor) -> torch.Tensor:
    """Open3D's registration information -> information of the pose-graph residual e_ij.

    info_o3d: ``get_information_matrix_from_point_clouds`` output, order (rotation, translation),
    for a left perturbation of T_ij in camera i (target)                              # [6, 6]
    T_ij: the registered relative pose (camera j -> camera i)                          # [4, 4]
    -> ``Ad(T_ij)^T P info P^T Ad(T_ij)`` in the order [rho, phi] for e_ij (camera j)   # [6, 6] float64
    """
    perm = torch.as_tensor(_O3D_TO_RHO_PHI)
    info_delta = info_o3d.to(torch.float64)[perm][:, perm]
    Ad = adjoint(T_ij.to(torch.float64))
    information = Ad.T @ info_delta @ Ad
    return 0.5 * (information + information.T)


def _rejected(T_ij, fitness, rmse, n, corr_m, corr_deg, reason, start) -> RegistrationResult:
    return RegistrationResult(T_ij, torch.zeros(6, 6, dtype=torch.float64), fitness, rmse, n, corr_m, corr_deg,
                              False, reason, time.perf_counter() - start)


def register_point_clouds(source, target, T_ij_init: torch.Tensor, options: RegistrationOptions = RegistrationOptions()) -> RegistrationResult:
    """Register Open3D clouds: source = keyframe j, target = keyframe i, both in their camera frames.

    T_ij_init: initial guess of T_i^-1 T_j  # [4, 4]
    """
    o3d = _open3d()
    reg = o3d.pipelines.registration
    start = time.perf_counter()
    init = T_ij_init.detach().to(torch.float64).cpu().numpy()
    if min(len(source.points), len(target.points)) < options.min_points:
        n = min(len(source.points), len(target.points))
        return _rejected(T_ij_init.to(torch.float64).cpu(), 0.0, math.inf, 0, 0.0, 0.0,
                         f"too few valid depth points ({n} < {options.min_points})", start)
    current = init.copy()
    result = None
    src_down = tgt_down = None
    max_distance = options.correspondence_factor * options.voxel_sizes[-1]
    for voxel, iterations in zip(options.voxel_sizes, options.iterations):
        src_down = source.voxel_down_sample(voxel)
        tgt_down = target.voxel_down_sample(voxel)
        search = o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * voxel, max_nn=30)
        src_down.estimate_normals(search)
        tgt_down.estimate_normals(search)
        max_distance = options.correspondence_factor * voxel
        criteria = reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=iterations)
        if options.method == "colored":
            result = reg.registration_colored_icp(src_down, tgt_down, max_distance, current,
                                                  reg.TransformationEstimationForColoredICP(), criteria)
        else:
            result = reg.registration_icp(src_down, tgt_down, max_distance, current,
                                          reg.TransformationEstimationPointToPlane(), criteria)
        current = np.asarray(result.transformation)

    T_ij = torch.as_tensor(current.copy(), dtype=torch.float64)
    change = torch.linalg.inv(T_ij_init.detach().to(torch.float64).cpu()) @ T_ij
    correction_m = float(change[:3, 3].norm())
    correction_deg = float(torch.rad2deg(rotation_angle(change[:3, :3])))
    fitness, rmse = float(result.fitness), float(result.inlier_rmse)
    n = len(result.correspondence_set)
    reasons = []
    if fitness < options.fitness_threshold:
        reasons.append(f"fitness {fitness:.3f} < {options.fitness_threshold}")
    if n == 0 or rmse > options.rmse_threshold:
        reasons.append(f"inlier RMSE {rmse:.4f} m > {options.rmse_threshold} m")
    if correction_m > options.max_correction_m or correction_deg > options.max_correction_deg:
        reasons.append(f"ICP moved {correction_m:.3f} m / {correction_deg:.1f} deg from the initial guess")
    if reasons:
        return _rejected(T_ij, fitness, rmse, n, correction_m, correction_deg, "; ".join(reasons), start)

    info_o3d = np.asarray(reg.get_information_matrix_from_point_clouds(src_down, tgt_down, max_distance, current))
    scale = min(1.0, options.max_independent_points / max(n, 1)) / options.point_sigma_m**2
    information = information_from_open3d(torch.as_tensor(info_o3d), T_ij) * scale
    return RegistrationResult(T_ij, information, fitness, rmse, n, correction_m, correction_deg, True, "",
                              time.perf_counter() - start)


def register_rgbd_pair(
    color_i: torch.Tensor,
    depth_i: torch.Tensor,
    color_j: torch.Tensor,
    depth_j: torch.Tensor,
    intrinsics: Intrinsics,
    T_ij_init: torch.Tensor,
    options: RegistrationOptions = RegistrationOptions(),
) -> RegistrationResult:
    """Verify a loop between keyframes i (target) and j (source) by ICP on their RGB-D clouds.

    color_* [H, W, 3] in [0, 1], depth_* [H, W] metres, T_ij_init [4, 4] = current T_i^-1 T_j.
    """
    kw = dict(pixel_stride=options.pixel_stride, min_depth_m=options.min_depth_m, max_depth_m=options.max_depth_m)
    target = rgbd_point_cloud(color_i, depth_i, intrinsics, **kw)
    source = rgbd_point_cloud(color_j, depth_j, intrinsics, **kw)
    result = register_point_clouds(source, target, T_ij_init, options)
    logger.debug("loop verification: fitness %.3f, rmse %.4f m, accepted=%s %s", result.fitness,
                 result.inlier_rmse_m, result.accepted, result.reason)
    return result
