"""Direct RGB-D alignment: the rigid motion that carries a reference view (points with intensity) onto a
target RGB-D image, by Gauss-Newton on photometric and depth residuals (pure functions on tensors).

The objective is dense visual odometry's (Kerl, Sturm & Cremers, "Robust Odometry Estimation for RGB-D
Cameras", ICRA 2013) with a depth term as in their "Dense Visual SLAM for RGB-D Cameras" (IROS 2013): for
each reference point ``X`` (camera frame of the reference, metres) with intensity ``I_r`` and the motion
``T`` (target camera from reference camera), ``X' = T X`` and ``u' = pi(X')``:

    r_c = I_t(u') - I_r - b      (intensity in [0, 1]; b: the median of I_t(u') - I_r over the points)
    r_d = (D_t(u') - z(X')) / z(X')^p   (metres for p = 0; ``depth_noise_power`` p = 2 puts it in units of
                                 an active depth sensor's noise, which grows as z^2: Khoshelham & Elberink 2012)

minimised as ``alpha / N_c * sum w_c (r_c / s_c)^2 + (1 - alpha) / N_d * sum w_d (r_d / s_d)^2``, where
``s`` is each term's robust scale (1.4826 x the median absolute residual) and ``w`` Huber's weight at
``HUBER_K`` scales (iteratively reweighted least squares). The increment is a left one in the target
camera, ``T <- exp(delta) T`` with ``delta = [rho, phi]`` as :func:`~mipslam.geometry.se3.se3_exp`; the
Jacobian of a residual ``r(X')`` is ``[g, X' x g]`` for its gradient ``g = dr/dX'``. Coarse to fine over
image pyramids, each step accepted only when it lowers the cost at the current weights (halved up to
``MAX_HALVINGS`` times otherwise). The offset ``b`` absorbs a change of brightness between the views (auto
exposure); it is re-estimated at every evaluation and treated as a constant in the Jacobian.

Pixel centres have integer coordinates (docs/design.md); images are sampled bilinearly at ``u'``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from mipslam.geometry.se3 import se3_exp

HUBER_K = 1.345  # Huber's constant for 95 % efficiency on Gaussian residuals
MAD_TO_SIGMA = 1.4826  # median absolute deviation -> standard deviation of a normal distribution
MAX_HALVINGS = 3  # step halvings before a level gives up on a step that raises the cost
MIN_SCALE_INTENSITY = 1e-3  # floors of the robust scales: a perfect fit must not divide by zero
MIN_SCALE_DEPTH = 1e-4  # metres
DEPTH_EDGE_RATIO = 0.05  # a depth gradient across a jump above this fraction of the depth is not used
MIN_POINTS = 64  # fewer usable residuals than this and a level is skipped


@dataclass(frozen=True)
class DirectTarget:
    """One pyramid level of the image to align to.

    channels: [1, 7, h, w] float32: intensity, its u and v derivatives, depth (0 = none), its u and v
              derivatives, and 1 where the depth and its derivatives are usable (0 across holes and jumps)
    K:        [3, 3] float32 intrinsics of this level (pixels)
    """

    channels: torch.Tensor
    K: torch.Tensor

    @property
    def height(self) -> int:
        return self.channels.shape[2]

    @property
    def width(self) -> int:
        return self.channels.shape[3]


@dataclass(frozen=True)
class DirectReference:
    """The view to move: points with intensity at one pyramid level.

    points:    [N, 3] float32 camera-frame points of the reference (metres)
    intensity: [N] float32 in [0, 1]
    """

    points: torch.Tensor
    intensity: torch.Tensor


@dataclass(frozen=True)
class DirectResult:
    """Outcome of :func:`align_direct`.

    T:          [4, 4] float64 target camera from reference camera
    iterations: Gauss-Newton steps taken over all levels
    points:     residuals (colour and depth) used at the last step of the finest level that ran
    ok:         False when no level had enough usable residuals (``T`` is then the initial motion)
    """

    T: torch.Tensor
    iterations: int
    points: int
    ok: bool


def intensity(color: torch.Tensor) -> torch.Tensor:
    """Grey level of an RGB image: the channel mean.  color [..., 3] -> [...]"""
    return color.mean(-1)


def _central_difference(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(d/du, d/dv) of image [h, w] by central differences; 0 on the border rows and columns."""
    du = torch.zeros_like(image)
    dv = torch.zeros_like(image)
    du[:, 1:-1] = 0.5 * (image[:, 2:] - image[:, :-2])
    dv[1:-1, :] = 0.5 * (image[2:, :] - image[:-2, :])
    return du, dv


def direct_target(
    color: torch.Tensor,  # [h, w, 3] in [0, 1]
    depth: torch.Tensor,  # [h, w] metres, 0 = no measurement
    K: torch.Tensor,  # [3, 3] intrinsics of this image (pixels)
) -> DirectTarget:
    """The target level of :func:`align_direct`: intensity, depth and their derivatives in one tensor.

    A pixel's depth counts as usable where it and its four neighbours are measured and the central
    differences do not cross a jump larger than ``DEPTH_EDGE_RATIO`` of its depth (a bilinear sample there
    would blend two surfaces).
    """
    gray = intensity(color).float()
    depth = depth.float()
    gu, gv = _central_difference(gray)
    du, dv = _central_difference(depth)
    valid = depth > 0
    usable = torch.zeros_like(valid)
    inner = valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    usable[1:-1, 1:-1] = inner
    jump = torch.maximum(du.abs(), dv.abs()) * 2.0 > DEPTH_EDGE_RATIO * depth
    usable &= ~jump
    channels = torch.stack([gray, gu, gv, depth, du, dv, usable.float()])[None]  # [1, 7, h, w]
    return DirectTarget(channels=channels.contiguous(), K=K.float())


def direct_reference(
    color: torch.Tensor,  # [h, w, 3] in [0, 1]
    depth: torch.Tensor,  # [h, w] metres
    mask: torch.Tensor,  # [h, w] bool: pixels whose colour and depth the reference vouches for
    K: torch.Tensor,  # [3, 3] intrinsics (pixels)
) -> DirectReference:
    """The reference points of :func:`align_direct`: the masked pixels with positive depth, back-projected."""
    keep = mask & (depth > 0)
    v, u = torch.nonzero(keep, as_tuple=True)
    z = depth[v, u].float()
    K = K.float()
    x = (u.float() - K[0, 2]) / K[0, 0] * z
    y = (v.float() - K[1, 2]) / K[1, 1] * z
    return DirectReference(points=torch.stack([x, y, z], -1), intensity=intensity(color[v, u]).float())


@dataclass(frozen=True)
class _Residuals:
    """Both terms at every reference point; points outside a term carry weight 0 (no boolean indexing:
    it costs more than the arithmetic at these sizes)."""

    points: torch.Tensor  # [3, N] X'
    color: torch.Tensor  # [N] r_c
    color_grad: torch.Tensor  # [3, N] d r_c / d X'
    color_mask: torch.Tensor  # [N] bool
    depth: torch.Tensor  # [N] r_d
    depth_grad: torch.Tensor  # [3, N]
    depth_mask: torch.Tensor  # [N] bool

    @property
    def count(self) -> int:
        return int(self.color_mask.sum()) + int(self.depth_mask.sum())


def _residuals(reference: DirectReference, target: DirectTarget, T: torch.Tensor,
               depth_noise_power: float = 0.0) -> _Residuals:
    """Residuals of both terms at motion T [4, 4] (float32 math), with their gradients in X'. With
    ``depth_noise_power`` p > 0 the depth residual and its gradient are divided by ``z(X')^p`` (a depth
    sensor's noise grows with distance; the weight is held fixed in the Jacobian, as Huber's)."""
    T = T.to(device=reference.points.device, dtype=torch.float32)
    R, t = T[:3, :3], T[:3, 3]
    X = torch.addmm(t[:, None], R, reference.points.T)  # [3, N]
    x, y, z = X[0], X[1], X[2]
    front = z > 1e-3
    inv_z = 1.0 / torch.where(front, z, torch.ones_like(z))
    K = target.K
    fx, fy = float(K[0, 0]), float(K[1, 1])
    xz, yz = x * inv_z, y * inv_z
    u = fx * xz + float(K[0, 2])
    v = fy * yz + float(K[1, 2])
    w, h = target.width, target.height
    inside = front & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    # grid_sample with align_corners=True maps -1 / +1 onto the centres of the first / last pixel
    grid = torch.stack([u * (2.0 / max(w - 1, 1)) - 1.0, v * (2.0 / max(h - 1, 1)) - 1.0], -1)
    s = F.grid_sample(target.channels, grid[None, None], mode="bilinear", padding_mode="border",
                      align_corners=True)[0, :, 0]  # [7, N]
    gray, gu, gv, depth, du, dv, usable = s
    fx_z, fy_z = fx * inv_z, fy * inv_z

    def through_projection(a_u: torch.Tensor, a_v: torch.Tensor, dz: float) -> torch.Tensor:  # -> [3, N]
        # d pi / d X' rows: (fx / z, 0, -fx x / z^2) and (0, fy / z, -fy y / z^2)
        pu, pv = a_u * fx_z, a_v * fy_z
        return torch.stack([pu, pv, dz - (pu * xz + pv * yz)])

    color = gray - reference.intensity
    kept = color[inside]
    if kept.numel():  # a brightness offset between the views (auto exposure) is not motion
        color = color - kept.median()
    depth_residual, depth_grad = depth - z, through_projection(du, dv, -1.0)
    if depth_noise_power > 0:
        noise = inv_z * inv_z if depth_noise_power == 2 else inv_z.pow(depth_noise_power)  # [N] 1 / z^p
        depth_residual, depth_grad = depth_residual * noise, depth_grad * noise
    return _Residuals(
        points=X,
        color=color, color_grad=through_projection(gu, gv, 0.0), color_mask=inside,
        depth=depth_residual, depth_grad=depth_grad, depth_mask=inside & (usable > 0.999),
    )


def _terms(res: _Residuals, alpha_color: float):
    """(residuals, gradients, mask, weight) of the two terms."""
    return ((res.color, res.color_grad, res.color_mask, alpha_color),
            (res.depth, res.depth_grad, res.depth_mask, 1.0 - alpha_color))


def _robust_scales(res: _Residuals) -> tuple[float, float]:
    """MAD_TO_SIGMA x the median absolute residual of each term, floored."""
    scales = []
    for r, mask, floor in ((res.color, res.color_mask, MIN_SCALE_INTENSITY), (res.depth, res.depth_mask, MIN_SCALE_DEPTH)):
        kept = r[mask]
        scales.append(max(MAD_TO_SIGMA * float(kept.abs().median()), floor) if kept.numel() else floor)
    return scales[0], scales[1]


def _huber_weights(a: torch.Tensor) -> torch.Tensor:
    """Huber's IRLS weight of scaled residual magnitudes a [N]."""
    return torch.where(a <= HUBER_K, torch.ones_like(a), HUBER_K / a.clamp_min(1e-12))


def _cost(res: _Residuals, scales: tuple[float, float], alpha_color: float) -> float:
    """The weighted objective at fixed robust scales (Huber's rho, averaged over each term's points)."""
    total = 0.0
    for (r, _, mask, weight), scale in zip(_terms(res, alpha_color), scales):
        n = int(mask.sum())
        if weight <= 0 or n == 0:
            continue
        a = (r / scale).abs()
        rho = torch.where(a <= HUBER_K, 0.5 * a * a, HUBER_K * (a - 0.5 * HUBER_K))
        total += weight * float((rho * mask).sum()) / n
    return total


def _normal_equations(res: _Residuals, scales: tuple[float, float], alpha_color: float):
    """H [6, 6] and b [6] (float64) of the IRLS step at fixed scales: delta = -H^-1 b."""
    H = torch.zeros(6, 6, dtype=torch.float64)
    b = torch.zeros(6, dtype=torch.float64)
    for (r, g, mask, weight), scale in zip(_terms(res, alpha_color), scales):
        n = int(mask.sum())
        if weight <= 0 or n == 0:
            continue
        J = torch.cat([g, torch.linalg.cross(res.points, g, dim=0)])  # [6, N]
        w = _huber_weights((r / scale).abs()) * mask * (weight / (scale * scale * n))  # [N]
        Jw = J * w
        H += (Jw @ J.T).double().cpu()
        b += (Jw @ r).double().cpu()
    return H, b


def align_direct(
    references: list[DirectReference],  # coarse to fine, one per pyramid level
    targets: list[DirectTarget],  # the same levels of the target
    T_init: torch.Tensor,  # [4, 4] float64 target camera from reference camera
    *,
    iterations: int,  # Gauss-Newton steps per level at most
    alpha_color: float,  # weight of the intensity term against depth, in [0, 1]
    convergence: float = 1e-5,  # a level stops once a step's se(3) norm falls below this
    depth_noise_power: float = 0.0,  # depth residuals in units of z^p (0: metres; see _residuals)
) -> DirectResult:
    """Align the reference points onto the target image (module docstring): the motion [4, 4] float64."""
    if len(references) != len(targets):
        raise ValueError(f"align_direct: {len(references)} reference levels against {len(targets)} target levels")
    T = T_init.to(torch.float64).cpu().clone()
    steps, points, ran = 0, 0, False
    for reference, target in zip(references, targets):
        if reference.points.shape[0] < MIN_POINTS:
            continue
        res = _residuals(reference, target, T, depth_noise_power)
        for _ in range(iterations):
            if res.count < MIN_POINTS:
                break
            scales = _robust_scales(res)
            H, b = _normal_equations(res, scales, alpha_color)
            H = H + 1e-9 * torch.eye(6, dtype=torch.float64) * float(H.diagonal().abs().max().clamp_min(1e-12))
            delta = -torch.linalg.solve(H, b)
            if not bool(torch.isfinite(delta).all()):
                break
            ran, points = True, res.count
            before = _cost(res, scales, alpha_color)
            accepted = None
            for _ in range(MAX_HALVINGS + 1):
                candidate = se3_exp(delta) @ T
                after = _residuals(reference, target, candidate, depth_noise_power)
                if after.count >= MIN_POINTS and _cost(after, scales, alpha_color) < before:
                    accepted = after
                    break
                delta = 0.5 * delta
            steps += 1
            if accepted is None:
                break
            T, res = candidate, accepted
            if float(delta.norm()) < convergence:
                break
    return DirectResult(T=T, iterations=steps, points=points, ok=ran and bool(torch.isfinite(T).all()))


def intensity_scale(reference: DirectReference, target: DirectTarget, T: torch.Tensor) -> tuple[float, int]:
    """The intensity term's robust scale (MAD_TO_SIGMA x the median absolute residual, the brightness offset
    removed) at motion T [4, 4] float64, and the points it was measured on: how well the views' intensities
    agree once aligned (a loop check: surfaces of equal shape and different texture align in depth alone).
    An intensity in [0, 1]; inf where no point lands in the target."""
    res = _residuals(reference, target, T.to(torch.float64).cpu())
    kept = res.color[res.color_mask]
    if kept.numel() == 0:
        return math.inf, 0
    return MAD_TO_SIGMA * float(kept.abs().median()), int(kept.numel())


def pyramid_scales(levels: int) -> list[float]:
    """Scales of ``levels`` pyramid levels, coarse to fine, each half the next: 3 -> [0.25, 0.5, 1.0]."""
    if levels < 1:
        raise ValueError(f"pyramid_scales: levels must be >= 1, got {levels}")
    return [math.pow(0.5, levels - 1 - i) for i in range(levels)]
