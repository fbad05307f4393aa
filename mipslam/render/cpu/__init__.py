"""The compiled CPU backend of the renderer: C++/OpenMP tile rasterizer with a SIMD forward and a
hand-written backward (docs/renderer.md, "CPU backend").

Split as in gsplat: the projection (:func:`mipslam.render.projection.project_gaussians`), the footprint
parameters of each mode (:func:`mipslam.render.footprint.footprint_parameters`) and the EAA node counts
stay in torch, shared with the torch backend line for line, so autograd carries the gradient from the
projected quantities to the 3D parameters and the viewmat. The extension receives, per Gaussian,

    means2d [N, 2] px, cov [N, 4] = (xx, xy, yy, det) px^2 / px^4 (the mode's sampling covariance),
    opacity [N] (the mode's), depth [N] metres, colors [N, C], node_counts [N] int32 (EAA)

and does the per-pixel part: tile binning, depth sort, footprint evaluation (point/mip/ewa as a centre
sample, EAA with its rows, exact Gauss-Legendre) and front-to-back compositing, forward and backward
(:class:`RasterizeProjected`, a ``torch.autograd.Function``).

Build: compiled from source on first use with ``torch.utils.cpp_extension.load`` (ninja), cached under
``$MIPSLAM_CACHE_DIR`` or ``$XDG_CACHE_HOME/mipslam`` or ``~/.cache/mipslam``, in a folder keyed by a hash
of the sources, the compiler flags, the compiler and the torch version. ``-mavx2 -mfma`` are added only
when this CPU has both (checked at run time before compiling); otherwise the x86-64 baseline build is
used, so the cached binary never needs more than the CPU that built it. If the build fails (no compiler,
no ninja, ...) one warning is logged and :func:`is_available` is False: ``backend="auto"`` then uses the
torch backend and ``backend="cpu"`` raises :class:`~mipslam.errors.BackendUnavailableError` with the
reason (:func:`unavailable_reason`). ``MIPSLAM_CPU_BACKEND=0`` disables the backend;
``MIPSLAM_CPU_CFLAGS`` appends compiler flags (e.g. ``-march=native`` for a build that will only ever
run on this machine).
"""
from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import threading
from pathlib import Path

import torch

from mipslam.errors import BackendUnavailableError, RenderError
from mipslam.render import footprint

log = logging.getLogger(__name__)

__all__ = ["is_available", "unavailable_reason", "unsupported_reason", "load_extension", "rasterize",
           "rasterize_projected", "RasterizeProjected", "build_flags", "MODE_IDS", "SUPPORTED_CHANNELS",
           "MAX_ROWS"]

_SOURCE_DIR = Path(__file__).resolve().parent
_SOURCES = ("raster_ext.cpp",)
_HEADERS = ("footprint_simd.h", "simd_math.h")
#: Footprint kernels of the extension: point/mip/ewa are all a centre sample of the mode's covariance.
MODE_IDS = {"point": 0, "mip": 0, "ewa": 0, "eaa": 1, "exact": 2}
#: Colour channel counts the extension is compiled for (template parameter, not a runtime loop bound).
SUPPORTED_CHANNELS = (1, 3, 4)
#: Cap of EAA nodes and of the exact-mode Gauss-Legendre order (MAX_ROWS in footprint_simd.h).
MAX_ROWS = 64

_lock = threading.Lock()
_state: dict = {"module": None, "reason": None, "tried": False}


# ------------------------------------------------------------------------------------------------
# Build and load
# ------------------------------------------------------------------------------------------------
def _cpu_has_avx2_fma() -> bool:
    """True if this CPU runs AVX2 and FMA code (x86-64 only; read from /proc/cpuinfo or torch)."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        try:
            for line in cpuinfo.read_text(errors="replace").splitlines():
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    return "avx2" in flags and "fma" in flags
        except OSError:
            pass
    capability = getattr(getattr(torch.backends, "cpu", None), "get_cpu_capability", lambda: "DEFAULT")()
    return capability in ("AVX2", "AVX512")


def build_flags() -> tuple[list[str], list[str]]:
    """(extra_cflags, extra_ldflags) for this machine: -O3, OpenMP, IEEE-exact maths (no -ffast-math: the
    kernels rely on NaN tests and the exp rounding trick), plus -mavx2 -mfma when this CPU has them.
    Never -march=native: the binary only assumes what the run-time check found."""
    cflags = ["-O3", "-std=c++17", "-fopenmp", "-fno-math-errno", "-fno-trapping-math"]
    if _cpu_has_avx2_fma():
        cflags += ["-mavx2", "-mfma"]
    # Extra flags for experiments or a machine-specific build (part of the cache key).
    cflags += os.environ.get("MIPSLAM_CPU_CFLAGS", "").split()
    return cflags, ["-fopenmp"]


def _compiler() -> str | None:
    name = os.environ.get("CXX", "c++")
    return shutil.which(name)


def _compiler_version(path: str) -> str:
    try:
        result = subprocess.run([path, "--version"], capture_output=True, text=True, timeout=30, check=False)
        return result.stdout.splitlines()[0] if result.stdout else ""
    except (OSError, subprocess.SubprocessError):
        return ""


def cache_root() -> Path:
    """Folder that holds the compiled extensions (one sub-folder per source/flag/torch hash)."""
    override = os.environ.get("MIPSLAM_CACHE_DIR")
    if override:
        return Path(override).expanduser() / "torch_extensions"
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "mipslam" / "torch_extensions"


def _build_key(cflags: list[str], ldflags: list[str], compiler: str) -> str:
    digest = hashlib.sha256()
    for name in _SOURCES + _HEADERS:
        digest.update(name.encode())
        digest.update((_SOURCE_DIR / name).read_bytes())
    for part in (" ".join(cflags), " ".join(ldflags), compiler, _compiler_version(compiler), torch.__version__,
                 platform.python_version(), platform.machine()):
        digest.update(part.encode())
    return digest.hexdigest()[:16]


def _build():
    if os.environ.get("MIPSLAM_CPU_BACKEND", "1").strip().lower() in ("0", "false", "off", "no"):
        raise BackendUnavailableError("the cpu backend is disabled by MIPSLAM_CPU_BACKEND=0")
    compiler = _compiler()
    if compiler is None:
        raise BackendUnavailableError(
            f"no C++ compiler found ('{os.environ.get('CXX', 'c++')}' is not on PATH); install g++ "
            "(e.g. apt-get install g++) or use backend='torch'")
    if shutil.which("ninja") is None:
        try:
            import ninja  # noqa: F401  (the pip package puts the binary next to the interpreter)
        except ImportError as exc:
            raise BackendUnavailableError("ninja is not installed (pip install ninja)") from exc
    from torch.utils import cpp_extension

    cflags, ldflags = build_flags()
    key = _build_key(cflags, ldflags, compiler)
    name = f"mipslam_raster_{key}"
    build_dir = cache_root() / name
    build_dir.mkdir(parents=True, exist_ok=True)
    log.info("loading the mipslam cpu rasterizer from %s (compiled on first use, about 30-60 s)", build_dir)
    return cpp_extension.load(name=name, sources=[str(_SOURCE_DIR / s) for s in _SOURCES],
                              extra_cflags=cflags, extra_ldflags=ldflags, build_directory=str(build_dir),
                              verbose=False)


def load_extension():
    """The compiled extension module (built on first call). Raises BackendUnavailableError with the reason."""
    with _lock:
        if _state["module"] is not None:
            return _state["module"]
        if _state["tried"]:
            raise BackendUnavailableError(f"the cpu backend is not available: {_state['reason']}")
        _state["tried"] = True
        try:
            _state["module"] = _build()
        except BackendUnavailableError as exc:
            _state["reason"] = str(exc)
        except (OSError, RuntimeError, ImportError, subprocess.SubprocessError, ValueError) as exc:
            _state["reason"] = f"building the C++ extension failed: {type(exc).__name__}: {str(exc)[-2000:]}"
        if _state["module"] is None:
            log.warning("mipslam cpu rasterizer unavailable, using the torch backend instead: %s", _state["reason"])
            raise BackendUnavailableError(f"the cpu backend is not available: {_state['reason']}")
        return _state["module"]


def is_available() -> bool:
    """True if the extension is (or could just now be) built and loaded."""
    try:
        load_extension()
    except BackendUnavailableError:
        return False
    return True


def unavailable_reason() -> str | None:
    """Why the extension cannot be used (None when it is available)."""
    return None if is_available() else _state["reason"]


def _reset_for_tests() -> None:
    """Forget the load attempt (tests monkeypatch the build and try again)."""
    with _lock:
        _state.update(module=None, reason=None, tried=False)


def unsupported_reason(means: torch.Tensor, colors: torch.Tensor, mode: str, options) -> str | None:
    """Why this call cannot run on the cpu backend (None if it can): device, dtype, channels, caps."""
    if means.device.type != "cpu":
        return f"the cpu backend needs CPU tensors, got {means.device}"
    if means.dtype != torch.float32:
        return f"the cpu backend computes in float32, got {means.dtype} (use backend='torch' for float64 checks)"
    if colors.dim() != 2 or colors.shape[1] not in SUPPORTED_CHANNELS:
        return f"the cpu backend renders {SUPPORTED_CHANNELS} colour channels, got colors of shape {list(colors.shape)}"
    if mode == "eaa" and int(options.eaa_max_nodes) > MAX_ROWS:
        return f"the cpu backend supports eaa_max_nodes <= {MAX_ROWS}, got {options.eaa_max_nodes}"
    if mode == "exact" and int(options.exact_order) > MAX_ROWS:
        return f"the cpu backend supports exact_order <= {MAX_ROWS}, got {options.exact_order}"
    return None


# ------------------------------------------------------------------------------------------------
# Autograd
# ------------------------------------------------------------------------------------------------
class RasterizeProjected(torch.autograd.Function):
    """Per-pixel part of the renderer in C++: projected Gaussians -> (color, depth, alpha, stats).

    Inputs (float32, contiguous): means2d [N, 2] px, cov [N, 4] (xx, xy, yy, det) of the mode's sampling
    covariance, opacity [N] (the mode's), depth [N] metres, colors [N, C]; node_counts [N] int32; then
    plain settings. Outputs color [H, W, C], depth [H, W], alpha [H, W] and stats [2] int64 (footprint
    lanes evaluated, (tile, Gaussian) pairs). The backward is the extension's hand-written one; it skips
    the colour sums when ``colors`` needs no gradient and the opacity sums when ``opacity`` needs none
    (pose-only tracking).
    """

    @staticmethod
    def forward(ctx, means2d, cov, opacity, depth, colors, node_counts, mode_id: int, width: int, height: int,
                k_sigma: float, eta: float, tau: float, gl_nodes, gl_weights, threads: int):
        ext = load_extension()
        (color, depth_img, alpha_img, order, tile_offsets, isect_ids, pair_offsets, isect_pos, last,
         stats) = ext.rasterize_forward(means2d, cov, opacity, depth, colors, node_counts, mode_id, width, height,
                                        k_sigma, eta, tau, gl_nodes, gl_weights, threads)
        ctx.settings = (mode_id, width, height, k_sigma, eta, tau, threads)
        ctx.save_for_backward(means2d, cov, opacity, depth, colors, node_counts, gl_nodes, gl_weights, order,
                              tile_offsets, isect_ids, pair_offsets, isect_pos, last, color, depth_img, alpha_img)
        ctx.mark_non_differentiable(stats)
        return color, depth_img, alpha_img, stats

    @staticmethod
    def backward(ctx, grad_color, grad_depth, grad_alpha, _grad_stats):
        (means2d, cov, opacity, depth, colors, node_counts, gl_nodes, gl_weights, order, tile_offsets, isect_ids,
         pair_offsets, isect_pos, last, color, depth_img, alpha_img) = ctx.saved_tensors
        mode_id, width, height, k_sigma, eta, tau, threads = ctx.settings

        def dense(grad, like):
            return torch.zeros_like(like) if grad is None else grad.contiguous().to(torch.float32)

        need = ctx.needs_input_grad
        g_means2d, g_cov, g_opacity, g_depth, g_colors = load_extension().rasterize_backward(
            means2d, cov, opacity, depth, colors, node_counts, mode_id, width, height, k_sigma, eta, tau, gl_nodes,
            gl_weights, order, tile_offsets, isect_ids, pair_offsets, isect_pos, last, color, depth_img, alpha_img,
            dense(grad_color, color), dense(grad_depth, depth_img), dense(grad_alpha, alpha_img), bool(need[4]),
            bool(need[2]), threads)
        return (g_means2d if need[0] else None, g_cov if need[1] else None, g_opacity if need[2] else None,
                g_depth if need[3] else None, g_colors if need[4] else None) + (None,) * 10


@dataclasses.dataclass(frozen=True)
class CpuImage:
    """Raw output of :func:`rasterize_projected`.  color [H, W, C], depth [H, W], alpha [H, W]

    ``lanes_evaluated``: footprint evaluations the kernel made (8-pixel row segments x 8), ``pairs``:
    (tile, Gaussian) pairs after binning.
    """

    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    lanes_evaluated: int
    pairs: int


def rasterize_projected(proj, width: int, height: int, settings, **_unused) -> CpuImage:
    """Drop-in for :func:`mipslam.render.rasterize_torch.rasterize_projected` on the compiled backend.

    ``proj``: :class:`~mipslam.render.projection.ProjectedGaussians` (float32, CPU); ``settings``:
    :class:`~mipslam.render.rasterize_torch.FootprintSettings`. Tiling options of the torch backend
    (tile_size, pair_budget, checkpoint) do not apply (the extension uses 16x16 tiles and O(pairs) memory).
    """
    mode = settings.mode
    if mode not in MODE_IDS:
        raise RenderError(f"rasterize (cpu backend): unknown mode '{mode}'")
    cov_xx, cov_xy, cov_yy = proj.cov2d.unbind(-1)
    xx, xy, yy, det, opacity = footprint.footprint_parameters(mode, cov_xx, cov_xy, cov_yy, proj.cov_det,
                                                              proj.opacities)
    if mode == "eaa":
        node_counts = footprint.eaa_node_counts(xx, xy, yy, det, max_nodes=int(settings.max_nodes),
                                                gamma=settings.gamma, point_area=settings.point_area)
    else:
        node_counts = torch.ones_like(opacity, dtype=torch.int64)
    gl_nodes, gl_weights = footprint.gauss_legendre(settings.exact_order if mode == "exact" else 1, torch.float32,
                                                    proj.means2d.device)
    cov = torch.stack([xx, xy, yy, det], -1)
    color, depth, alpha, stats = RasterizeProjected.apply(
        proj.means2d.contiguous(), cov.contiguous(), opacity.contiguous(), proj.depths.contiguous(),
        proj.colors.contiguous(), node_counts.to(torch.int32).contiguous(), MODE_IDS[mode], int(width), int(height),
        float(settings.k_sigma), float(settings.eta), float(settings.tau), gl_nodes.contiguous(),
        gl_weights.contiguous(), torch.get_num_threads())
    return CpuImage(color=color, depth=depth, alpha=alpha, lanes_evaluated=int(stats[0]), pairs=int(stats[1]))


def rasterize(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *, mode: str, options):
    """:func:`mipslam.render.rasterize` on the compiled backend (inputs already checked by it).

    Projection, footprint parameters, radii and the optional normalised depth are the torch backend's own
    code (:func:`mipslam.render.rasterize_torch` with this module's per-pixel stage).
    """
    reason = unsupported_reason(means, colors, mode, options)
    if reason is not None:
        raise BackendUnavailableError(f"rasterize: {reason}")
    load_extension()
    from mipslam.render import rasterize_torch

    out = rasterize_torch(means, quats, scales, opacities, colors, viewmat, K, width, height, mode, options,
                          rasterizer=rasterize_projected)
    return dataclasses.replace(out, backend="cpu")
