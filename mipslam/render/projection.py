"""EWA projection of 3D Gaussians to the image (Zwicker et al. 2002; Kerbl et al. 2023).

``Sigma2D = J W Sigma3D W^T J^T`` with ``Sigma3D = R S S R^T`` (R from the wxyz quaternion, S the
scales as standard deviations in metres), W the rotation of ``viewmat = T_cw`` and J the Jacobian of
the pinhole projection at the Gaussian's camera-frame centre. The 2D covariance is assembled from
``M = J W R S`` (2x3) as ``M M^T``, and its determinant by Cauchy-Binet as the sum of the squared
2x2 minors of M, which is never negative and keeps full relative precision for thin splats.

Robustness (numerical extremes): Gaussians with a non-finite entry in any input, a zero
quaternion, a centre at or behind the near plane or beyond the far plane, a direction far outside the
view (|x/z| > 1e6) or a projected size above 1e9 px are dropped (``visible = False``, opacity 0) and
their values replaced before any arithmetic, so neither images nor gradients see NaN or Inf. As in
gsplat, the Jacobian is evaluated at the centre direction clamped to 1.3x the field of view, so
splats far outside the image do not explode. The covariance gets a floor of ``COV_FLOOR`` px^2.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from mipslam.geometry.camera import sampling_rate
from mipslam.geometry.se3 import quat_wxyz_to_rotmat

#: Added to both diagonal entries of every 2D covariance (px^2): sigma >= 1e-4 px, so conics stay finite.
COV_FLOOR = 1e-8
#: Fraction of the half field of view by which the Jacobian's direction may leave the image (gsplat: 0.3).
FOV_MARGIN = 0.3
#: Gaussians projected larger than this (sigma in px) are dropped: beyond it det Sigma2D overflows float32.
MAX_SIGMA_PX = 1e9
#: Gaussians whose direction |x/z| or |y/z| exceeds this are dropped (never on screen, would overflow).
MAX_TANGENT = 1e6


@dataclass(frozen=True)
class ProjectedGaussians:
    """Image-space Gaussians (all [N, ...], aligned with the input order).

    means2d  [N, 2] px       centre in the image (pixel centres at integers)
    depths   [N]    metres   camera-frame z of the centre
    cov2d    [N, 3] px^2     (xx, xy, yy) of Sigma2D (with the 3D filter if on, floor included)
    cov_det  [N]    px^4     det Sigma2D
    opacities[N]             in [0, 1], times the 3D filter's factor, 0 where not visible
    colors   [N, 3]          input colours with dropped rows zeroed
    visible  [N]    bool     finite, in front of the near plane, overlapping the image
    """

    means2d: torch.Tensor
    depths: torch.Tensor
    cov2d: torch.Tensor
    cov_det: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    visible: torch.Tensor


def finite_rows(*tensors: torch.Tensor) -> torch.Tensor:
    """True for rows finite in every tensor.  each [N, ...] -> [N] bool"""
    ok = None
    for t in tensors:
        row = torch.isfinite(t.reshape(t.shape[0], int(math.prod(t.shape[1:])))).all(-1)
        ok = row if ok is None else ok & row
    return ok


def _replace_rows(x: torch.Tensor, keep: torch.Tensor, value: float) -> torch.Tensor:
    """Rows where ``keep`` is False replaced by ``value`` (gradient 0 there).  [N, ...] -> [N, ...]"""
    shape = (-1,) + (1,) * (x.dim() - 1)
    return torch.where(keep.view(shape), x, torch.full_like(x, value))


def filter_3d_variance(depths: torch.Tensor, K: torch.Tensor, filter_scale: float,
                       max_sampling_rate: torch.Tensor | None) -> torch.Tensor:
    """Mip-Splatting 3D smoothing variance (m^2) per Gaussian: ``s / nu^2``.

    nu is the Gaussian's maximal sampling rate (pixels per metre, ``focal / depth`` for the camera
    that sees it largest); when not given it is computed from this camera: ``max(fx, fy) / z``.
    depths [N] metres, K [3, 3], max_sampling_rate [N] or None -> [N] m^2.
    """
    if max_sampling_rate is None:
        max_sampling_rate = sampling_rate(K, depths)
    return filter_scale / (max_sampling_rate * max_sampling_rate)


def project_gaussians(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                      colors: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, *,
                      near_plane: float = 0.01, far_plane: float = 1e10, extent_sigma: float = 3.0,
                      extent_pad: float = 0.0, extent_dilation: float = 0.0,
                      filter_3d_scale: float | None = None,
                      max_sampling_rate: torch.Tensor | None = None) -> ProjectedGaussians:
    """Project Gaussians with the EWA linearisation.

    means [N, 3] world metres, quats [N, 4] wxyz (any norm), scales [N, 3] std-devs in metres,
    opacities [N] in [0, 1], colors [N, C], viewmat [4, 4] world-to-camera (T_cw), K [3, 3].
    ``extent_sigma``, ``extent_dilation`` (px^2) and ``extent_pad`` (px) give the box of the on-screen
    test: ``k * sqrt(diag Sigma + dilation) + pad`` around the centre (the footprint mode's support). ``filter_3d_scale`` (e.g. 0.2) turns on the
    Mip-Splatting 3D filter: ``Sigma3D + (s / nu^2) I`` and opacity times
    ``sqrt(det Sigma3D / det(Sigma3D + (s / nu^2) I))``.
    """
    dtype = means.dtype
    keep = finite_rows(means, quats, scales, opacities.reshape(-1, 1), colors)
    quat_norm = quats.norm(dim=-1)
    keep = keep & (quat_norm > 0) & torch.isfinite(quat_norm)
    means = _replace_rows(means, keep, 0.0)
    quats = _replace_rows(quats, keep, 1.0)
    scales = _replace_rows(scales, keep, 1.0)
    opacities = _replace_rows(opacities, keep, 0.0).clamp(0.0, 1.0)
    colors = _replace_rows(colors, keep, 0.0)

    W = viewmat[:3, :3]
    means_c = means @ W.T + viewmat[:3, 3]  # [N, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # Rows the arithmetic below can take without overflow: in front of the near plane, before the
    # far plane, not absurdly off-axis, projected sigma below MAX_SIGMA_PX. The others are replaced by
    # a harmless row *before* any division or product, so not even their zero gradients meet an Inf.
    with torch.no_grad():
        z_raw = means_c[:, 2]
        z_pos = z_raw.clamp_min(near_plane)
        sigma_px_bound = scales.abs().amax(-1) * torch.maximum(fx, fy).abs() / z_pos
        in_range = (z_raw > near_plane) & (z_raw < far_plane) & torch.isfinite(means_c).all(-1) \
            & (means_c[:, 0].abs() < MAX_TANGENT * z_pos) & (means_c[:, 1].abs() < MAX_TANGENT * z_pos) \
            & (sigma_px_bound < MAX_SIGMA_PX)
        keep = keep & in_range
    means_c = torch.where(keep[:, None], means_c, torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=means.device))
    scales = _replace_rows(scales, keep, 1.0)
    z = means_c[:, 2]
    u = fx * means_c[:, 0] / z + cx
    v = fy * means_c[:, 1] / z + cy
    means2d = torch.stack([u, v], -1)

    # Jacobian of (fx x/z + cx, fy y/z + cy) at the centre direction clamped to the widened view.
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + FOV_MARGIN * tan_x, cx / fx + FOV_MARGIN * tan_x
    lim_y_pos, lim_y_neg = (height - cy) / fy + FOV_MARGIN * tan_y, cy / fy + FOV_MARGIN * tan_y
    tx = torch.minimum(torch.maximum(means_c[:, 0] / z, -lim_x_neg), lim_x_pos)
    ty = torch.minimum(torch.maximum(means_c[:, 1] / z, -lim_y_neg), lim_y_pos)
    zero = torch.zeros_like(z)
    J = torch.stack([torch.stack([fx / z, zero, -fx * tx / z], -1),
                     torch.stack([zero, fy / z, -fy * ty / z], -1)], -2)  # [N, 2, 3]

    std3d = scales  # [N, 3]; the sign of a scale does not matter (Sigma = M M^T)
    if filter_3d_scale:
        var3d = filter_3d_variance(z, K, filter_3d_scale, max_sampling_rate)  # [N]
        scales_sq = scales * scales
        filtered_sq = scales_sq + var3d[:, None]
        opacities = opacities * torch.sqrt(torch.prod(scales_sq / filtered_sq, dim=-1))
        std3d = torch.sqrt(filtered_sq)
    R = quat_wxyz_to_rotmat(quats)  # [N, 3, 3]
    M = (J @ W) @ (R * std3d[:, None, :])  # [N, 2, 3] = J W R S
    cov = M @ M.transpose(1, 2)  # [N, 2, 2]
    # det by Cauchy-Binet on M / c (c = the largest |entry|, no gradient), so no product overflows.
    c = M.detach().abs().amax(dim=(1, 2)).clamp_min(torch.finfo(dtype).tiny)  # [N]
    Mn = M / c[:, None, None]
    minors = torch.stack([Mn[:, 0, 0] * Mn[:, 1, 1] - Mn[:, 0, 1] * Mn[:, 1, 0],
                          Mn[:, 0, 0] * Mn[:, 1, 2] - Mn[:, 0, 2] * Mn[:, 1, 0],
                          Mn[:, 0, 1] * Mn[:, 1, 2] - Mn[:, 0, 2] * Mn[:, 1, 1]], -1)
    cov_xx = cov[:, 0, 0] + COV_FLOOR
    cov_yy = cov[:, 1, 1] + COV_FLOOR
    cov_xy = cov[:, 0, 1]
    cov_det = (c * c) * (c * c) * (minors * minors).sum(-1) + COV_FLOOR * (cov[:, 0, 0] + cov[:, 1, 1]) \
        + COV_FLOOR * COV_FLOOR

    finite2d = torch.isfinite(means2d).all(-1) & torch.isfinite(cov_xx) & torch.isfinite(cov_yy) \
        & torch.isfinite(cov_xy) & torch.isfinite(cov_det)
    ext_x = extent_sigma * torch.sqrt(cov_xx + extent_dilation) + extent_pad
    ext_y = extent_sigma * torch.sqrt(cov_yy + extent_dilation) + extent_pad
    on_screen = (u + ext_x > -0.5) & (u - ext_x < width - 0.5) & (v + ext_y > -0.5) & (v - ext_y < height - 0.5)
    visible = keep & finite2d & on_screen & (opacities > 0)

    # Dropped rows get harmless finite values so later arithmetic (and its gradient) stays finite.
    means2d = _replace_rows(means2d, visible, -1e6)
    cov_xx = _replace_rows(cov_xx, visible, 1.0)
    cov_yy = _replace_rows(cov_yy, visible, 1.0)
    cov_xy = _replace_rows(cov_xy, visible, 0.0)
    cov_det = _replace_rows(cov_det, visible, 1.0)
    opacities = _replace_rows(opacities, visible, 0.0)
    depths = _replace_rows(z, visible, 0.0)
    return ProjectedGaussians(
        means2d=means2d, depths=depths, cov2d=torch.stack([cov_xx, cov_xy, cov_yy], -1).to(dtype),
        cov_det=cov_det, opacities=opacities, colors=colors, visible=visible)
