"""The compiled CPU backend (mipslam/render/cpu): equal to the torch reference, robust, deterministic,
portable build and a clean fallback when it cannot be built (issue 3, "Backends")."""
from __future__ import annotations

import logging
import math
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from mipslam.errors import BackendUnavailableError
from mipslam.render import rasterize
from mipslam.render import cpu as cpu_backend
from mipslam.geometry.se3 import se3_exp
from test_render_extremes import extreme_scene


@pytest.fixture(scope="module")
def ext():
    if not cpu_backend.is_available():
        pytest.skip(f"the cpu backend cannot be built here: {cpu_backend.unavailable_reason()}")
    return cpu_backend.load_extension()


def camera(width, height, focal, dtype=torch.float32):
    K = torch.tensor([[focal, 0.0, (width - 1) / 2 + 0.3], [0.0, focal * 1.1, (height - 1) / 2 - 0.2],
                      [0.0, 0.0, 1.0]], dtype=dtype)
    xi = torch.tensor([0.02, -0.03, 0.05, 0.04, -0.02, 0.03], dtype=torch.float64)
    return se3_exp(xi).to(dtype), K  # a general T_cw, so every viewmat entry matters


def mixed_scene(n, width, height, focal, seed=0):
    """Gaussians in front of :func:`camera`: sub-pixel (sigma 0.05-0.5 px), pixel-sized to several
    pixels, and elongated (one axis 10-30x), with random rotations, opacities and colours."""
    g = torch.Generator().manual_seed(seed)
    z = 1.5 + 1.5 * torch.rand(n, generator=g)
    u = (torch.rand(n, generator=g) * 1.2 - 0.1) * width
    v = (torch.rand(n, generator=g) * 1.2 - 0.1) * height
    means = torch.stack([(u - width / 2) * z / focal, (v - height / 2) * z / focal, z], -1)
    kind = torch.rand(n, generator=g)
    sigma_px = torch.where(kind < 0.35, 0.05 + 0.45 * torch.rand(n, generator=g),
                           0.7 + 3.0 * torch.rand(n, generator=g))
    scales = (sigma_px * z / focal)[:, None] * (0.6 + 0.8 * torch.rand(n, 3, generator=g))
    elongated = kind > 0.8
    scales[elongated, 0] *= 10 + 20 * torch.rand(int(elongated.sum()), generator=g)
    quats = torch.randn(n, 4, generator=g)
    opacities = 0.05 + 0.93 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return [means, quats, scales, opacities, colors]


def render_with_grads(scene, viewmat, K, width, height, backend, mode, **options):
    inputs = [t.clone().requires_grad_() for t in scene] + [viewmat.clone().requires_grad_()]
    out = rasterize(*inputs, K, width, height, mode=mode, backend=backend, **options)
    g = torch.Generator().manual_seed(7)
    loss = (out.color * torch.rand(out.color.shape, generator=g)).sum() \
        + (out.depth * torch.randn(out.depth.shape, generator=g)).sum() \
        + (out.alpha * torch.randn(out.alpha.shape, generator=g)).sum()
    loss.backward()
    return out, [t.grad for t in inputs]


def cosine(a, b):
    return float(torch.nn.functional.cosine_similarity(a.flatten().double(), b.flatten().double(), dim=0))


INPUT_NAMES = ("means", "quats", "scales", "opacities", "colors", "viewmat")


def assert_backends_agree(scene, viewmat, K, width, height, mode, **options):
    out_t, grads_t = render_with_grads(scene, viewmat, K, width, height, "torch", mode, **options)
    out_c, grads_c = render_with_grads(scene, viewmat, K, width, height, "cpu", mode, **options)
    assert out_c.backend == "cpu" and out_t.backend == "torch"
    assert out_t.alpha.max() > 0.5, "the scene should cover the image"
    for name in ("color", "depth", "alpha"):
        diff = (getattr(out_c, name) - getattr(out_t, name)).abs().max().item()
        assert diff <= 1e-4, f"{mode}: {name} differs by {diff}"
    for name, gt, gc in zip(INPUT_NAMES, grads_t, grads_c):
        assert gc is not None and torch.isfinite(gc).all(), f"{mode}: gradient of {name} missing or not finite"
        assert gt.abs().max() > 0, f"{mode}: the reference gradient of {name} is zero (test is vacuous)"
        assert cosine(gt, gc) >= 0.999, f"{mode}: gradient of {name} has cosine {cosine(gt, gc):.6f}"
    return out_t, out_c


# --- the SIMD maths --------------------------------------------------------------------------------
def test_vector_exp_and_erf_are_accurate(ext):
    x = torch.linspace(-80.0, 80.0, 200_001)
    rel = ((ext.vector_math(x, 0).double() - torch.exp(x.double())) / torch.exp(x.double())).abs().max().item()
    assert rel < 5e-7
    x = torch.linspace(-6.0, 6.0, 120_001)
    err = (ext.vector_math(x, 1).double() - torch.erf(x.double())).abs()
    assert err.max().item() < 7e-7  # 1e-4 is the images' tolerance; the rounding near 0 is the largest part
    assert err[x.abs() >= 0.5].max().item() < 3e-7
    erf = ext.vector_math(torch.tensor([0.0, -0.0, 1e-6, -1e-6, 3.0, -3.0]), 1)
    assert erf[0] == 0 and erf[1] == 0 and erf[2] > 0 and erf[3] == -erf[2] and erf[4] == -erf[5]
    assert torch.isfinite(ext.vector_math(torch.tensor([-1e30, -1e4, 1e4, 1e30]), 0)).all()  # clamped


# --- equality with the torch reference -------------------------------------------------------------
CASES = [
    ("point", {}),
    ("mip", {}),
    ("ewa", {}),
    ("eaa", {}),
    ("eaa", {"eaa_eta": 2.0, "eaa_tau": 0.25, "eaa_max_nodes": 10, "eaa_single_node_sigma": 0.5}),
    ("point", {"filter_3d_scale": 0.2}),
    ("eaa", {"filter_3d_scale": 0.2, "eaa_eta": 1.0}),
]


@pytest.mark.parametrize("mode,options", CASES, ids=[f"{m}-{i}" for i, (m, _) in enumerate(CASES)])
def test_cpu_equals_torch_images_and_gradients(ext, mode, options):
    width, height, focal = 32, 24, 30.0
    viewmat, K = camera(width, height, focal)
    assert_backends_agree(mixed_scene(100, width, height, focal, seed=1), viewmat, K, width, height, mode, **options)


def test_cpu_equals_torch_exact_mode(ext):
    width, height, focal = 16, 12, 14.0
    viewmat, K = camera(width, height, focal)
    assert_backends_agree(mixed_scene(30, width, height, focal, seed=2), viewmat, K, width, height, "exact",
                          exact_order=5)


@pytest.mark.parametrize("channels", [1, 4])
def test_other_channel_counts(ext, channels):
    width, height, focal = 20, 14, 18.0
    viewmat, K = camera(width, height, focal)
    scene = mixed_scene(40, width, height, focal, seed=3)
    scene[4] = torch.rand(40, channels, generator=torch.Generator().manual_seed(4))
    out_t, out_c = assert_backends_agree(scene, viewmat, K, width, height, "point")
    assert out_c.color.shape == (height, width, channels)


def test_unsupported_calls_fall_back_on_auto_and_raise_on_cpu(ext):
    width, height, focal = 16, 12, 14.0
    viewmat, K = camera(width, height, focal, dtype=torch.float64)
    scene = [t.double() for t in mixed_scene(20, width, height, focal)]
    assert rasterize(*scene, viewmat, K, width, height, backend="auto").backend == "torch"
    with pytest.raises(BackendUnavailableError, match="float32"):
        rasterize(*scene, viewmat, K, width, height, backend="cpu")
    scene32 = [t.float() for t in scene]
    scene32[4] = torch.rand(20, 2)
    with pytest.raises(BackendUnavailableError, match="colour channels"):
        rasterize(*scene32, viewmat.float(), K.float(), width, height, backend="cpu")
    assert rasterize(*[t.float() for t in scene], viewmat.float(), K.float(), width, height).backend == "cpu"


def test_masked_loss_gradients_match(ext):
    """Pixels without incoming gradient are skipped by the cpu backward; the result must not change."""
    width, height, focal = 24, 18, 22.0
    viewmat, K = camera(width, height, focal)
    scene = mixed_scene(60, width, height, focal, seed=8)
    mask = torch.rand(height, width, generator=torch.Generator().manual_seed(9)) < 0.5
    grads = {}
    for backend in ("torch", "cpu"):
        inputs = [t.clone().requires_grad_() for t in scene] + [viewmat.clone().requires_grad_()]
        out = rasterize(*inputs, K, width, height, mode="eaa", backend=backend)
        ((out.color.sum(-1) + out.depth) * mask).sum().backward()
        grads[backend] = [t.grad for t in inputs]
    for name, gt, gc in zip(INPUT_NAMES, grads["torch"], grads["cpu"]):
        assert cosine(gt, gc) >= 0.999, f"gradient of {name} has cosine {cosine(gt, gc):.6f}"


# --- pose-only backward ----------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["point", "mip", "eaa"])
def test_pose_only_gives_the_same_pose_gradient(ext, mode):
    width, height, focal = 24, 18, 22.0
    viewmat, K = camera(width, height, focal)
    scene = mixed_scene(60, width, height, focal, seed=5)
    _, grads_full = render_with_grads(scene, viewmat, K, width, height, "cpu", mode)
    _, grads_pose = render_with_grads(scene, viewmat, K, width, height, "cpu", mode, pose_only=True)
    _, grads_torch = render_with_grads(scene, viewmat, K, width, height, "torch", mode, pose_only=True)
    assert all(g is None for g in grads_pose[:5])
    assert torch.allclose(grads_pose[5], grads_full[5], rtol=1e-5, atol=1e-6)
    assert cosine(grads_pose[5], grads_torch[5]) >= 0.999


# --- numerical extremes: tests/test_render_extremes.py runs them on every backend ------------------


# --- determinism -----------------------------------------------------------------------------------
def test_backward_is_deterministic_and_independent_of_the_thread_count(ext):
    width, height, focal = 48, 40, 40.0
    viewmat, K = camera(width, height, focal)
    scene = mixed_scene(300, width, height, focal, seed=6)
    threads = torch.get_num_threads()
    try:
        results = []
        for n_threads in (threads, threads, 1, 3):
            torch.set_num_threads(n_threads)
            results.append(render_with_grads(scene, viewmat, K, width, height, "cpu", "eaa"))
    finally:
        torch.set_num_threads(threads)
    (out0, grads0) = results[0]
    for out, grads in results[1:]:
        assert torch.equal(out.color, out0.color)
        for g, g0 in zip(grads, grads0):
            assert torch.equal(g, g0)


# --- build: portability, vectorisation, fallback ---------------------------------------------------
def test_build_flags_are_portable():
    cflags, _ = cpu_backend.build_flags()
    assert not any(f.startswith("-march") or f.startswith("-mtune=native") for f in cflags
                   if f not in cpu_backend.os.environ.get("MIPSLAM_CPU_CFLAGS", "").split())
    assert ("-mavx2" in cflags) == cpu_backend._cpu_has_avx2_fma()
    assert "-ffast-math" not in cflags  # the kernels rely on IEEE comparisons and the exp rounding trick


def test_kernels_are_vectorised_and_call_no_libm(ext):
    objdump = shutil.which("objdump")
    if objdump is None:
        pytest.skip("objdump (binutils) is not installed")
    info = ext.build_info()
    disassembly = subprocess.run([objdump, "-d", "--no-show-raw-insn", "-C", ext.__file__], capture_output=True,
                                 text=True, check=True, timeout=120).stdout
    kernels = re.split(r"\n(?=[0-9a-f]+ <)", disassembly)
    tile_kernels = [k for k in kernels if re.match(r"[0-9a-f]+ <[^>]*(forward|backward)_tile", k)]
    assert len(tile_kernels) >= 6
    register = "%ymm" if "avx2" in info else "%xmm"
    for body in tile_kernels:
        assert register in body
        assert not re.search(r"call\s+\S+\s+<[^>]*(exp|erf)", body), "a tile kernel calls libm exp/erf"
        # packed single-precision FMAs/multiplies: the per-pixel maths (exp polynomial included) is SIMD
        assert re.search(r"\tv?(vfmadd\S*ps|mulps|vmulps)\s", body)


@pytest.fixture
def fresh_loader(monkeypatch):
    """Let a test fail the build; the real extension is restored afterwards."""
    saved = dict(cpu_backend._state)
    cpu_backend._reset_for_tests()
    yield monkeypatch
    cpu_backend._state.clear()
    cpu_backend._state.update(saved)


def test_failed_build_warns_once_and_falls_back_to_torch(fresh_loader, caplog):
    def failing_build():
        raise RuntimeError("Error building extension 'mipslam_raster': g++: fatal error")

    fresh_loader.setattr(cpu_backend, "_build", failing_build)
    width, height, focal = 16, 12, 14.0
    viewmat, K = camera(width, height, focal)
    scene = mixed_scene(10, width, height, focal)
    with caplog.at_level(logging.WARNING, logger="mipslam.render.cpu"):
        assert not cpu_backend.is_available()
        assert rasterize(*scene, viewmat, K, width, height, backend="auto").backend == "torch"
        assert rasterize(*scene, viewmat, K, width, height, backend="auto").backend == "torch"
        with pytest.raises(BackendUnavailableError, match="g\\+\\+: fatal error"):
            rasterize(*scene, viewmat, K, width, height, backend="cpu")
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "torch backend" in warnings[0].getMessage()


def test_missing_compiler_is_reported(fresh_loader):
    fresh_loader.setenv("CXX", "/nonexistent/c++")
    assert not cpu_backend.is_available()
    assert "no C++ compiler" in cpu_backend.unavailable_reason()


def test_disabled_by_environment(fresh_loader):
    fresh_loader.setenv("MIPSLAM_CPU_BACKEND", "0")
    assert not cpu_backend.is_available()
    assert "MIPSLAM_CPU_BACKEND" in cpu_backend.unavailable_reason()


def test_cache_key_follows_sources_and_flags(tmp_path):
    compiler = cpu_backend._compiler() or "c++"
    base = cpu_backend._build_key(["-O3"], [], compiler)
    assert cpu_backend._build_key(["-O3", "-mavx2"], [], compiler) != base
    assert cpu_backend._build_key(["-O3"], [], compiler) == base
    assert Path(cpu_backend.cache_root()).name == "torch_extensions"
    assert math.isfinite(len(base)) and len(base) == 16


# --- fused projection (projection.h) against the torch reference ------------------------------------
from mipslam.render import RenderOptions  # noqa: E402

PROJECTION_CASES = [
    ("point", {}),
    ("mip", {}),
    ("ewa", {}),
    ("eaa", {"eaa_max_nodes": 6, "eaa_gamma": 1.0}),
    ("exact", {}),
    ("mip", {"filter_3d_scale": 0.2}),
    ("eaa", {"filter_3d_scale": 0.2, "eaa_max_nodes": 3}),
    ("point", {"filter_3d_scale": 0.2, "max_sampling_rate": "given"}),
]
PARAM_NAMES = ("means", "quats", "scales", "opacities", "viewmat")


def projection_inputs(scene, viewmat, dtype, pose_only=False):
    """(means, quats, scales, opacities, colors, viewmat) as fresh leaves of ``dtype``."""
    params = [t.to(dtype).clone().requires_grad_(not pose_only) for t in scene[:4]]
    return params + [scene[4].to(dtype), viewmat.to(dtype).clone().requires_grad_()]


def project_both(scene, viewmat, K, width, height, mode, options, dtype):
    """The fused projection and the torch reference on the same inputs, each backpropagated from the same
    random weighting of means2d, depths, cov and opacities. Returns (fused, reference, grads_f, grads_r)."""
    results, grads = [], []
    for project in (cpu_backend.project_footprints, cpu_backend.reference_footprints):
        inputs = projection_inputs(scene, viewmat, dtype)
        out = project(*inputs[:5], inputs[5], K.to(dtype), width, height, mode=mode, options=options)
        g = torch.Generator().manual_seed(11)
        loss = sum((getattr(out, name) * torch.randn(getattr(out, name).shape, generator=g, dtype=dtype)).sum()
                   for name in ("means2d", "depths", "cov", "opacities"))
        loss.backward()
        results.append(out)
        grads.append([inputs[i].grad for i in (0, 1, 2, 3, 5)])
    return results[0], results[1], grads[0], grads[1]


def assert_projection_close(fused, ref, rtol):
    assert torch.equal(fused.visible, ref.visible)
    assert fused.n_visible == ref.n_visible == int(ref.visible.sum())
    assert torch.equal(fused.node_counts, ref.node_counts)
    torch.testing.assert_close(fused.depths, ref.depths, rtol=rtol, atol=0.0)
    torch.testing.assert_close(fused.means2d, ref.means2d, rtol=rtol, atol=rtol * 100)  # px; 100 px ~ image
    torch.testing.assert_close(fused.opacities, ref.opacities, rtol=rtol, atol=rtol * 1e-2)
    torch.testing.assert_close(fused.radii, ref.radii, rtol=rtol, atol=0.0)
    # the covariance relative to its own size: xx, yy to the larger variance, xy to sqrt(xx yy), det to xx yy
    xx, xy, yy, det = ref.cov.detach().unbind(-1)
    scale = torch.stack([torch.maximum(xx, yy), torch.sqrt(xx * yy), torch.maximum(xx, yy), xx * yy], -1)
    err = ((fused.cov.detach() - ref.cov.detach()).abs() / scale).max().item()
    assert err <= rtol, f"covariance differs by {err:.2e} of its size"


@pytest.mark.parametrize("mode,options", PROJECTION_CASES, ids=[f"{m}-{i}" for i, (m, _) in enumerate(PROJECTION_CASES)])
def test_fused_projection_equals_the_torch_reference(ext, mode, options):
    """Values (rtol 1e-5, covariance relative to its size) and the gradient of every input (1e-5 of the
    largest entry) on random Gaussians (sub-pixel, large, elongated, partly off screen) and the extreme rows
    (NaN/Inf, behind the camera, near plane, depth 1e6, scales 1e-8 and 1e3, anisotropy 1e6, opacity 0/1,
    zero quaternion)."""
    width, height, focal = 32, 24, 30.0
    viewmat, K = camera(width, height, focal)
    scenes = [(mixed_scene(200, width, height, focal, seed=21), viewmat, K, width, height)]
    Ke = torch.tensor([[10.0, 0.0, 7.5], [0.0, 10.0, 5.5], [0.0, 0.0, 1.0]])
    scenes.append((extreme_scene(), torch.eye(4), Ke, 16, 12))
    for scene, view, Kc, w, h in scenes:
        opts = dict(options)
        if opts.get("max_sampling_rate") == "given":
            opts["max_sampling_rate"] = 10.0 + 50.0 * torch.rand(scene[0].shape[0],
                                                                 generator=torch.Generator().manual_seed(2))
        fused, ref, grads_f, grads_r = project_both(scene, view, Kc, w, h, mode, RenderOptions(**opts),
                                                    torch.float32)
        assert ref.visible.any() and not ref.visible.all()
        assert_projection_close(fused, ref, rtol=1e-5)
        for name, gf, gr in zip(PARAM_NAMES, grads_f, grads_r):
            assert torch.isfinite(gf).all(), f"gradient of {name} not finite"
            assert gr.abs().max() > 0, f"the reference gradient of {name} is zero (test is vacuous)"
            torch.testing.assert_close(gf, gr, rtol=1e-4, atol=1e-5 * gr.abs().max().item(), msg=name)


@pytest.mark.parametrize("mode,options", PROJECTION_CASES, ids=[f"{m}-{i}" for i, (m, _) in enumerate(PROJECTION_CASES)])
def test_fused_projection_in_float64_equals_the_reference_to_rounding(ext, mode, options):
    width, height, focal = 32, 24, 30.0
    viewmat, K = camera(width, height, focal, dtype=torch.float64)
    scene = mixed_scene(120, width, height, focal, seed=22)
    opts = dict(options)
    if opts.get("max_sampling_rate") == "given":
        opts["max_sampling_rate"] = 10.0 + 50.0 * torch.rand(120, generator=torch.Generator().manual_seed(3),
                                                             dtype=torch.float64)
    fused, ref, grads_f, grads_r = project_both(scene, viewmat, K, width, height, mode, RenderOptions(**opts),
                                                torch.float64)
    assert_projection_close(fused, ref, rtol=1e-12)
    for name, gf, gr in zip(PARAM_NAMES, grads_f, grads_r):
        torch.testing.assert_close(gf, gr, rtol=1e-10, atol=1e-12 * gr.abs().max().item(), msg=name)


@pytest.mark.parametrize("mode,options", [("point", {}), ("mip", {}), ("eaa", {"filter_3d_scale": 0.2}),
                                          ("ewa", {"filter_3d_scale": 0.2})])
def test_fused_projection_backward_passes_gradcheck(ext, mode, options):
    """The hand-written backward against finite differences (float64), every input including the viewmat."""
    from test_render_gradients import tiny_scene

    means, quats, scales, opacities, colors, viewmat, K = tiny_scene()
    opts = RenderOptions(**options)

    def project(m, q, s, o, v):
        out = cpu_backend.project_footprints(m, q, s, o, colors, v, K, 4, 3, mode=mode, options=opts)
        return out.means2d, out.depths, out.cov, out.opacities

    inputs = tuple(t.clone().requires_grad_() for t in (means, quats, scales, opacities, viewmat))
    assert cpu_backend.project_footprints(*inputs[:4], colors, inputs[4], K, 4, 3, mode=mode,
                                          options=opts).visible.all()
    assert torch.autograd.gradcheck(project, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_fused_projection_pose_only_and_thread_count_determinism(ext):
    """Only the viewmat needing a gradient gives the same viewmat gradient (bit for bit) as the full
    backward; that gradient is a fixed-order reduction, identical for 1, 2 and 3 threads (N is above the
    size from which the projection runs in parallel)."""
    width, height, focal = 64, 48, 60.0
    viewmat, K = camera(width, height, focal)
    scene = mixed_scene(6000, width, height, focal, seed=23)
    opts = RenderOptions(filter_3d_scale=0.2)
    threads = torch.get_num_threads()
    results = []
    try:
        for n_threads, pose_only in ((threads, False), (threads, True), (1, True), (3, True)):
            torch.set_num_threads(n_threads)
            inputs = projection_inputs(scene, viewmat, torch.float32, pose_only=pose_only)
            out = cpu_backend.project_footprints(*inputs[:5], inputs[5], K, width, height, mode="mip", options=opts)
            weights = torch.linspace(-1.0, 1.0, out.cov.numel()).reshape(out.cov.shape)
            ((out.cov * weights).sum() + out.means2d.sum() + out.depths.sum() + out.opacities.sum()).backward()
            assert (inputs[0].grad is None) == pose_only
            results.append(inputs[5].grad)
    finally:
        torch.set_num_threads(threads)
    assert results[0].abs().max() > 0
    for g in results[1:]:
        assert torch.equal(g, results[0])


def test_camera_gradient_uses_the_torch_projection(ext):
    """K (and a differentiable sampling rate) are constants of the fused projection: when they need a
    gradient the cpu backend puts the torch projection in front of its rasterizer, and agrees with torch."""
    width, height, focal = 24, 18, 22.0
    viewmat, K = camera(width, height, focal)
    scene = mixed_scene(60, width, height, focal, seed=24)
    grads = {}
    for backend in ("torch", "cpu"):
        K_leaf = K.clone().requires_grad_()
        out = rasterize(*scene, viewmat, K_leaf, width, height, mode="eaa", backend=backend)
        assert out.backend == backend
        (out.color.sum() + out.alpha.sum()).backward()
        grads[backend] = K_leaf.grad
    assert grads["torch"].abs().max() > 0 and cosine(grads["torch"], grads["cpu"]) >= 0.999


@pytest.mark.parametrize("bad", ["nan_pose", "inf_K", "negative_focal"])
def test_invalid_cameras_raise_render_errors_on_the_cpu_backend(ext, bad):
    from mipslam.errors import RenderError

    width, height, focal = 16, 12, 14.0
    viewmat, K = camera(width, height, focal)
    scene = mixed_scene(10, width, height, focal)
    if bad == "nan_pose":
        viewmat = viewmat.clone()
        viewmat[0, 3] = float("nan")
    elif bad == "inf_K":
        K = K.clone()
        K[0, 2] = float("inf")
    else:
        K = K.clone()
        K[1, 1] = -focal
    with pytest.raises(RenderError, match="finite|focal lengths must be positive"):
        rasterize(*scene, viewmat, K, width, height, backend="cpu")


def test_profile_kernels_times_each_extension_call(ext):
    width, height, focal = 16, 12, 14.0
    viewmat, K = camera(width, height, focal)
    inputs = [t.clone().requires_grad_() for t in mixed_scene(30, width, height, focal)]
    with cpu_backend.profile_kernels() as forward:
        out = rasterize(*inputs, viewmat, K, width, height, backend="cpu")
    with cpu_backend.profile_kernels() as backward:
        out.color.sum().backward()
    assert forward.calls == {"project_forward": 1, "rasterize_forward": 1}
    assert backward.calls == {"rasterize_backward": 1, "project_backward": 1}
    assert forward.total > 0 and backward.total > 0
    assert not isinstance(cpu_backend.load_extension(), cpu_backend._TimedExtension)


@pytest.mark.skipif(sys.platform == "win32", reason="flock is POSIX")
def test_stale_torch_build_lock_of_a_killed_build_is_removed(tmp_path):
    # A process killed during the build leaves torch's plain 'lock' file; without this, every later
    # process would wait on it for ever.
    (tmp_path / "lock").write_text("")
    probe = ("import fcntl, sys; f = open(sys.argv[1], 'a+b')\n"
             "try:\n    fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)\nexcept OSError:\n    sys.exit(3)\n")
    with cpu_backend._exclusive_build(tmp_path):
        assert not (tmp_path / "lock").exists()
        held = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "mipslam-build.flock")], check=False)
        assert held.returncode == 3  # another process cannot build while this one does
    free = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "mipslam-build.flock")], check=False)
    assert free.returncode == 0


def test_the_extension_compiles_a_copy_of_its_sources_that_every_checkout_shares(tmp_path):
    # ninja names sources by path: compiling the checkout's files made two checkouts rebuild each other.
    folder = cpu_backend._copy_sources(tmp_path / "src")
    names = cpu_backend._SOURCES + cpu_backend._HEADERS
    for name in names:
        assert (folder / name).read_bytes() == (cpu_backend._SOURCE_DIR / name).read_bytes()
    stamps = {name: (folder / name).stat().st_mtime_ns for name in names}
    time.sleep(0.01)
    cpu_backend._copy_sources(tmp_path / "src")  # same content: nothing rewritten, ninja sees no change
    assert {name: (folder / name).stat().st_mtime_ns for name in names} == stamps
    (folder / names[0]).write_text("stale")
    cpu_backend._copy_sources(tmp_path / "src")
    assert (folder / names[0]).read_bytes() == (cpu_backend._SOURCE_DIR / names[0]).read_bytes()
    assert not list(folder.glob(".*.partial"))
