"""Geometric verification of a loop candidate: register two keyframes' RGB-D data (Open3D).

``register_rgbd_pair`` aligns keyframe j to keyframe i, initialised from the current estimate of
the relative pose, with one of three methods:

* ``point_to_plane`` / ``colored``: back-project both keyframes (camera frames, metres),
  down-sample them on a voxel grid coarse to fine and run point-to-plane or coloured ICP
  (Park et al. 2017);
* ``rgbd_odometry``: dense direct RGB-D alignment on image pyramids (Open3D's
  ``compute_rgbd_odometry`` with the hybrid photometric + depth Jacobian, Steinbruecker et al.
  2011 / Park et al. 2017), then the same point-cloud checks at the result. Point-to-plane ICP
  slides along the large planes of a room (a wall seen head-on constrains only 3 of 6 degrees of
  freedom) while still reporting a high fitness; the photometric term pins the sliding directions
  wherever the surfaces are textured (docs/pgo.md, "Verification in the SLAM loop");
* ``direct``: the same kind of alignment by tracking's Gauss-Newton (:mod:`mipslam.geometry.direct`,
  compiled where the CPU library is built: Huber-weighted intensity and depth residuals at robust
  scales, the brightness offset removed) on a pyramid whose finest level is ``direct_scale`` of the
  keyframes, then the same point-cloud checks; about 5x faster than ``rgbd_odometry``. Its basin is
  narrower, so a result that moved the estimate by more than ``direct_trust_m`` / ``direct_trust_deg``
  is redone by ``rgbd_odometry`` from the same start.

Conventions:

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
from mipslam.geometry import resize_area, rotation_angle, unproject_depth
from mipslam.geometry.direct import DirectReference, DirectTarget, direct_reference, direct_target, pyramid_scales
from mipslam.loop.pose_graph import adjoint
from mipslam.types import Intrinsics

logger = logging.getLogger(__name__)

# Open3D orders a twist (rotation, translation); this project orders it (rho = translation, phi = rotation).
_O3D_TO_RHO_PHI = np.r_[3, 4, 5, 0, 1, 2]
_GREY = (0.299, 0.587, 0.114)


def load_open3d():
    """Import Open3D (on first use, or at a run's set-up), with a message that says how to fix a failed import."""
    try:
        import open3d as o3d
    except ImportError as err:  # open3d missing, or its system library libusb-1.0 missing
        raise MipslamError(
            f"geometric loop verification needs Open3D, which failed to import ({err}); install the "
            "'open3d-cpu' package and, on Debian/Ubuntu, the system library 'libusb-1.0-0'"
        ) from err
    # One thread: Open3D's parallel reductions (ICP normal equations, information matrices) sum in an
    # order that changes from run to run, which broke bit-identical resume (docs/robustness.md, "Interrupted runs").
    # A registration takes a few milliseconds at SLAM resolutions, so nothing is lost.
    if hasattr(o3d.utility, "set_max_threads") and o3d.utility.get_max_threads() != 1:
        o3d.utility.set_max_threads(1)
    return o3d


@dataclass(frozen=True)
class RegistrationOptions:
    """Settings of :func:`register_rgbd_pair` (lengths in metres)."""

    method: Literal["point_to_plane", "colored", "rgbd_odometry", "direct"] = "point_to_plane"
    voxel_sizes: tuple[float, ...] = (0.04, 0.02)  # coarse to fine (the finest one also for the checks)
    iterations: tuple[int, ...] = (30, 20)  # ICP iterations per scale
    odometry_iterations: tuple[int, ...] = (40, 20, 10)  # rgbd_odometry: per pyramid level, coarse to fine
    odometry_depth_difference_m: float = 0.07  # rgbd_odometry: largest depth difference of a correspondence
    direct_scale: float = 0.5  # direct: the finest pyramid level, a fraction of the keyframes' resolution ...
    direct_min_width: int = 160  # ... but never below this many pixels wide (small keyframes keep theirs)
    direct_levels: int = 3  # direct: pyramid levels, each half the next
    direct_iterations: int = 20  # direct: Gauss-Newton steps per level at most
    direct_alpha_color: float = 0.5  # direct: weight of the intensity term against depth (robust-scale units)
    direct_depth_noise_power: float = 0.0  # direct: depth residuals in units of z^p (align_direct's depth_noise_power)
    # direct: an alignment that moves the estimate further than this is redone by Open3D's rgbd_odometry, whose
    # basin is wider (15 deg of rotation at 40x30 where Gauss-Newton's ends near 10; docs/pgo.md)
    direct_trust_m: float = 0.1
    direct_trust_deg: float = 5.0
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
        if self.method not in ("point_to_plane", "colored", "rgbd_odometry", "direct"):
            raise ValueError("RegistrationOptions.method must be 'point_to_plane', 'colored', 'rgbd_odometry' or "
                             f"'direct', got {self.method!r}")
        if not (0.0 < self.direct_scale <= 1.0 and self.direct_min_width >= 1 and self.direct_levels >= 1
                and self.direct_iterations >= 1 and 0.0 <= self.direct_alpha_color <= 1.0
                and self.direct_depth_noise_power >= 0
                and self.direct_trust_m >= 0 and self.direct_trust_deg >= 0):
            raise ValueError("RegistrationOptions: direct_scale must be in (0, 1], direct_min_width, direct_levels "
                             "and direct_iterations >= 1, direct_alpha_color in [0, 1], direct_depth_noise_power and "
                             "direct_trust_* >= 0")
        if not self.odometry_iterations or min(self.odometry_iterations) < 1:
            raise ValueError("RegistrationOptions.odometry_iterations needs at least one level, each >= 1 iteration")


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
    o3d = load_open3d()
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


def _keyframe_clouds(color_i, depth_i, color_j, depth_j, intrinsics: Intrinsics, options: RegistrationOptions):
    """The Open3D clouds of keyframes i (target) and j (source) in their camera frames, as the checks read them."""
    kw = dict(pixel_stride=options.pixel_stride, min_depth_m=options.min_depth_m, max_depth_m=options.max_depth_m)
    return rgbd_point_cloud(color_i, depth_i, intrinsics, **kw), rgbd_point_cloud(color_j, depth_j, intrinsics, **kw)


def _too_few_points(source, target, T_ij_init: torch.Tensor, options: RegistrationOptions,
                    start: float) -> RegistrationResult | None:
    """The rejection of a pair whose clouds hold under ``options.min_points`` points, else None."""
    n = min(len(source.points), len(target.points))
    if n >= options.min_points:
        return None
    return _rejected(T_ij_init.to(torch.float64).cpu(), 0.0, math.inf, 0, 0.0, 0.0,
                     f"too few valid depth points ({n} < {options.min_points})", start)


def register_point_clouds(source, target, T_ij_init: torch.Tensor, options: RegistrationOptions = RegistrationOptions()) -> RegistrationResult:
    """Register Open3D clouds: source = keyframe j, target = keyframe i, both in their camera frames.

    T_ij_init: initial guess of T_i^-1 T_j  # [4, 4]
    ``options.method`` must be an ICP variant (dense alignment needs the images: :func:`register_rgbd_pair`).
    """
    if options.method in ("rgbd_odometry", "direct"):
        raise ValueError("register_point_clouds runs ICP; dense RGB-D alignment needs the images, use register_rgbd_pair")
    o3d = load_open3d()
    reg = o3d.pipelines.registration
    start = time.perf_counter()
    init = T_ij_init.detach().to(torch.float64).cpu().numpy()
    rejected = _too_few_points(source, target, T_ij_init, options, start)
    if rejected is not None:
        return rejected
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

    return _verify(src_down, tgt_down, T_ij_init, np.asarray(current), max_distance, options, start,
                   (float(result.fitness), float(result.inlier_rmse), len(result.correspondence_set)))


def _verify(source, target, T_ij_init: torch.Tensor, T_ij_np: np.ndarray, max_distance: float,
            options: RegistrationOptions, start: float, measured: tuple[float, float, int] | None = None) -> RegistrationResult:
    """Acceptance checks and information of a registered pair (clouds already down-sampled).

    measured: (fitness, inlier RMSE, correspondences) where the registration computed them; else
    Open3D's ``evaluate_registration`` at ``T_ij_np`` with ``max_distance``.
    """
    o3d = load_open3d()
    reg = o3d.pipelines.registration
    T_ij = torch.as_tensor(T_ij_np.copy(), dtype=torch.float64)
    if not bool(torch.isfinite(T_ij).all()):
        return _rejected(T_ij_init.detach().to(torch.float64).cpu(), 0.0, math.inf, 0, math.inf, math.inf,
                         "registration diverged (non-finite pose)", start)
    if measured is None:
        evaluation = reg.evaluate_registration(source, target, max_distance, T_ij_np)
        measured = (float(evaluation.fitness), float(evaluation.inlier_rmse), len(evaluation.correspondence_set))
    fitness, rmse, n = measured
    change = torch.linalg.inv(T_ij_init.detach().to(torch.float64).cpu()) @ T_ij
    correction_m = float(change[:3, 3].norm())
    correction_deg = float(torch.rad2deg(rotation_angle(change[:3, :3])))
    reasons = []
    if fitness < options.fitness_threshold:
        reasons.append(f"fitness {fitness:.3f} < {options.fitness_threshold}")
    if n == 0 or rmse > options.rmse_threshold:
        reasons.append(f"inlier RMSE {rmse:.4f} m > {options.rmse_threshold} m")
    if correction_m > options.max_correction_m or correction_deg > options.max_correction_deg:
        reasons.append(f"registration moved {correction_m:.3f} m / {correction_deg:.1f} deg from the initial guess")
    if reasons:
        return _rejected(T_ij, fitness, rmse, n, correction_m, correction_deg, "; ".join(reasons), start)

    info_o3d = np.asarray(reg.get_information_matrix_from_point_clouds(source, target, max_distance, T_ij_np))
    scale = min(1.0, options.max_independent_points / max(n, 1)) / options.point_sigma_m**2
    information = information_from_open3d(torch.as_tensor(info_o3d), T_ij) * scale
    return RegistrationResult(T_ij, information, fitness, rmse, n, correction_m, correction_deg, True, "",
                              time.perf_counter() - start)


def _open3d_rgbd(o3d, color: torch.Tensor, depth: torch.Tensor, options: RegistrationOptions):
    """Open3D RGBDImage (grey intensity in [0, 1], depth in metres) of one frame.  color [H, W, 3], depth [H, W]"""
    grey = (color.detach().to(torch.float32).cpu() @ torch.tensor(_GREY)).contiguous().numpy()
    z = depth.detach().to(torch.float32).cpu().contiguous().numpy()
    return o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(grey), o3d.geometry.Image(z), depth_scale=1.0, depth_trunc=options.max_depth_m,
        convert_rgb_to_intensity=False)


def register_rgbd_odometry(
    color_i: torch.Tensor,
    depth_i: torch.Tensor,
    color_j: torch.Tensor,
    depth_j: torch.Tensor,
    intrinsics: Intrinsics,
    T_ij_init: torch.Tensor,
    options: RegistrationOptions = RegistrationOptions(method="rgbd_odometry"),
) -> RegistrationResult:
    """Dense RGB-D alignment of keyframe j (source) to keyframe i (target), then the point-cloud checks.

    color_* [H, W, 3] in [0, 1], depth_* [H, W] metres, T_ij_init [4, 4] = current T_i^-1 T_j.
    Fitness and inlier RMSE are Open3D's ``evaluate_registration`` of the clouds (finest voxel,
    correspondence distance ``correspondence_factor`` x voxel) at the aligned pose.
    """
    o3d = load_open3d()
    start = time.perf_counter()
    target, source = _keyframe_clouds(color_i, depth_i, color_j, depth_j, intrinsics, options)
    rejected = _too_few_points(source, target, T_ij_init, options, start)
    if rejected is not None:
        return rejected
    camera = o3d.camera.PinholeCameraIntrinsic(intrinsics.width, intrinsics.height, intrinsics.fx, intrinsics.fy,
                                               intrinsics.cx, intrinsics.cy)
    odometry = o3d.pipelines.odometry
    option = odometry.OdometryOption(
        iteration_number_per_pyramid_level=o3d.utility.IntVector(list(options.odometry_iterations)),
        depth_diff_max=options.odometry_depth_difference_m, depth_min=options.min_depth_m, depth_max=options.max_depth_m)
    init = T_ij_init.detach().to(torch.float64).cpu().numpy()
    success, T_ij_np, _ = odometry.compute_rgbd_odometry(
        _open3d_rgbd(o3d, color_j, depth_j, options), _open3d_rgbd(o3d, color_i, depth_i, options), camera, init,
        odometry.RGBDOdometryJacobianFromHybridTerm(), option)
    if not success:
        return _rejected(T_ij_init.detach().to(torch.float64).cpu(), 0.0, math.inf, 0, 0.0, 0.0,
                         "dense RGB-D alignment failed (too few correspondences)", start)
    voxel = options.voxel_sizes[-1]
    return _verify(source.voxel_down_sample(voxel), target.voxel_down_sample(voxel), T_ij_init, np.asarray(T_ij_np),
                   options.correspondence_factor * voxel, options, start)


def _direct_pyramids(color_i: torch.Tensor, depth_i: torch.Tensor, color_j: torch.Tensor, depth_j: torch.Tensor,
                     intrinsics: Intrinsics, options: RegistrationOptions
                     ) -> tuple[list[DirectReference], list[DirectTarget]]:
    """Keyframe j as reference points and keyframe i as the target image, coarse to fine, the finest level at
    ``options.direct_scale`` (at least ``direct_min_width`` pixels wide); depth outside [min_depth_m, max_depth_m]
    is left out of both."""
    def in_range(depth: torch.Tensor) -> torch.Tensor:
        return (depth > options.min_depth_m) & (depth < options.max_depth_m)

    finest = max(options.direct_scale, min(1.0, options.direct_min_width / intrinsics.width))
    references, targets = [], []
    for scale in pyramid_scales(options.direct_levels):
        scale = scale * finest
        level = []
        for color, depth in ((color_j, depth_j), (color_i, depth_i)):
            color, depth = color.detach().float().cpu(), depth.detach().float().cpu()
            depth = torch.where(in_range(depth), depth, 0.0)
            if scale < 1.0:
                color, depth = resize_area(color, scale), resize_area(depth, scale, valid=depth > 0)
            level.append((color, depth))
        (color_r, depth_r), (color_t, depth_t) = level
        K = intrinsics.scaled(scale).matrix(dtype=torch.float32)
        references.append(direct_reference(color_r, depth_r, depth_r > 0, K))
        targets.append(direct_target(color_t, depth_t, K))
    return references, targets


def register_rgbd_direct(
    color_i: torch.Tensor,
    depth_i: torch.Tensor,
    color_j: torch.Tensor,
    depth_j: torch.Tensor,
    intrinsics: Intrinsics,
    T_ij_init: torch.Tensor,
    options: RegistrationOptions = RegistrationOptions(method="direct"),
) -> RegistrationResult:
    """Direct RGB-D alignment of keyframe j (source) onto keyframe i (target) by Gauss-Newton
    (:func:`mipslam.geometry.direct.align_direct`, compiled where available), then the point-cloud checks; an
    alignment that fails or moves the estimate beyond ``options.direct_trust_m`` / ``direct_trust_deg`` is
    redone by :func:`register_rgbd_odometry` (a wider basin).

    color_* [H, W, 3] in [0, 1], depth_* [H, W] metres, T_ij_init [4, 4] = current T_i^-1 T_j. Fitness and
    inlier RMSE as :func:`register_rgbd_odometry` measures them.
    """
    from mipslam.render import direct_aligner  # the renderer's package owns the compiled library

    start = time.perf_counter()
    target, source = _keyframe_clouds(color_i, depth_i, color_j, depth_j, intrinsics, options)
    rejected = _too_few_points(source, target, T_ij_init, options, start)
    if rejected is not None:
        return rejected
    references, targets = _direct_pyramids(color_i, depth_i, color_j, depth_j, intrinsics, options)
    align = direct_aligner("auto", torch.device("cpu"))
    aligned = align(references, targets, T_ij_init.detach().to(torch.float64).cpu(),
                    iterations=options.direct_iterations, alpha_color=options.direct_alpha_color,
                    depth_noise_power=options.direct_depth_noise_power)
    change = torch.linalg.inv(T_ij_init.detach().to(torch.float64).cpu()) @ aligned.T
    if (not aligned.ok or float(change[:3, 3].norm()) > options.direct_trust_m
            or math.degrees(float(rotation_angle(change[:3, :3]))) > options.direct_trust_deg):
        return register_rgbd_odometry(color_i, depth_i, color_j, depth_j, intrinsics, T_ij_init, options)
    voxel = options.voxel_sizes[-1]
    return _verify(source.voxel_down_sample(voxel), target.voxel_down_sample(voxel), T_ij_init,
                   aligned.T.numpy(), options.correspondence_factor * voxel, options, start)


def register_rgbd_pair(
    color_i: torch.Tensor,
    depth_i: torch.Tensor,
    color_j: torch.Tensor,
    depth_j: torch.Tensor,
    intrinsics: Intrinsics,
    T_ij_init: torch.Tensor,
    options: RegistrationOptions = RegistrationOptions(),
) -> RegistrationResult:
    """Verify a loop between keyframes i (target) and j (source): ICP on their RGB-D clouds, or
    dense RGB-D alignment (Open3D's or tracking's Gauss-Newton; ``options.method``), then the acceptance checks.

    color_* [H, W, 3] in [0, 1], depth_* [H, W] metres, T_ij_init [4, 4] = current T_i^-1 T_j.
    """
    if options.method == "rgbd_odometry":
        result = register_rgbd_odometry(color_i, depth_i, color_j, depth_j, intrinsics, T_ij_init, options)
    elif options.method == "direct":
        result = register_rgbd_direct(color_i, depth_i, color_j, depth_j, intrinsics, T_ij_init, options)
    else:
        target, source = _keyframe_clouds(color_i, depth_i, color_j, depth_j, intrinsics, options)
        result = register_point_clouds(source, target, T_ij_init, options)
    logger.debug("loop verification: fitness %.3f, rmse %.4f m, accepted=%s %s", result.fitness,
                 result.inlier_rmse_m, result.accepted, result.reason)
    return result
