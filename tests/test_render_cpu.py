"""The compiled CPU backend (mipslam/render/cpu): equal to the torch reference, robust, deterministic,
portable build (baseline and AVX2/FMA libraries chosen at run time), loading without compiling, and a clean
fallback when the library is missing or stale."""
from __future__ import annotations

import logging
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mipslam.errors import BackendUnavailableError
from mipslam.render import rasterize, rasterize_pose_only
from mipslam.render import cpu as cpu_backend
from mipslam.geometry.se3 import se3_exp
from test_render_extremes import extreme_scene

ROOT = Path(__file__).resolve().parents[1]


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


@pytest.mark.parametrize("mode", ["mip", "eaa", "exact"])
def test_pose_only_render_without_autograd_is_bit_equal_to_autograd(ext, mode):
    """rasterize_pose_only (tracking's compiled step) against rasterize + autograd: the same images and viewmat
    gradient, bit for bit, for any upstream gradient images."""
    width, height, focal = 40, 30, 36.0
    viewmat, K = camera(width, height, focal)
    scene = mixed_scene(120, width, height, focal, seed=12)
    generator = torch.Generator().manual_seed(13)
    grad_color, grad_depth = torch.randn(height, width, 3, generator=generator), torch.randn(height, width,
                                                                                               generator=generator)
    view = viewmat.clone().requires_grad_(True)
    out = rasterize(*scene, view, K, width, height, mode=mode, backend="cpu", pose_only=True)
    ((out.color * grad_color).sum() + (out.depth * grad_depth).sum()).backward()
    render = rasterize_pose_only(*scene, viewmat, K, width, height, mode=mode, backend="cpu")
    for ours, theirs in ((render.color, out.color), (render.depth, out.depth), (render.alpha, out.alpha)):
        assert torch.equal(ours, theirs.detach())
    assert torch.equal(render.viewmat_gradient(grad_color, grad_depth), view.grad)


def test_pose_only_render_without_autograd_declines_what_only_autograd_renders(ext):
    width, height, focal = 16, 12, 14.0
    viewmat, K = camera(width, height, focal)
    scene = mixed_scene(10, width, height, focal, seed=14)
    assert rasterize_pose_only(*scene, viewmat, K, width, height, backend="torch") is None
    assert rasterize_pose_only(*scene, viewmat, K.clone().requires_grad_(True), width, height) is None
    assert rasterize_pose_only(*(t.double() for t in scene), viewmat.double(), K.double(), width, height) is None
    assert rasterize_pose_only(*scene, viewmat, K, width, height, backend="cpu") is not None


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


# --- build: portability, vectorisation, loading, fallback --------------------------------------------
from mipslam.render.cpu import build as cpu_build, library as cpu_library  # noqa: E402


def test_build_flags_are_portable():
    """Never -march=native: the avx2 library only adds AVX2 and FMA, and only the avx2 library does."""
    for isa in cpu_build.isas():
        flags = cpu_build.compile_command(isa, Path("out.so"))
        assert not any(f.startswith("-march") or f == "-mtune=native" for f in flags
                       if f not in os.environ.get("MIPSLAM_CPU_CFLAGS", "").split())
        assert ("-mavx2" in flags and "-mfma" in flags) == (isa == "avx2")
        assert "-ffast-math" not in flags  # the kernels rely on IEEE comparisons and the exp rounding trick
    assert cpu_build.isas()[0] == "baseline"


def built_libraries():
    """The libraries of this platform that are built and current (skip when none is)."""
    isas = [isa for isa in cpu_build.isas() if cpu_build.is_current(isa)]
    if not isas:
        pytest.skip("the C++ rasterizer is not built here (python -m mipslam.render.cpu.build)")
    return isas


def test_the_libraries_are_built_and_current_where_a_compiler_exists():
    """./scripts/setup (or pip install) built the libraries of this platform from these sources; without
    this, every test below would skip and the pipeline would silently render with torch."""
    if shutil.which(cpu_build.compiler()[0]) is None:
        pytest.skip("no C++ compiler here: the torch backend is used")
    stale = [cpu_build.library_path(isa).name for isa in cpu_build.isas() if not cpu_build.is_current(isa)]
    assert not stale, f"missing or stale: {stale}; run python -m mipslam.render.cpu.build"


@pytest.mark.parametrize("isa", ["baseline", "avx2"])
def test_kernels_are_vectorised_and_call_no_libm(isa):
    """The tile kernels are SIMD code (ymm registers and packed FMAs in the avx2 library, xmm in the
    baseline one) and evaluate exp/erf inline."""
    if isa not in built_libraries():
        pytest.skip(f"no current {isa} library on this platform")
    objdump = shutil.which("objdump")
    if objdump is None:
        pytest.skip("objdump (binutils) is not installed")
    path = cpu_build.library_path(isa)
    disassembly = subprocess.run([objdump, "-d", "--no-show-raw-insn", "-C", str(path)], capture_output=True,
                                 text=True, check=True, timeout=120).stdout
    kernels = re.split(r"\n(?=[0-9a-f]+ <)", disassembly)
    tile_kernels = [k for k in kernels if re.match(r"[0-9a-f]+ <[^>]*(forward|backward)_tile", k)]
    assert len(tile_kernels) >= 6
    for body in tile_kernels:
        assert not re.search(r"call\s+\S+\s+<[^>]*(exp|erf)", body), "a tile kernel calls libm exp/erf"
        if isa == "avx2":
            assert "%ymm" in body and re.search(r"\tvfmadd\S*ps\s", body), "no AVX2 FMA in a tile kernel"
        else:
            assert "%ymm" not in body and re.search(r"\tmulps\s", body)
            assert not re.search(r"\tv(fmadd|mulps)", body), "VEX code in the baseline library"


def test_the_loaded_library_matches_this_cpu(ext):
    assert ext.isa in cpu_build.isas()
    if ext.isa == "avx2":
        assert ext.cpu_supports_avx2_fma() and "avx2 fma" in ext.build_info()
    elif "avx2" in cpu_build.isas() and cpu_build.is_current("avx2"):
        assert not ext.cpu_supports_avx2_fma() or \
            os.environ.get("MIPSLAM_CPU_ISA", "").strip().lower() == "baseline"


def test_baseline_build_equals_the_torch_reference(ext):
    """The portable library (what a CPU without AVX2/FMA runs) against the torch reference, and against the
    library this CPU runs."""
    baseline = cpu_library.load_library("baseline")
    assert "avx2" not in baseline.build_info()
    width, height, focal = 32, 24, 30.0
    viewmat, K = camera(width, height, focal)
    scene = mixed_scene(100, width, height, focal, seed=1)
    with cpu_library.using(baseline):
        for mode, options in (("eaa", {}), ("mip", {"filter_3d_scale": 0.2})):
            _, out_base = assert_backends_agree(scene, viewmat, K, width, height, mode, **options)
            assert cpu_backend.load_extension() is baseline
    out = rasterize(*scene, viewmat, K, width, height, mode="mip", backend="cpu", filter_3d_scale=0.2)
    torch.testing.assert_close(out.color, out_base.color, rtol=0, atol=1e-5)


def test_loading_never_compiles_and_takes_well_under_a_second(ext, tmp_path):
    """A fresh process loads the built library without a compiler or ninja on PATH (nothing is compiled at
    run time), in well under a second, whatever environment it runs in."""
    code = ("import time, torch\n"
            "from mipslam.render import cpu\n"
            "start = time.perf_counter(); library = cpu.load_extension(); took = time.perf_counter() - start\n"
            "print(library.isa, took)\n")
    env = {"PATH": str(tmp_path), "CXX": "/nonexistent/c++", "HOME": str(tmp_path), "PYTHONPATH": str(ROOT),
           "XDG_CACHE_HOME": str(tmp_path / "cache")}
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300,
                            check=False)
    assert result.returncode == 0, result.stderr[-2000:]
    isa, took = result.stdout.split()
    assert isa == ext.isa
    assert float(took) < 1.0, f"loading the library took {float(took):.2f} s"
    assert not (tmp_path / "cache").exists()


@pytest.fixture
def fresh_loader(monkeypatch):
    """Let a test change how the library is found; the loaded library is restored afterwards."""
    saved = dict(cpu_library._state)
    cpu_library._reset_for_tests()
    yield monkeypatch
    cpu_library._state.clear()
    cpu_library._state.update(saved)


def test_missing_library_warns_once_and_falls_back_to_torch(fresh_loader, tmp_path, caplog):
    fresh_loader.setattr(cpu_library, "LIBRARY_DIR", tmp_path)  # an install without the compiled library
    width, height, focal = 16, 12, 14.0
    viewmat, K = camera(width, height, focal)
    scene = mixed_scene(10, width, height, focal)
    with caplog.at_level(logging.WARNING, logger="mipslam.render.cpu"):
        assert not cpu_backend.is_available()
        assert rasterize(*scene, viewmat, K, width, height, backend="auto").backend == "torch"
        assert rasterize(*scene, viewmat, K, width, height, backend="auto").backend == "torch"
        with pytest.raises(BackendUnavailableError, match="not built .*mipslam.render.cpu.build"):
            rasterize(*scene, viewmat, K, width, height, backend="cpu")
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "torch backend" in warnings[0].getMessage()


def test_a_library_built_from_other_sources_is_refused(fresh_loader, tmp_path):
    """Sources edited after the build: the stale library is not loaded, and the reason says to rebuild."""
    isa = built_libraries()[0]
    for name in cpu_build.SOURCES + cpu_build.HEADERS:
        shutil.copy(cpu_build.SOURCE_DIR / name, tmp_path / name)
    shutil.copy(cpu_build.library_path(isa), cpu_build.library_path(isa, tmp_path))
    assert cpu_library.load_library(isa, tmp_path).isa == isa
    with open(tmp_path / "footprint_simd.h", "a") as header:
        header.write("\n// edited\n")
    assert cpu_build.embedded_hash(cpu_build.library_path(isa, tmp_path)) != cpu_build.source_hash(isa, tmp_path)
    with pytest.raises(BackendUnavailableError, match="other sources.*mipslam.render.cpu.build"):
        cpu_library.load_library(isa, tmp_path)


def test_missing_compiler_is_reported_by_the_build(monkeypatch, tmp_path):
    monkeypatch.setenv("CXX", "/nonexistent/c++")
    with pytest.raises(cpu_build.BuildError, match="cannot run the C\\+\\+ compiler"):
        cpu_build.compile_library("baseline", tmp_path / "lib.so")
    assert list(tmp_path.iterdir()) == []  # no partial file left behind


def test_disabled_by_environment(fresh_loader):
    fresh_loader.setenv("MIPSLAM_CPU_BACKEND", "0")
    assert not cpu_backend.is_available()
    assert "MIPSLAM_CPU_BACKEND" in cpu_backend.unavailable_reason()


def test_source_hash_follows_sources_and_flags(tmp_path):
    for name in cpu_build.SOURCES + cpu_build.HEADERS:
        shutil.copy(cpu_build.SOURCE_DIR / name, tmp_path / name)
    base = cpu_build.source_hash("baseline", tmp_path)
    assert base == cpu_build.source_hash("baseline") and len(base) == 16
    assert cpu_build.source_hash("avx2", tmp_path) != base
    (tmp_path / "raster_ext.cpp").write_text((tmp_path / "raster_ext.cpp").read_text() + "\n")
    assert cpu_build.source_hash("baseline", tmp_path) != base


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
    assert not isinstance(cpu_backend.load_extension(), cpu_library._TimedExtension)
