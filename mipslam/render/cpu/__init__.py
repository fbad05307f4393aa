"""The compiled CPU backend of the renderer: C++/OpenMP tile rasterizer with a SIMD forward and a
hand-written backward, and a fused projection (docs/renderer_cpu.md).

Split as in gsplat: the fused projection (projection.h, checked against
:func:`mipslam.render.projection.project_gaussians` + :func:`mipslam.render.footprint.mode_footprint`) turns
the 3D Gaussians into, per Gaussian,

    means2d [N, 2] px, cov [N, 4] = (xx, xy, yy, det) px^2 / px^4 (the mode's sampling covariance),
    opacity [N] (the mode's), depth [N] metres, node_counts [N] int32 (EAA)

and the rasterizer does the per-pixel part: tile binning, depth sort, footprint evaluation (point/mip/ewa as
a centre sample, EAA with its rows, exact Gauss-Legendre) and front-to-back compositing, forward and
backward. Modules, one job each:

    build.py     compiles raster_ext.cpp into plain shared libraries at install time (no torch needed)
    library.py   finds, checks and loads the built library (ctypes), calls it with tensors; kernel timing
    autograd.py  the torch.autograd.Functions around the library's forward and backward
    backend.py   the entry points (rasterize, rasterize_projected, project_footprints, ...)
    direct_align.h  tracking's direct RGB-D alignment (align_direct), the twin of mipslam.geometry.direct's
    feature_match.h the feature front-end's guided matching, the twin of mipslam.frontend's k-d tree gate
    rgbd_loss.h     tracking's masked RGB-D L1 loss and its gradients, the twin of
                    mipslam.losses.photometric.rgbd_l1_loss_and_gradients
    ssim_loss.h     mapping's SSIM loss term and its analytic gradient, the twin of mipslam.losses.structural.ssim
                    (mipslam.losses.structural.ssim_loss calls it)

Nothing here compiles: a missing or stale build logs one warning, :func:`is_available` is False,
``backend="auto"`` uses the torch backend and ``backend="cpu"`` raises
:class:`~mipslam.errors.BackendUnavailableError` with the reason (:func:`unavailable_reason`).
"""
from __future__ import annotations

from mipslam.render.cpu.autograd import ProjectFootprints, RasterizeProjected
from mipslam.render.cpu.backend import (MAX_ROWS, MODE_IDS, SUPPORTED_CHANNELS, CpuImage, FootprintProjection,
                                        PoseOnlyRender, align_direct, pose_only_unsupported_reason,
                                        project_footprints, rasterize, rasterize_pose_only, rasterize_projected, rasterize_unfused,
                                        reference_footprints, rgbd_l1_loss_and_gradients, unsupported_reason)
from mipslam.render.cpu.library import (KernelTimes, Library, is_available, load_extension, profile_kernels,
                                        unavailable_reason, warm_up)

__all__ = ["is_available", "unavailable_reason", "unsupported_reason", "load_extension", "warm_up", "rasterize",
           "rasterize_unfused", "rasterize_projected", "RasterizeProjected", "ProjectFootprints",
           "project_footprints", "reference_footprints", "FootprintProjection", "CpuImage", "profile_kernels",
           "KernelTimes", "Library", "MODE_IDS", "SUPPORTED_CHANNELS", "MAX_ROWS", "align_direct",
           "rasterize_pose_only", "pose_only_unsupported_reason", "PoseOnlyRender", "rgbd_l1_loss_and_gradients"]
