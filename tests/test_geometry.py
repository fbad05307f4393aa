"""mipslam.geometry: SO(3)/SE(3) exp/log, quaternions, inverse, gradients, camera model, rigidity."""
from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation
from torch.autograd import gradcheck

from mipslam.geometry import (
    hat,
    interpolate_pose,
    pixel_grid,
    project,
    quat_wxyz_to_rotmat,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_wxyz,
    relative_motion,
    rigidity_error,
    rotation_angle,
    rotmat_to_quat_wxyz,
    se3_compose,
    se3_exp,
    se3_exp_times,
    se3_exp_times_vjp,
    se3_inverse,
    se3_log,
    so3_exp,
    so3_log,
    transform_points,
    unproject,
    unproject_depth,
    vee,
)
from mipslam.types import Intrinsics

F64 = torch.float64


def random_rotvecs(n: int, seed: int, max_angle: float = math.pi - 1e-3) -> torch.Tensor:
    """Rotation vectors with uniformly random axes and angles in [0, max_angle).  -> [n, 3]"""
    generator = torch.Generator().manual_seed(seed)
    axes = torch.randn(n, 3, generator=generator, dtype=F64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    angles = torch.rand(n, 1, generator=generator, dtype=F64) * max_angle
    return axes * angles


def random_twists(n: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed + 1000)
    rho = torch.randn(n, 3, generator=generator, dtype=F64) * 2.0
    return torch.cat([rho, random_rotvecs(n, seed)], -1)


# ----------------------------------------------------------------------------- exp / log round trips


def test_so3_exp_log_round_trip_random():
    phi = random_rotvecs(500, seed=1)
    assert torch.allclose(so3_log(so3_exp(phi)), phi, atol=1e-12, rtol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-14, 1e-10, 1e-8, 1e-6, 1e-4, 3e-3, 1e-2])
def test_so3_round_trip_near_zero(angle):
    axis = torch.tensor([0.48, -0.6, 0.64], dtype=F64)
    phi = axis * angle
    R = so3_exp(phi)
    assert torch.allclose(so3_log(R), phi, atol=1e-15, rtol=1e-12)
    # first-order behaviour: R = I + hat(phi) + O(angle^2)
    assert torch.allclose(R, torch.eye(3, dtype=F64) + hat(phi), atol=angle**2 + 1e-16)


@pytest.mark.parametrize("angle", [math.pi - 1e-2, math.pi - 1e-5, math.pi - 1e-8, math.pi])
def test_so3_round_trip_near_pi(angle):
    axis = torch.tensor([0.48, -0.6, 0.64], dtype=F64)
    R = so3_exp(axis * angle)
    phi = so3_log(R)
    assert abs(phi.norm().item() - angle) < 1e-9
    # At pi, phi and -phi are the same rotation; the round trip through exp must be exact.
    assert torch.allclose(so3_exp(phi), R, atol=1e-12)
    if angle < math.pi - 1e-7:
        assert torch.allclose(phi, axis * angle, atol=1e-7)


def test_so3_exp_matches_scipy():
    phi = random_rotvecs(200, seed=2)
    expected = torch.from_numpy(Rotation.from_rotvec(phi.numpy()).as_matrix())
    assert torch.allclose(so3_exp(phi), expected, atol=1e-13)
    assert torch.allclose(rotation_angle(so3_exp(phi)), phi.norm(dim=-1), atol=1e-12)


def test_se3_exp_log_round_trip_random_and_special():
    xi = random_twists(300, seed=3)
    assert torch.allclose(se3_log(se3_exp(xi)), xi, atol=1e-11, rtol=0)
    special = torch.tensor(
        [
            [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            [1.0, -2.0, 3.0, 0.0, 0.0, 0.0],  # pure translation
            [0.5, 0.1, -0.2, 1e-9, -2e-9, 5e-10],  # tiny rotation
            [0.3, -0.2, 0.5, 0.0, 0.0, math.pi - 1e-6],  # almost half a turn
        ],
        dtype=F64,
    )
    assert torch.allclose(se3_log(se3_exp(special)), special, atol=1e-10, rtol=0)
    # exp of a pure translation twist is that translation
    assert torch.allclose(se3_exp(special[1])[:3, 3], special[1, :3])


def test_se3_exp_closed_form_matches_matrix_exponential():
    xi = random_twists(50, seed=4)
    twist_matrix = torch.zeros(50, 4, 4, dtype=F64)
    twist_matrix[:, :3, :3] = hat(xi[:, 3:])
    twist_matrix[:, :3, 3] = xi[:, :3]
    assert torch.allclose(se3_exp(xi), torch.linalg.matrix_exp(twist_matrix), atol=1e-10)


def test_batched_shapes_and_float32():
    xi = random_twists(24, seed=5).reshape(2, 3, 4, 6)
    T = se3_exp(xi)
    assert T.shape == (2, 3, 4, 4, 4)
    assert se3_log(T).shape == (2, 3, 4, 6)
    assert so3_exp(xi[..., 3:]).shape == (2, 3, 4, 3, 3)
    assert so3_log(T[..., :3, :3]).shape == (2, 3, 4, 3)
    assert rotmat_to_quat_wxyz(T[..., :3, :3]).shape == (2, 3, 4, 4)
    assert se3_inverse(T).shape == T.shape
    assert rigidity_error(T).shape == (2, 3, 4)
    # the batch of one equals the unbatched call
    assert torch.allclose(se3_exp(xi[1, 2, 3]), T[1, 2, 3])
    # float32 stays float32 and is accurate to float32 precision
    T32 = se3_exp(xi.float())
    assert T32.dtype == torch.float32
    assert torch.allclose(T32.double(), T, atol=5e-6)
    assert torch.allclose(se3_log(T32).double(), xi, atol=5e-5)


def test_hat_vee_inverse():
    phi = random_rotvecs(10, seed=6)
    K = hat(phi)
    assert torch.allclose(K, -K.transpose(-1, -2))
    assert torch.allclose(vee(K), phi)
    v = torch.randn(10, 3, dtype=F64)
    assert torch.allclose((K @ v[..., None])[..., 0], torch.linalg.cross(phi, v))


# ----------------------------------------------------------------------------- quaternions


def test_quaternion_conversions_against_scipy_both_orders():
    rotations = Rotation.random(300, random_state=7)
    quats_xyzw = torch.from_numpy(rotations.as_quat())  # scipy: scalar last (x, y, z, w) = TUM order
    quats_wxyz = quat_xyzw_to_wxyz(quats_xyzw)
    assert torch.equal(quats_wxyz[:, 0], quats_xyzw[:, 3])
    assert torch.equal(quat_wxyz_to_xyzw(quats_wxyz), quats_xyzw)
    expected_R = torch.from_numpy(rotations.as_matrix())
    assert torch.allclose(quat_wxyz_to_rotmat(quats_wxyz), expected_R, atol=1e-13)
    # matrix -> quaternion: w >= 0, same as scipy's canonical quaternion
    back_wxyz = rotmat_to_quat_wxyz(expected_R)
    assert bool((back_wxyz[:, 0] >= 0).all())
    canonical_xyzw = torch.from_numpy(rotations.as_quat(canonical=True))
    assert torch.allclose(quat_wxyz_to_xyzw(back_wxyz), canonical_xyzw, atol=1e-12)
    # scipy's wxyz order agrees with ours as well
    assert torch.allclose(back_wxyz, torch.from_numpy(rotations.as_quat(canonical=True, scalar_first=True)), atol=1e-12)


def test_quaternion_of_every_pivot_case_and_unnormalised_input():
    # Rotations by pi about each axis force each branch of Shepperd's method.
    for axis in torch.eye(3, dtype=F64):
        for angle in (math.pi, math.pi - 0.1, 0.3):
            R = so3_exp(axis * angle)
            q_wxyz = rotmat_to_quat_wxyz(R)
            assert abs(q_wxyz.norm().item() - 1) < 1e-14
            assert torch.allclose(quat_wxyz_to_rotmat(q_wxyz), R, atol=1e-13)
    q_wxyz = torch.tensor([2.0, 0.4, -0.2, 0.8], dtype=F64)  # not unit: normalised inside
    R = quat_wxyz_to_rotmat(q_wxyz)
    assert torch.allclose(R, torch.from_numpy(Rotation.from_quat(q_wxyz.numpy(), scalar_first=True).as_matrix()))
    assert rigidity_error(R4(R)).item() < 1e-14


def R4(R: torch.Tensor) -> torch.Tensor:
    T = torch.eye(4, dtype=R.dtype).repeat(*R.shape[:-2], 1, 1)
    T[..., :3, :3] = R
    return T


# ----------------------------------------------------------------------------- inverse, compose, points


def test_se3_inverse_and_compose():
    T = se3_exp(random_twists(100, seed=8))
    T_inv = se3_inverse(T)
    eye = torch.eye(4, dtype=F64).expand_as(T)
    assert torch.allclose(se3_compose(T, T_inv), eye, atol=1e-12)
    assert torch.allclose(se3_compose(T_inv, T), eye, atol=1e-12)
    assert torch.allclose(T_inv, torch.linalg.inv(T), atol=1e-11)
    # log(T^-1) = -log(T)
    assert torch.allclose(se3_log(T_inv), -se3_log(T), atol=1e-10)


def test_transform_points_matches_homogeneous_product():
    T = se3_exp(random_twists(1, seed=9))[0]
    p = torch.randn(17, 3, dtype=F64)
    homogeneous = torch.cat([p, torch.ones(17, 1, dtype=F64)], -1)
    expected = (T @ homogeneous.T).T[:, :3]
    assert torch.allclose(transform_points(T, p), expected, atol=1e-13)
    assert torch.allclose(transform_points(se3_inverse(T), transform_points(T, p)), p, atol=1e-12)


# ----------------------------------------------------------------------------- gradients (float64 gradcheck)


def _gradcheck(fn, x: torch.Tensor) -> bool:
    return gradcheck(fn, (x.detach().clone().requires_grad_(True),), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gradcheck_se3_exp_random_and_near_zero():
    assert _gradcheck(se3_exp, random_twists(4, seed=10))
    tiny = random_twists(3, seed=11)
    tiny[:, 3:] *= 1e-8
    assert _gradcheck(se3_exp, tiny)
    assert _gradcheck(se3_exp, torch.zeros(2, 6, dtype=F64))


def test_gradcheck_se3_log_random_and_near_zero():
    assert _gradcheck(se3_log, se3_exp(random_twists(4, seed=12)))
    near_zero = se3_exp(torch.tensor([[0.1, 0.2, 0.3, 1e-7, -2e-7, 0.0]], dtype=F64))
    assert _gradcheck(se3_log, near_zero)
    assert _gradcheck(se3_log, torch.eye(4, dtype=F64)[None])


def test_gradcheck_so3_log_random_zero_and_near_pi():
    assert _gradcheck(so3_log, so3_exp(random_rotvecs(4, seed=13)))
    assert _gradcheck(so3_log, torch.eye(3, dtype=F64)[None])
    assert _gradcheck(so3_log, so3_exp(torch.tensor([[0.0, 1e-7, 0.0]], dtype=F64)))
    assert _gradcheck(so3_log, so3_exp(torch.tensor([[0.0, 0.0, math.pi - 1e-3]], dtype=F64)))


def test_gradcheck_quat_wxyz_to_rotmat_including_near_zero_angle():
    generator = torch.Generator().manual_seed(14)
    assert _gradcheck(quat_wxyz_to_rotmat, torch.randn(4, 4, generator=generator, dtype=F64))
    assert _gradcheck(quat_wxyz_to_rotmat, torch.tensor([[1.0, 1e-8, -2e-8, 0.0], [1.0, 0.0, 0.0, 0.0]], dtype=F64))


def test_gradients_are_finite_at_exact_zero():
    xi = torch.zeros(6, dtype=F64, requires_grad=True)
    se3_log(se3_exp(xi)).sum().backward()
    assert torch.isfinite(xi.grad).all()
    # d log(exp(xi)) / d xi = I at zero
    jac = torch.autograd.functional.jacobian(lambda x: se3_log(se3_exp(x)), torch.zeros(6, dtype=F64))
    assert torch.allclose(jac, torch.eye(6, dtype=F64), atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-6, 5e-3, 0.0099, 0.0101, 0.3, 2.5])
def test_se3_exp_times_matches_se3_exp_values_and_gradients(angle):
    """The closed-form backward of tracking's pose step against autograd through se3_exp: float32 bit for bit
    (what tracking renders and steps on), float64 to rounding, on both sides of the series switch (theta^2 =
    1e-4, theta = 0.01)."""
    generator = torch.Generator().manual_seed(int(angle * 1e4) + 21)
    T = se3_exp(torch.randn(6, generator=generator, dtype=F64))
    for dtype in (torch.float32, F64):
        axis = torch.randn(3, generator=generator, dtype=F64)
        phi0 = (axis / axis.norm() * angle).to(dtype)
        rho0 = (0.05 * torch.randn(3, generator=generator, dtype=F64)).to(dtype)
        upstream = torch.randn(4, 4, generator=generator, dtype=F64).to(dtype)
        grads = []
        for closed_form in (False, True):
            rho, phi = rho0.clone().requires_grad_(True), phi0.clone().requires_grad_(True)
            if closed_form:
                out = se3_exp_times(rho, phi, T, dtype)
            else:
                out = (se3_exp(torch.cat([rho, phi]).to(F64)) @ T).to(dtype)
            (out * upstream).sum().backward()
            assert out.dtype == dtype and rho.grad.dtype == dtype and phi.grad.dtype == dtype
            grads.append((out.detach(), rho.grad, phi.grad))
        (out_ref, rho_ref, phi_ref), (out_new, rho_new, phi_new) = grads
        if dtype == torch.float32:
            assert torch.equal(out_ref, out_new)
            assert torch.allclose(rho_ref, rho_new, rtol=1e-6, atol=1e-7)
            assert torch.allclose(phi_ref, phi_new, rtol=1e-6, atol=1e-7)
        else:
            assert torch.allclose(out_ref, out_new, rtol=0, atol=1e-14)
            assert torch.allclose(rho_ref, rho_new, rtol=1e-12, atol=1e-13)
            assert torch.allclose(phi_ref, phi_new, rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("angle", [0.0, 5e-3, 0.0101, 0.3])
def test_se3_exp_times_vjp_is_bit_equal_to_autograd(angle):
    """Tracking's compiled step carries the pose's chain rule itself: value and gradients equal to
    se3_exp_times under autograd, bit for bit, in float32 and float64."""
    generator = torch.Generator().manual_seed(int(angle * 1e4) + 31)
    T = se3_exp(torch.randn(6, generator=generator, dtype=F64))
    for dtype in (torch.float32, F64):
        axis = torch.randn(3, generator=generator, dtype=F64)
        rho = (0.05 * torch.randn(3, generator=generator, dtype=F64)).to(dtype).requires_grad_(True)
        phi = (axis / axis.norm() * angle).to(dtype).requires_grad_(True)
        upstream = torch.randn(4, 4, generator=generator, dtype=F64).to(dtype)
        out = se3_exp_times(rho, phi, T, dtype)
        out.backward(upstream)
        value, vjp = se3_exp_times_vjp(rho, phi, T, dtype)
        grad_rho, grad_phi = vjp(upstream)
        assert torch.equal(value, out.detach()) and not value.requires_grad
        assert torch.equal(grad_rho, rho.grad) and torch.equal(grad_phi, phi.grad)
        assert grad_rho.dtype == dtype and grad_phi.dtype == dtype
    with pytest.raises(ValueError, match="rho \\[3\\], phi \\[3\\] and T \\[4, 4\\]"):
        se3_exp_times_vjp(torch.zeros(3), torch.zeros(4), T, F64)


def test_se3_exp_times_gradcheck_and_shape_errors():
    T = se3_exp(random_twists(1, seed=22))[0]
    for scale in (1.0, 1e-3, 0.0):
        twist = random_twists(1, seed=23)[0] * scale
        rho, phi = (twist[:3].clone().requires_grad_(True), twist[3:].clone().requires_grad_(True))
        assert gradcheck(lambda r, p: se3_exp_times(r, p, T, F64), (rho, phi), eps=1e-6, atol=1e-6, rtol=1e-5)
    with pytest.raises(ValueError, match="rho \\[3\\], phi \\[3\\] and T \\[4, 4\\]"):
        se3_exp_times(torch.zeros(6), torch.zeros(3), T, F64)


# ----------------------------------------------------------------------------- camera


def test_project_unproject_round_trip():
    K = torch.tensor([[517.3, 0.0, 318.6], [0.0, 516.5, 255.3], [0.0, 0.0, 1.0]], dtype=F64)
    generator = torch.Generator().manual_seed(15)
    uv = torch.rand(200, 2, generator=generator, dtype=F64) * torch.tensor([640.0, 480.0], dtype=F64) - 0.5
    depth = 0.2 + 5 * torch.rand(200, generator=generator, dtype=F64)
    points = unproject(uv, depth, K)
    uv_back, z = project(points, K)
    assert torch.allclose(uv_back, uv, atol=1e-10)
    assert torch.allclose(z, depth)
    # the principal point looks straight ahead
    centre = unproject(torch.tensor([318.6, 255.3], dtype=F64), torch.tensor(2.0, dtype=F64), K)
    assert torch.allclose(centre, torch.tensor([0.0, 0.0, 2.0], dtype=F64))


def test_unproject_depth_uses_pixel_centres():
    K = torch.tensor([[100.0, 0.0, 2.0], [0.0, 100.0, 1.0], [0.0, 0.0, 1.0]], dtype=F64)
    depth = torch.full((3, 5), 2.0, dtype=F64)
    points = unproject_depth(depth, K)
    assert points.shape == (3, 5, 3)
    assert torch.allclose(points[1, 2], torch.tensor([0.0, 0.0, 2.0], dtype=F64))  # pixel (u=2, v=1) = (cx, cy)
    assert torch.allclose(points[0, 4], torch.tensor([2 * 2.0 / 100, -1 * 2.0 / 100, 2.0], dtype=F64))
    grid = pixel_grid(3, 5)
    assert grid[2, 4].tolist() == [4.0, 2.0]


def test_intrinsics_scaled_pixel_centre_rule():
    intr = Intrinsics(fx=500.0, fy=400.0, cx=319.5, cy=239.5, width=640, height=480)
    up = intr.scaled(2.0)
    assert (up.width, up.height) == (1280, 960)
    assert (up.fx, up.fy) == (1000.0, 800.0)
    K, K_up = intr.matrix(F64), up.matrix(F64)
    generator = torch.Generator().manual_seed(16)
    points = torch.randn(50, 3, generator=generator, dtype=F64) + torch.tensor([0.0, 0.0, 4.0], dtype=F64)
    uv, _ = project(points, K)
    uv_up, _ = project(points, K_up)
    assert torch.allclose(uv_up, 2 * uv + 0.5, atol=1e-10)  # pixel centre u -> 2u + 0.5
    # the image edges stay the image edges: -0.5 -> -0.5 and width - 0.5 -> 2 width - 0.5
    for edge, edge_up in ((-0.5, -0.5), (intr.width - 0.5, up.width - 0.5)):
        ray = unproject(torch.tensor([edge, edge], dtype=F64), torch.tensor(1.0, dtype=F64), K)
        uv_edge, _ = project(ray, K_up)
        assert abs(uv_edge[0].item() - edge_up) < 1e-10
    # halving then doubling gives the original camera back
    back = intr.scaled(0.5).scaled(2.0)
    assert (back.fx, back.fy, back.cx, back.cy, back.width, back.height) == (500.0, 400.0, 319.5, 239.5, 640, 480)
    with pytest.raises(ValueError):
        intr.scaled(0.0)


# ----------------------------------------------------------------------------- rigidity


def test_rigidity_error_detects_non_rigid_and_non_finite():
    T = se3_exp(random_twists(5, seed=17))
    assert rigidity_error(T).max().item() < 1e-13
    scaled = T.clone()
    scaled[:, :3, :3] *= 1.01  # a similarity, not a rigid motion
    assert (rigidity_error(scaled) > 0.019).all()
    sheared = T.clone()
    sheared[:, 0, 1] += 0.05
    assert (rigidity_error(sheared) > 0.01).all()
    reflected = T.clone()
    reflected[:, :3, 0] *= -1  # orthogonal but det = -1
    assert torch.allclose(rigidity_error(reflected), torch.full((5,), 2.0, dtype=F64), atol=1e-12)
    bottom = T.clone()
    bottom[:, 3, 0] = 0.3
    assert torch.allclose(rigidity_error(bottom), torch.full((5,), 0.3, dtype=F64), atol=1e-12)
    for bad in (float("nan"), float("inf")):
        broken = T.clone()
        broken[2, 1, 3] = bad
        err = rigidity_error(broken)
        assert math.isinf(err[2].item())
        assert torch.isfinite(err[[0, 1, 3, 4]]).all()


@pytest.mark.parametrize("angle", [1e-7, 1e-5, 1e-4, 1e-3, 1e-2, 3e-2, 0.3])
def test_se3_log_of_exp_is_accurate_at_small_angles(angle):
    """Log(Exp(xi)) = xi to float64 precision across the series/closed-form switch (no cancellation loss)."""
    direction = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    phi = angle * direction / direction.norm()
    xi = torch.cat([torch.tensor([0.2, -0.1, 0.4], dtype=torch.float64), phi])
    back = se3_log(se3_exp(xi))
    assert (back - xi).abs().max() < 1e-13 * max(1.0, float(xi.norm()))


def test_relative_motion_is_the_motion_from_the_first_pose_to_the_second():
    # b is a turned 30 degrees about its own y axis and moved 0.5 m along a's x: |t| and the angle of T_a^-1 T_b,
    # whatever a's own pose; batched over the first argument
    T_a = se3_exp(torch.tensor([0.3, -1.0, 2.0, 0.4, 0.1, -0.7], dtype=torch.float64))
    T_ab = se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, math.radians(30), 0.0], dtype=torch.float64))
    T_ab[0, 3] = 0.5
    translation, angle = relative_motion(T_a, T_a @ T_ab)
    assert float(translation) == pytest.approx(0.5) and float(angle) == pytest.approx(30.0)
    translations, angles = relative_motion(torch.stack([T_a, T_a @ T_ab]), T_a @ T_ab)
    assert translations.shape == (2,) and torch.allclose(translations, torch.tensor([0.5, 0.0], dtype=torch.float64))
    assert torch.allclose(angles, torch.tensor([30.0, 0.0], dtype=torch.float64), atol=1e-9)


def test_interpolate_pose_batched_matches_one_pose_at_a_time():
    generator = torch.Generator().manual_seed(3)
    T_a = se3_exp(0.5 * torch.randn(7, 6, generator=generator, dtype=torch.float64))
    T_b = se3_exp(0.5 * torch.randn(7, 6, generator=generator, dtype=torch.float64))
    weight = torch.rand(7, generator=generator, dtype=torch.float64)
    batched = interpolate_pose(T_a, T_b, weight)
    assert batched.shape == (7, 4, 4)
    for k in range(7):
        torch.testing.assert_close(batched[k], interpolate_pose(T_a[k], T_b[k], float(weight[k])), rtol=0, atol=1e-12)
    # the ends are the poses themselves, halfway the rotation is half the relative one
    torch.testing.assert_close(interpolate_pose(T_a, T_b, torch.zeros(7, dtype=torch.float64)), T_a, rtol=0, atol=1e-12)
    torch.testing.assert_close(interpolate_pose(T_a, T_b, 1.0), T_b, rtol=0, atol=1e-12)
    half = interpolate_pose(T_a[0], T_b[0], 0.5)
    angle_ab = float(rotation_angle(T_a[0, :3, :3].T @ T_b[0, :3, :3]))
    assert float(rotation_angle(T_a[0, :3, :3].T @ half[:3, :3])) == pytest.approx(angle_ab / 2, abs=1e-12)


def test_one_transform_in_float64_is_bitwise_the_batched_forms():
    """se3_log, se3_exp, se3_inverse and so3_log of one CPU float64 transform (computed with Python floats) give
    bitwise what the batched torch forms give for it, at every angle from 1e-6 rad to pi; float32 and gradients
    take the batched forms."""
    generator = torch.Generator().manual_seed(3)
    for k in range(3000):
        scale = (1e-6, 1e-3, 0.02, 0.3, 3.0)[k % 5]
        xi = scale * torch.randn(6, generator=generator, dtype=torch.float64)
        T = se3_exp(xi[None])[0]
        assert torch.equal(se3_exp(xi), T)
        assert torch.equal(se3_log(T), se3_log(T[None])[0])
        assert torch.equal(se3_inverse(T), se3_inverse(T[None])[0])
        assert torch.equal(so3_log(T[:3, :3]), so3_log(T[None, :3, :3])[0])
    R_pi = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # the quaternion's w = 0
    assert torch.equal(so3_log(R_pi), so3_log(R_pi[None])[0])
    assert torch.equal(se3_log(torch.eye(4, dtype=torch.float64)), torch.zeros(6, dtype=torch.float64))
    xi = torch.full((6,), 0.1, dtype=torch.float64, requires_grad=True)
    se3_log(se3_exp(xi)).sum().backward()  # a gradient flows through the batched forms
    assert xi.grad is not None and torch.isfinite(xi.grad).all()
    forward = torch.func.jacfwd(lambda v: se3_log(se3_exp(v)))(torch.full((6,), 0.1, dtype=torch.float64))
    assert torch.allclose(forward, torch.eye(6, dtype=torch.float64), atol=1e-8)  # forward mode too: log(exp(v)) = v
    assert se3_exp(xi.detach().float()).dtype == torch.float32
