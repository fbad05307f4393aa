"""SO(3)/SE(3) on batched tensors: exp, log, compose, invert, quaternion conversions.

Every function works on any leading batch shape ``[...]``, on any device and dtype, and is
differentiable (small-angle branches use Taylor expansions, so gradients stay finite at 0).

Conventions (docs/design.md): a twist is ``xi = [rho, phi]`` (translation part first, then the
rotation vector), ``T = exp(xi)`` is a 4x4 homogeneous matrix. Quaternions are ``wxyz`` here;
files use TUM order ``xyzw`` and convert at the boundary with :func:`quat_xyzw_to_wxyz`.
References: Barfoot, "State Estimation for Robotics" (2017), sections 7.1-7.2; Sola et al.,
"A micro Lie theory for state estimation in robotics" (2018).
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np
import torch
import torch.autograd.forward_ad  # noqa: F401  (torch.autograd.forward_ad._current_level)

# Below this squared angle the closed forms of B = (1 - cos t)/t^2, C = (t - sin t)/t^3 and
# D = (1 - A/(2B))/t^2 lose digits to cancellation, so their Taylor series take over. The series
# are kept to the t^4 term: at the switch the truncation error (~t^6 / 4e4) is below the dtype's
# epsilon, and above it the cancellation error (~eps / t^2) is small (4e-12 for float64 at t = 0.01).
_SERIES_ANGLE_SQ = {torch.float64: 1e-4, torch.float32: 1e-2, torch.float16: 1e-1, torch.bfloat16: 1e-1}
# so3_log's atan2(n, w) / n has no cancellation; its series is needed only to avoid 0 / 0.
_TINY_SIN_SQ = {torch.float64: 1e-10, torch.float32: 1e-5, torch.float16: 1e-3, torch.bfloat16: 1e-3}


def _small(dtype: torch.dtype) -> float:
    return _SERIES_ANGLE_SQ.get(dtype, 1e-2)


def hat(phi: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix of a 3-vector.  phi [..., 3] -> [..., 3, 3]"""
    x, y, z = phi.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack(
        [torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1), torch.stack([-y, x, zero], -1)], -2
    )


def vee(omega: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`hat` (antisymmetric part).  omega [..., 3, 3] -> [..., 3]"""
    return 0.5 * torch.stack(
        [omega[..., 2, 1] - omega[..., 1, 2], omega[..., 0, 2] - omega[..., 2, 0], omega[..., 1, 0] - omega[..., 0, 1]],
        -1,
    )


def _rodrigues_coeffs(theta2: torch.Tensor, small: float):
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3, stable at t -> 0."""
    is_small = theta2 < small
    t2 = torch.where(is_small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    a = torch.where(is_small, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(t) / t)
    b = torch.where(is_small, 0.5 - theta2 / 24 + theta2**2 / 720, (1 - torch.cos(t)) / t2)
    c = torch.where(is_small, 1.0 / 6 - theta2 / 120 + theta2**2 / 5040, (t - torch.sin(t)) / (t2 * t))
    return a, b, c


# ----------------------------------------------------------------------------- one transform in float64 on the CPU
# Tracking, the sensor timing and the keyframe tests take the log, exp or inverse of one 4x4 pose at a time, where
# the ~60 tensor operations of the batched forms cost ~1 ms of dispatch for a few hundred flops. The functions below
# compute one transform with Python floats by the same operations in the same order (sums left to right, as the
# batched forms reduce 3 and 4 elements), and take torch's own scalar sqrt, sin and cos, which differ from math's
# in the last bit: the results are bitwise those of the batched forms (tests/test_geometry.py).

# None where this torch does not say: the batched forms then run always
_functorch_transforms_active = getattr(torch._C, "_are_functorch_transforms_active", None)


def _one(t: torch.Tensor, shape: tuple[int, ...]) -> bool:
    """Whether ``t`` is one CPU float64 transform of ``shape`` that no gradient flows through: no autograd, and no
    functorch transform (jacfwd, vmap) or forward-mode dual level active, whose tangents Python floats would drop."""
    if t.dtype != torch.float64 or t.shape != shape or t.device.type != "cpu" or t.requires_grad:
        return False
    dual_level = getattr(torch.autograd.forward_ad, "_current_level", None)  # changes: read at each call
    return _functorch_transforms_active is not None and not _functorch_transforms_active() and dual_level == -1


def _scalar(op: Callable[[torch.Tensor], torch.Tensor], x: float) -> float:
    return op(torch.tensor(x, dtype=torch.float64)).item()


def _coeffs_one(theta2: float) -> tuple[float, float, float]:
    """:func:`_rodrigues_coeffs` of one float64 squared angle."""
    if theta2 < _SERIES_ANGLE_SQ[torch.float64]:
        return (1 - theta2 / 6 + theta2**2 / 120, 0.5 - theta2 / 24 + theta2**2 / 720,
                1.0 / 6 - theta2 / 120 + theta2**2 / 5040)
    t = _scalar(torch.sqrt, theta2)
    sin = _scalar(torch.sin, t)
    return sin / t, (1 - _scalar(torch.cos, t)) / theta2, (t - sin) / (theta2 * t)


def _hat_one(x: float, y: float, z: float) -> tuple:
    return ((0.0, -z, y), (z, 0.0, -x), (-y, x, 0.0))


def _matmul_one(A: Sequence[Sequence[float]], B: Sequence[Sequence[float]]) -> list[list[float]]:
    return [[A[i][0] * B[0][j] + A[i][1] * B[1][j] + A[i][2] * B[2][j] for j in range(len(B[0]))] for i in range(3)]


def _combine_one(a: float, K: Sequence[Sequence[float]], b: float, K2: Sequence[Sequence[float]]) -> list[list[float]]:
    """``I + a K + b K2`` (3x3), added in that order."""
    return [[(1.0 if i == j else 0.0) + a * K[i][j] + b * K2[i][j] for j in range(3)] for i in range(3)]


def _quat_one(R: Sequence[Sequence[float]]) -> tuple[float, float, float, float]:
    """:func:`rotmat_to_quat_wxyz` of one rotation."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R
    trace = r00 + r11 + r22
    candidates = ((1 + trace, r21 - r12, r02 - r20, r10 - r01),
                  (r21 - r12, 1 + r00 - r11 - r22, r01 + r10, r02 + r20),
                  (r02 - r20, r01 + r10, 1 - r00 + r11 - r22, r12 + r21),
                  (r10 - r01, r02 + r20, r12 + r21, 1 - r00 - r11 + r22))
    pivots = (trace, r00, r11, r22)
    q = candidates[max(range(4), key=lambda i: (pivots[i], -i))]  # argmax: the first of equal pivots
    norm = max(math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), torch.finfo(torch.float64).tiny)
    q = tuple(v / norm for v in q)
    return tuple(-v for v in q) if q[0] < 0 else q


def _so3_log_one(R: Sequence[Sequence[float]]) -> tuple[float, float, float]:
    """:func:`so3_log` of one rotation."""
    w, x, y, z = _quat_one(R)
    n2 = x * x + y * y + z * z
    if n2 < _TINY_SIN_SQ[torch.float64]:
        scale = 2 / w * (1 - n2 / (3 * w**2))
    else:
        n = _scalar(torch.sqrt, n2)
        scale = 2 * _scalar(lambda v: torch.atan2(v, torch.tensor(w, dtype=torch.float64)), n) / n
    return scale * x, scale * y, scale * z


def _matrix(R: Sequence[Sequence[float]], t: Sequence[float]) -> torch.Tensor:
    return torch.tensor([[*R[0], t[0]], [*R[1], t[1]], [*R[2], t[2]], [0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)


def _se3_exp_one(xi: Sequence[float]) -> torch.Tensor:
    rho, phi = xi[:3], xi[3:]
    a, b, c = _coeffs_one(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    K = _hat_one(*phi)
    K2 = _matmul_one(K, K)
    R, V = _combine_one(a, K, b, K2), _combine_one(b, K, c, K2)
    return _matrix(R, [row[0] for row in _matmul_one(V, [[r] for r in rho])])


def _se3_log_one(T: Sequence[Sequence[float]]) -> torch.Tensor:
    R, t = [row[:3] for row in T[:3]], [[row[3]] for row in T[:3]]
    phi = _so3_log_one(R)
    theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    if theta2 < _small(torch.float64):
        d = 1.0 / 12 + theta2 / 720 + theta2**2 / 30240
    else:
        a, b, _ = _coeffs_one(theta2)
        d = (1 - a / (2 * b)) / theta2
    K = _hat_one(*phi)
    V_inv = _combine_one(-0.5, K, d, _matmul_one(K, K))  # I - K/2 + D K^2 (-0.5 * k is exactly 0.5 * k negated)
    return torch.tensor([row[0] for row in _matmul_one(V_inv, t)] + list(phi), dtype=torch.float64)


def _se3_inverse_one(T: Sequence[Sequence[float]]) -> torch.Tensor:
    R_t = [[T[j][i] for j in range(3)] for i in range(3)]
    return _matrix(R_t, [-row[0] for row in _matmul_one(R_t, [[T[0][3]], [T[1][3]], [T[2][3]]])])


def so3_exp(phi: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of a rotation vector (Rodrigues).  phi [..., 3] -> R [..., 3, 3]"""
    theta2 = (phi * phi).sum(-1)
    a, b, _ = _rodrigues_coeffs(theta2, _small(phi.dtype))
    k = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def rotmat_to_quat_wxyz(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternion (w >= 0) of a rotation matrix, Shepperd's method.  R [..., 3, 3] -> q [..., 4]"""
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    trace = r00 + r11 + r22
    # Four candidate formulas, each well conditioned where its pivot is the largest.
    cand = torch.stack(
        [
            torch.stack([1 + trace, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1),
            torch.stack([R[..., 2, 1] - R[..., 1, 2], 1 + r00 - r11 - r22, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], -1),
            torch.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0], 1 - r00 + r11 - r22, R[..., 1, 2] + R[..., 2, 1]], -1),
            torch.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 - r00 - r11 + r22], -1),
        ],
        -2,
    )  # [..., 4, 4]
    pivots = torch.stack([trace, r00, r11, r22], -1)
    best = pivots.argmax(-1)  # [...]
    q = torch.gather(cand, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(R.dtype).tiny)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_wxyz_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of a quaternion (normalised here).  q [..., 4] (w, x, y, z) -> R [..., 3, 3]"""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def quat_xyzw_to_wxyz(q_xyzw: torch.Tensor) -> torch.Tensor:
    """TUM file order (qx qy qz qw) to the internal order (w, x, y, z).  [..., 4] -> [..., 4]"""
    return torch.cat([q_xyzw[..., 3:], q_xyzw[..., :3]], -1)


def quat_wxyz_to_xyzw(q_wxyz: torch.Tensor) -> torch.Tensor:
    """Internal order (w, x, y, z) to TUM file order (qx qy qz qw).  [..., 4] -> [..., 4]"""
    return torch.cat([q_wxyz[..., 1:], q_wxyz[..., :1]], -1)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vector of a rotation matrix, valid for every angle in [0, pi].  R [..., 3, 3] -> phi [..., 3]

    Goes through the quaternion: ``phi = 2 atan2(|v|, w) v / |v|`` is well conditioned at 0 and pi.
    """
    if _one(R, (3, 3)):
        return torch.tensor(_so3_log_one(R.tolist()), dtype=torch.float64)
    q = rotmat_to_quat_wxyz(R)
    w, v = q[..., 0], q[..., 1:]
    n2 = (v * v).sum(-1)
    is_small = n2 < _TINY_SIN_SQ.get(R.dtype, 1e-5)
    n = torch.sqrt(torch.where(is_small, torch.ones_like(n2), n2))
    w_safe = torch.where(is_small, w, torch.ones_like(w))
    scale = torch.where(is_small, 2 / w_safe * (1 - n2 / (3 * w_safe**2)), 2 * torch.atan2(n, w) / n)
    return scale[..., None] * v


def se3_from_rt(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Homogeneous matrix from rotation and translation.  R [..., 3, 3], t [..., 3] -> T [..., 4, 4]"""
    top = torch.cat([R, t[..., None]], -1)
    bottom = torch.zeros(*R.shape[:-2], 1, 4, dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """SE(3) exponential.  xi [..., 6] = [rho, phi] -> T [..., 4, 4]"""
    if _one(xi, (6,)):
        return _se3_exp_one(xi.tolist())
    rho, phi = xi[..., :3], xi[..., 3:]
    theta2 = (phi * phi).sum(-1)
    a, b, c = _rodrigues_coeffs(theta2, _small(xi.dtype))
    k = hat(phi)
    k2 = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(k.shape)
    R = eye + a[..., None, None] * k + b[..., None, None] * k2
    V = eye + b[..., None, None] * k + c[..., None, None] * k2
    return se3_from_rt(R, (V @ rho[..., None])[..., 0])


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """SE(3) logarithm.  T [..., 4, 4] -> xi [..., 6] = [rho, phi]"""
    if _one(T, (4, 4)):
        return _se3_log_one(T.tolist())
    R, t = T[..., :3, :3], T[..., :3, 3]
    phi = so3_log(R)
    theta2 = (phi * phi).sum(-1)
    is_small = theta2 < _small(T.dtype)
    t2 = torch.where(is_small, torch.ones_like(theta2), theta2)
    a, b, _ = _rodrigues_coeffs(theta2, _small(T.dtype))
    # V^-1 = I - K/2 + D K^2 with D = (1 - A / (2 B)) / theta^2
    d = torch.where(is_small, 1.0 / 12 + theta2 / 720 + theta2**2 / 30240, (1 - a / (2 * b)) / t2)
    k = hat(phi)
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand(k.shape)
    V_inv = eye - 0.5 * k + d[..., None, None] * (k @ k)
    return torch.cat([(V_inv @ t[..., None])[..., 0], phi], -1)


def se3_inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse of a rigid transform using R^T (exact, no matrix inversion).  [..., 4, 4] -> [..., 4, 4]"""
    if _one(T, (4, 4)):
        return _se3_inverse_one(T.tolist())
    R_t = T[..., :3, :3].transpose(-1, -2)
    return se3_from_rt(R_t, -(R_t @ T[..., :3, 3:4])[..., 0])


def se3_compose(T_ab: torch.Tensor, T_bc: torch.Tensor) -> torch.Tensor:
    """T_ac = T_ab T_bc (broadcasting).  [..., 4, 4] x [..., 4, 4] -> [..., 4, 4]"""
    return T_ab @ T_bc


def transform_points(T_ab: torch.Tensor, p_b: torch.Tensor) -> torch.Tensor:
    """Points from frame b to frame a.  T_ab [4, 4] (or broadcastable [..., 4, 4]), p_b [..., 3] -> [..., 3]"""
    return p_b @ T_ab[..., :3, :3].transpose(-1, -2) + T_ab[..., :3, 3]


def rigidity_error(T: torch.Tensor) -> torch.Tensor:
    """How far a 4x4 matrix is from a rigid transform (max abs deviation).  [..., 4, 4] -> [...]

    Measures ``|R^T R - I|``, ``|det R - 1|`` and the bottom row ``[0, 0, 0, 1]``; non-finite
    entries give ``inf``.
    """
    R = T[..., :3, :3]
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    ortho = (R.transpose(-1, -2) @ R - eye).abs().flatten(-2).amax(-1)
    det = (torch.linalg.det(R) - 1).abs()
    bottom = (T[..., 3, :] - torch.tensor([0, 0, 0, 1], dtype=T.dtype, device=T.device)).abs().amax(-1)
    err = torch.maximum(torch.maximum(ortho, det), bottom)
    finite = torch.isfinite(T).flatten(-2).all(-1)
    return torch.where(finite, err, torch.full_like(err, float("inf")))


def rotation_angle(R: torch.Tensor) -> torch.Tensor:
    """Geodesic angle of a rotation in radians, in [0, pi].  R [..., 3, 3] -> [...]"""
    return so3_log(R).norm(dim=-1)


def relative_motion(T_a: torch.Tensor, T_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Translation (the poses' units) and rotation angle (degrees) of ``T_a^-1 T_b``, the motion from pose a to
    pose b.  T_a, T_b [..., 4, 4] (broadcast, float64) -> ([...], [...])"""
    relative = se3_inverse(T_a.to(torch.float64)) @ T_b.to(torch.float64)
    return relative[..., :3, 3].norm(dim=-1), torch.rad2deg(rotation_angle(relative[..., :3, :3]))


def nearest_rigid(T: torch.Tensor) -> torch.Tensor:
    """The rigid transform nearest to ``T`` (rotation block projected onto SO(3) by SVD), float64.

    T [4, 4] -> [4, 4]. Tracking and mapping compose poses in the map's float32; their 1e-7 departures
    from orthonormality would otherwise grow through the constant-velocity prediction
    ``T_prev T_prev2^-1 T_prev`` (which inverts by transposition) by a factor ~2.4 per frame.
    """
    T = T.to(torch.float64).clone()
    U, _, Vh = torch.linalg.svd(T[:3, :3])
    d = torch.sign(torch.linalg.det(U @ Vh))
    T[:3, :3] = U @ torch.diag(torch.stack([torch.ones_like(d), torch.ones_like(d), d])) @ Vh
    T[3] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    return T


def _rodrigues_parts(phi: np.ndarray) -> tuple:
    """The coefficients A, B, C of :func:`_rodrigues_coeffs` and their derivatives with respect to theta^2
    (float64, one rotation vector ``phi`` [3]): the derivative of the same branch, so the series' own
    derivative below the switch, as autograd takes it through :func:`se3_exp`."""
    s = float(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    if s < _SERIES_ANGLE_SQ[torch.float64]:
        return (1 - s / 6 + s**2 / 120, 0.5 - s / 24 + s**2 / 720, 1.0 / 6 - s / 120 + s**2 / 5040,
                -1.0 / 6 + s / 60, -1.0 / 24 + s / 360, -1.0 / 120 + s / 2520)
    t = math.sqrt(s)
    sin, cos = math.sin(t), math.cos(t)
    return (sin / t, (1 - cos) / s, (t - sin) / (s * t),
            (t * cos - sin) / (2 * s * t), (t * sin / 2 - (1 - cos)) / (s * s),
            (1 - cos) / (2 * s * s) - 1.5 * (t - sin) / (s * s * t))


def _hat_np(v) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


_HAT_BASIS = tuple(_hat_np(e) for e in np.eye(3))  # hat(e_k), k = 0, 1, 2


def _left_increment(rho: torch.Tensor, phi: torch.Tensor, T: torch.Tensor) -> tuple[np.ndarray, tuple]:
    """``exp([rho, phi]) T`` in float64 numpy and the parts its derivative needs (:func:`_left_increment_vjp`)."""
    rho64 = rho.detach().to(device="cpu", dtype=torch.float64).numpy()
    phi64 = phi.detach().to(device="cpu", dtype=torch.float64).numpy()
    a, b, c, da, db, dc = _rodrigues_parts(phi64)
    K = _hat_np(phi64)
    K2 = K @ K
    eye = np.eye(3)
    R = eye + a * K + b * K2
    V = eye + b * K + c * K2
    increment = np.eye(4)
    increment[:3, :3], increment[:3, 3] = R, V @ rho64
    T64 = T.detach().to(device="cpu", dtype=torch.float64).numpy()
    return increment @ T64, (rho64, phi64, T64, K, K2, V, a, b, c, da, db, dc)


def _left_increment_vjp(parts: tuple, grad: torch.Tensor, dtypes: tuple[torch.dtype, torch.dtype]
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """dL/drho [3], dL/dphi [3] (in ``dtypes``, on the gradient's device) from dL/d(exp([rho, phi]) T) ``grad``
    [4, 4]."""
    rho64, phi64, T64, K, K2, V, a, b, c, da, db, dc = parts
    G = grad.detach().to(device="cpu", dtype=torch.float64).numpy() @ T64.T  # dL/d(increment) [4, 4]
    G_R, G_t = G[:3, :3], G[:3, 3]
    H = np.outer(G_t, rho64)  # t = V rho: dL/dV
    grad_rho = V.T @ G_t
    # dR = dA K + A dK + dB K^2 + B (dK K + K dK), dV = dB K + B dK + dC K^2 + C (dK K + K dK);
    # dA = A'(s) 2 phi_k, dK = hat(e_k)
    radial = 2.0 * (da * np.sum(G_R * K) + db * np.sum(G_R * K2) + db * np.sum(H * K) + dc * np.sum(H * K2))
    linear, quadratic = a * G_R + b * H, b * G_R + c * H
    grad_phi = np.array([radial * phi64[k] + np.sum(linear * E) + np.sum(quadratic * (E @ K + K @ E))
                         for k, E in enumerate(_HAT_BASIS)])
    return (torch.from_numpy(grad_rho).to(device=grad.device, dtype=dtypes[0]),
            torch.from_numpy(grad_phi).to(device=grad.device, dtype=dtypes[1]))


class _LeftIncrement(torch.autograd.Function):
    """``exp([rho, phi]) T`` with the derivative of the Rodrigues formulas written out (see
    :func:`se3_exp_times`)."""

    @staticmethod
    def forward(ctx, rho, phi, T, dtype):
        product, ctx.parts = _left_increment(rho, phi, T)
        ctx.input_dtypes = (rho.dtype, phi.dtype)
        return torch.from_numpy(product).to(device=T.device, dtype=dtype)

    @staticmethod
    def backward(ctx, grad):
        return _left_increment_vjp(ctx.parts, grad, ctx.input_dtypes) + (None, None)


def se3_exp_times(rho: torch.Tensor, phi: torch.Tensor, T: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``(se3_exp([rho, phi]) @ T).to(dtype)`` in float64 for one twist, differentiable in rho and phi: a pose
    that an optimiser moves by a left increment (tracking's step). The values are those of :func:`se3_exp`; the
    backward is the derivative of its Rodrigues formulas written out (A, B, C and their derivatives in theta^2,
    the series below the same switch), about 20 numpy operations on 3x3 matrices against the ~40 tensor
    operations autograd records for se3_exp: one tracking step's pose with its backward costs 0.2 ms instead of
    0.9 (2 threads, median of 500).

    rho [3] metres, phi [3] radians (any float dtype; their gradients come back in it), T [4, 4] (no gradient)
    -> [4, 4] in ``dtype`` on T's device.
    """
    _check_left_increment("se3_exp_times", rho, phi, T)
    return _LeftIncrement.apply(rho, phi, T, dtype)


def se3_exp_times_vjp(rho: torch.Tensor, phi: torch.Tensor, T: torch.Tensor, dtype: torch.dtype
                      ) -> tuple[torch.Tensor, Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]]:
    """:func:`se3_exp_times` without autograd: the pose and its vector-Jacobian product, for a caller that
    carries the chain rule itself (tracking's compiled step). The same values and gradients, bit for bit.

    rho [3], phi [3], T [4, 4] -> (``(se3_exp([rho, phi]) @ T).to(dtype)`` [4, 4] on T's device, ``vjp``: dL/dpose
    [4, 4] -> (dL/drho [3], dL/dphi [3]) in rho's and phi's dtypes and on the gradient's device).
    """
    _check_left_increment("se3_exp_times_vjp", rho, phi, T)
    product, parts = _left_increment(rho, phi, T)
    dtypes = (rho.dtype, phi.dtype)
    return (torch.from_numpy(product).to(device=T.device, dtype=dtype),
            lambda grad: _left_increment_vjp(parts, grad, dtypes))


def _check_left_increment(name: str, rho: torch.Tensor, phi: torch.Tensor, T: torch.Tensor) -> None:
    if rho.shape != (3,) or phi.shape != (3,) or T.shape != (4, 4):
        raise ValueError(f"{name}: rho [3], phi [3] and T [4, 4] expected, got {tuple(rho.shape)}, "
                         f"{tuple(phi.shape)} and {tuple(T.shape)}")


def interpolate_pose(T_a: torch.Tensor, T_b: torch.Tensor, weight: float | torch.Tensor) -> torch.Tensor:
    """Pose a fraction ``weight`` of the way from T_a to T_b.  [..., 4, 4], [..., 4, 4], weight float or [...]
    -> [..., 4, 4]

    Translation linear, rotation ``R_a exp(weight * log(R_a^T R_b))`` (SLERP).
    """
    weight = torch.as_tensor(weight, dtype=T_a.dtype, device=T_a.device)[..., None]  # [..., 1]
    R_a, R_b = T_a[..., :3, :3], T_b[..., :3, :3]
    R = R_a @ so3_exp(weight * so3_log(R_a.transpose(-1, -2) @ R_b))
    t = (1.0 - weight) * T_a[..., :3, 3] + weight * T_b[..., :3, 3]
    return se3_from_rt(R, t)
