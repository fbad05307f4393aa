"""Direct RGB-D alignment (mipslam/geometry/direct.py, and its compiled twin mipslam.render.cpu.align_direct) on an
analytic scene: a textured slanted plane seen by two cameras, each image computed by intersecting its pixel rays
with the plane (no renderer involved). Every behaviour test runs on both; the compiled one must also equal the
reference to rounding and give the same bits whatever the thread count."""
from __future__ import annotations

import math

import pytest
import torch

from mipslam.geometry import se3_exp, se3_inverse, se3_log
from mipslam.geometry.direct import align_direct as reference_align_direct
from mipslam.geometry.direct import direct_reference, direct_target, pyramid_scales
from mipslam.render import cpu as cpu_backend

WIDTH, HEIGHT = 96, 72
K = torch.tensor([[80.0, 0.0, 47.5], [0.0, 80.0, 35.5], [0.0, 0.0, 1.0]])
PLANE_NORMAL = torch.tensor([0.25, -0.15, 1.0], dtype=torch.float64)  # world plane n . X = 1.6 (slanted)
PLANE_OFFSET = 1.6


def _texture(X: torch.Tensor) -> torch.Tensor:
    """Smooth intensity in [0.15, 0.85] on the plane.  X [..., 3] world points -> [...]"""
    x, y = X[..., 0], X[..., 1]
    return 0.5 + 0.2 * torch.sin(9.0 * x) * torch.cos(7.0 * y) + 0.15 * torch.sin(13.0 * (x + 0.6 * y))


def _view(T_cw: torch.Tensor, width: int = WIDTH, height: int = HEIGHT, k: torch.Tensor = K):
    """Colour [h, w, 3] and depth [h, w] of the plane seen from world-to-camera T_cw [4, 4] float64."""
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                          indexing="ij")
    k = k.double()
    rays = torch.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], torch.ones_like(u)], -1)  # z = 1
    T_wc = se3_inverse(T_cw)
    R, origin = T_wc[:3, :3], T_wc[:3, 3]
    directions = rays @ R.T
    s = (PLANE_OFFSET - PLANE_NORMAL @ origin) / (directions @ PLANE_NORMAL)  # depth along the camera's z
    gray = _texture(origin + s[..., None] * directions)
    return gray[..., None].expand(height, width, 3).float().contiguous(), s.float()


def _pyramids(T_cw_reference, T_cw_target, levels=2, brightness=0.0):
    references, targets = [], []
    color_r, depth_r = _view(T_cw_reference)
    color_t, depth_t = _view(T_cw_target)
    color_t = (color_t + brightness).clamp(0, 1)
    for scale in pyramid_scales(levels):
        w, h = round(WIDTH * scale), round(HEIGHT * scale)
        k = K.clone()
        k[:2] *= scale
        k[0, 2], k[1, 2] = scale * (K[0, 2] + 0.5) - 0.5, scale * (K[1, 2] + 0.5) - 0.5
        cr, dr = _view(T_cw_reference, w, h, k)
        ct, dt = _view(T_cw_target, w, h, k)
        references.append(direct_reference(cr, dr, torch.ones(h, w, dtype=torch.bool), k))
        targets.append(direct_target((ct + brightness).clamp(0, 1), dt, k))
    return references, targets


def _error(T: torch.Tensor, T_true: torch.Tensor) -> tuple[float, float]:
    e = se3_log(T @ se3_inverse(T_true))
    return float(e[:3].norm()), math.degrees(float(e[3:].norm()))


@pytest.fixture(params=["torch", "cpu"])
def align_direct(request):
    """The torch reference or the compiled alignment (skipped where the library is not built)."""
    if request.param == "torch":
        return reference_align_direct
    if not cpu_backend.is_available():
        pytest.skip(f"the compiled CPU library is not available: {cpu_backend.unavailable_reason()}")
    return cpu_backend.align_direct


MOTION = torch.tensor([0.02, -0.012, 0.015, 0.012, -0.02, 0.01], dtype=torch.float64)  # 2.8 cm, 1.4 degrees


@pytest.mark.parametrize("alpha_color, depth_noise_power", [(0.5, 0.0), (0.9, 0.0), (0.5, 2.0)])
def test_direct_alignment_recovers_a_known_motion_to_a_fraction_of_a_millimetre(align_direct, alpha_color,
                                                                                 depth_noise_power):
    T_ref = torch.eye(4, dtype=torch.float64)
    T_motion = se3_exp(MOTION)  # target camera from reference camera
    references, targets = _pyramids(T_ref, T_motion @ T_ref)
    start = _error(torch.eye(4, dtype=torch.float64), T_motion)
    result = align_direct(references, targets, torch.eye(4, dtype=torch.float64), iterations=15,
                          alpha_color=alpha_color, depth_noise_power=depth_noise_power)
    translation, rotation = _error(result.T, T_motion)
    assert result.ok and result.iterations > 0 and result.points > 1000
    assert start[0] > 0.02 and translation < 5e-4, (start, translation)
    assert rotation < 0.03, rotation


def test_direct_alignment_ignores_a_brightness_offset_between_the_views(align_direct):
    T_motion = se3_exp(MOTION)
    eye = torch.eye(4, dtype=torch.float64)
    plain = align_direct(*_pyramids(eye, T_motion), eye, iterations=15, alpha_color=0.9)
    brighter = align_direct(*_pyramids(eye, T_motion, brightness=0.08), eye, iterations=15, alpha_color=0.9)
    assert _error(brighter.T, T_motion)[0] < 1e-3
    assert _error(brighter.T, plain.T)[0] < 5e-4


def test_depth_alone_pins_the_motion_of_a_slanted_plane_only_partly_and_colour_completes_it(align_direct):
    # A plane constrains three of the six degrees of freedom through depth; the texture pins the others.
    T_motion = se3_exp(MOTION)
    eye = torch.eye(4, dtype=torch.float64)
    depth_only = align_direct(*_pyramids(eye, T_motion), eye, iterations=15, alpha_color=0.0)
    both = align_direct(*_pyramids(eye, T_motion), eye, iterations=15, alpha_color=0.5)
    assert _error(both.T, T_motion)[0] < 0.1 * _error(depth_only.T, T_motion)[0]


def test_an_alignment_without_enough_points_keeps_the_initial_motion(align_direct):
    eye = torch.eye(4, dtype=torch.float64)
    references, targets = _pyramids(eye, se3_exp(MOTION))
    empty = [direct_reference(torch.zeros(4, 4, 3), torch.zeros(4, 4), torch.zeros(4, 4, dtype=torch.bool), K)
             for _ in references]
    start = se3_exp(0.5 * MOTION)
    result = align_direct(empty, targets, start, iterations=10, alpha_color=0.5)
    assert not result.ok and result.iterations == 0
    assert torch.equal(result.T, start)
    with pytest.raises(ValueError, match="levels"):
        align_direct(references[:1], targets, eye, iterations=10, alpha_color=0.5)


def _noisy_pyramids(seed: int):
    """The plane's pyramids with per-pixel noise, depth holes and a brightness offset: residuals whose medians,
    Huber weights and step halvings all take part."""
    generator = torch.Generator().manual_seed(seed)
    eye = torch.eye(4, dtype=torch.float64)
    references, targets = _pyramids(eye, se3_exp(MOTION), levels=3, brightness=0.03)
    noisy = []
    for target in targets:
        channels = target.channels.clone()
        channels[0, 0] += 0.02 * torch.randn(channels.shape[2:], generator=generator)
        holes = torch.rand(channels.shape[2:], generator=generator) < 0.1
        channels[0, 3][holes] = 0.0
        channels[0, 6][holes] = 0.0
        noisy.append(type(target)(channels=channels, K=target.K))
    return references, noisy


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("alpha_color", [0.5, 0.8])  # depth alone leaves a plane's motion free (see below)
@pytest.mark.parametrize("depth_noise_power", [0.0, 2.0])
def test_the_compiled_alignment_equals_the_reference_to_rounding(seed, alpha_color, depth_noise_power):
    if not cpu_backend.is_available():
        pytest.skip(f"the compiled CPU library is not available: {cpu_backend.unavailable_reason()}")
    references, targets = _noisy_pyramids(seed)
    start = se3_exp(0.3 * MOTION)
    options = dict(iterations=8, alpha_color=alpha_color, depth_noise_power=depth_noise_power)
    reference = reference_align_direct(references, targets, start, **options)
    compiled = cpu_backend.align_direct(references, targets, start, **options)
    assert compiled.ok and reference.ok
    assert compiled.iterations == reference.iterations
    assert abs(compiled.points - reference.points) <= 0.001 * reference.points
    translation, rotation = _error(compiled.T, reference.T)
    assert translation < 2e-5 and rotation < 1e-3, (translation, rotation)  # metres, degrees


def test_the_compiled_alignment_gives_the_same_bits_whatever_the_thread_count():
    if not cpu_backend.is_available():
        pytest.skip(f"the compiled CPU library is not available: {cpu_backend.unavailable_reason()}")
    references, targets = _noisy_pyramids(2)
    assert references[-1].points.shape[0] >= 4096  # the finest level runs in parallel (direct_align.h, PARALLEL_MIN)
    threads = torch.get_num_threads()
    try:
        results = {}
        for count in (1, 2, 3):
            torch.set_num_threads(count)
            runs = [cpu_backend.align_direct(references, targets, torch.eye(4, dtype=torch.float64), iterations=8,
                                             alpha_color=0.8) for _ in range(3)]
            assert all(torch.equal(run.T, runs[0].T) for run in runs)
            results[count] = runs[0].T
        assert torch.equal(results[1], results[2]) and torch.equal(results[1], results[3])
    finally:
        torch.set_num_threads(threads)


def test_the_compiled_alignment_keeps_a_non_finite_start_and_reports_it():
    if not cpu_backend.is_available():
        pytest.skip(f"the compiled CPU library is not available: {cpu_backend.unavailable_reason()}")
    references, targets = _pyramids(torch.eye(4, dtype=torch.float64), se3_exp(MOTION))
    start = torch.full((4, 4), float("nan"), dtype=torch.float64)
    result = cpu_backend.align_direct(references, targets, start, iterations=5, alpha_color=0.5)
    assert not result.ok and result.iterations == 0 and torch.isnan(result.T).all()


def test_target_depth_is_unusable_across_holes_and_jumps():
    depth = torch.full((12, 12), 2.0)
    depth[:, 6:] = 3.0  # a jump of 1 m between columns 5 and 6
    depth[2, 2] = 0.0  # a hole
    target = direct_target(torch.full((12, 12, 3), 0.5), depth, K)
    usable = target.channels[0, 6]
    assert usable[4, 3] == 1 and usable[4, 9] == 1
    assert usable[4, 5] == 0 and usable[4, 6] == 0  # their central differences cross the jump
    assert usable[2, 2] == 0 and usable[2, 3] == 0 and usable[1, 2] == 0  # the hole and its neighbours
    assert usable[0].sum() == 0 and usable[:, 0].sum() == 0  # no central difference on the border


def test_pyramid_scales_are_coarse_to_fine_halves():
    assert pyramid_scales(1) == [1.0]
    assert pyramid_scales(3) == [0.25, 0.5, 1.0]
    with pytest.raises(ValueError):
        pyramid_scales(0)
