"""The compiled CPU backend of the renderer: C++/OpenMP tile rasterizer with a SIMD forward and a
hand-written backward (docs/renderer.md, "CPU backend").

Split as in gsplat: the projection (:func:`mipslam.render.projection.project_gaussians`), the footprint
parameters of each mode and EAA node counts (:func:`mipslam.render.footprint.mode_footprint`)
stay in torch, shared with the torch backend line for line, so autograd carries the gradient from the
projected quantities to the 3D parameters and the viewmat. The extension receives, per Gaussian,

    means2d [N, 2] px, cov [N, 4] = (xx, xy, yy, det) px^2 / px^4 (the mode's sampling covariance),
    opacity [N] (the mode's), depth [N] metres, colors [N, C], node_counts [N] int32 (EAA)

and does the per-pixel part: tile binning, depth sort, footprint evaluation (point/mip/ewa as a centre
sample, EAA with its rows, exact Gauss-Legendre) and front-to-back compositing, forward and backward
(:class:`RasterizeProjected`, a ``torch.autograd.Function``).

Build: compiled from source on first use with ``torch.utils.cpp_extension.load`` (ninja), cached under
``$MIPSLAM_CACHE_DIR`` or ``$XDG_CACHE_HOME/mipslam`` or ``~/.cache/mipslam``, in a folder keyed by a hash
of the sources, the compiler flags, the compiler and the torch version; the sources are compiled from a copy
in that folder, so every checkout of the same code shares one build. ``-mavx2 -mfma`` are added only
when this CPU has both (checked at run time before compiling); otherwise the x86-64 baseline build is
used, so the cached binary never needs more than the CPU that built it. If the build fails (no compiler,
no ninja, ...) one warning is logged and :func:`is_available` is False: ``backend="auto"`` then uses the
torch backend and ``backend="cpu"`` raises :class:`~mipslam.errors.BackendUnavailableError` with the
reason (:func:`unavailable_reason`). ``MIPSLAM_CPU_BACKEND=0`` disables the backend;
``MIPSLAM_CPU_CFLAGS`` appends compiler flags (e.g. ``-march=native`` for a build that will only ever
run on this machine).
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import threading
import time
from pathlib import Path

import torch

from mipslam.errors import BackendUnavailableError, RenderError
from mipslam.render import footprint, projection

log = logging.getLogger(__name__)

__all__ = ["is_available", "unavailable_reason", "unsupported_reason", "load_extension", "rasterize",
           "rasterize_unfused", "rasterize_projected", "RasterizeProjected", "ProjectFootprints",
           "project_footprints", "reference_footprints", "FootprintProjection", "profile_kernels", "KernelTimes",
           "build_flags", "MODE_IDS",
           "SUPPORTED_CHANNELS", "MAX_ROWS"]

_SOURCE_DIR = Path(__file__).resolve().parent
_SOURCES = ("raster_ext.cpp",)
_HEADERS = ("footprint_simd.h", "simd_math.h", "projection.h")
#: Footprint kernels of the extension: point/mip/ewa are all a centre sample of the mode's covariance.
MODE_IDS = {"point": 0, "mip": 0, "ewa": 0, "eaa": 1, "exact": 2}
#: Colour channel counts the extension is compiled for (template parameter, not a runtime loop bound).
SUPPORTED_CHANNELS = (1, 3, 4)
#: Cap of EAA nodes and of the exact-mode Gauss-Legendre order (MAX_ROWS in footprint_simd.h).
MAX_ROWS = 64

_lock = threading.Lock()
_state: dict = {"module": None, "reason": None, "tried": False, "timed": None}


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
    with _exclusive_build(build_dir):
        sources = _copy_sources(build_dir / "src")
        return cpp_extension.load(name=name, sources=[str(sources / s) for s in _SOURCES],
                                  extra_cflags=cflags, extra_ldflags=ldflags, build_directory=str(build_dir),
                                  verbose=False)


def _copy_sources(folder: Path) -> Path:
    """Copy the sources and headers into ``folder`` (inside the content-keyed build folder) and return it.

    ninja's build file names the sources by path. Compiling the checkout's own files made two checkouts of
    the same commit (a CI clone and a working tree, a frozen copy for a benchmark) rewrite it in turn and
    rebuild each other's extension. The copy has the same path for every checkout. A file is rewritten only
    when its content differs, so its modification time, which ninja compares, stays put.
    """
    folder.mkdir(parents=True, exist_ok=True)
    for name in _SOURCES + _HEADERS:
        data = (_SOURCE_DIR / name).read_bytes()
        target = folder / name
        if target.exists() and target.read_bytes() == data:
            continue
        partial = folder / f".{name}.partial"
        partial.write_bytes(data)
        os.replace(partial, target)
    return folder


@contextlib.contextmanager
def _exclusive_build(build_dir: Path):
    """Serialise builds of one extension across processes with a kernel lock (``flock``).

    torch's own build lock is a plain file (``build_dir/lock``) that a process killed mid-build
    (kill -9, power loss) leaves behind, and every later process then waits on it for ever. The
    kernel drops a ``flock`` with its holder, so whoever holds this one knows that any ``lock`` file
    left in the folder is stale and removes it. Without fcntl (Windows) torch's lock alone is used.
    """
    try:
        import fcntl
    except ImportError:
        yield
        return
    with open(build_dir / "mipslam-build.flock", "a+b") as handle:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX)
        try:
            stale = build_dir / "lock"
            if stale.exists():
                log.warning("removing %s left by a build that was killed", stale)
                stale.unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(handle.fileno(), fcntl.LOCK_UN)


def load_extension():
    """The compiled extension module (built on first call). Raises BackendUnavailableError with the reason."""
    timed = _state["timed"]
    if timed is not None:
        return timed
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


class _TimedExtension:
    """The extension with every function call timed (wall and process CPU seconds, call count per name)."""

    def __init__(self, module, times: "KernelTimes"):
        self._module, self._times = module, times

    def __getattr__(self, name):
        attr = getattr(self._module, name)
        if not callable(attr):
            return attr

        def timed(*args):
            start, start_cpu = time.perf_counter(), time.process_time()
            try:
                return attr(*args)
            finally:
                times = self._times
                times.seconds[name] = times.seconds.get(name, 0.0) + time.perf_counter() - start
                times.cpu_seconds[name] = times.cpu_seconds.get(name, 0.0) + time.process_time() - start_cpu
                times.calls[name] = times.calls.get(name, 0) + 1

        return timed


@dataclasses.dataclass
class KernelTimes:
    """Time spent inside the C++ extension's functions, per function name: wall seconds, process CPU
    seconds (all threads: core-seconds, robust to a loaded machine) and call counts."""

    seconds: dict
    cpu_seconds: dict
    calls: dict

    @property
    def total(self) -> float:
        """Wall seconds inside the extension."""
        return sum(self.seconds.values())

    @property
    def total_cpu(self) -> float:
        """Process CPU seconds inside the extension."""
        return sum(self.cpu_seconds.values())


@contextlib.contextmanager
def profile_kernels():
    """Time every call into the extension made inside the block (benchmarks: kernel time against the whole
    call; the Python and torch work around the kernels is the difference). Not thread-safe; not nestable.

        with profile_kernels() as kernels:
            out = rasterize(...)
        kernels.total, kernels.seconds["rasterize_forward"]
    """
    times = KernelTimes(seconds={}, cpu_seconds={}, calls={})
    _state["timed"] = _TimedExtension(load_extension(), times)
    try:
        yield times
    finally:
        _state["timed"] = None


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
        _state.update(module=None, reason=None, tried=False, timed=None)


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
# Fused projection (projection.h)
# ------------------------------------------------------------------------------------------------
# Order of the parameter vector of projection.h (enum ProjectionParam).
_PROJECTION_PARAM_NAMES = (
    "near", "far", "extent_sigma", "extent_pad", "extent_dilation", "filter_scale", "dilation", "dilation_sq",
    "energy", "eaa", "max_nodes", "gamma", "single_node_sigma", "box_variance", "radius_sigma", "radius_pad",
    "cov_floor", "cov_floor_sq", "fov_margin", "max_sigma_px", "max_tangent")


@functools.lru_cache(maxsize=64)
def _projection_params(mode: str, near_plane: float, far_plane: float, k_sigma: float, filter_3d_scale: float,
                       max_nodes: int, gamma: float, single_node_sigma: float) -> tuple[float, ...]:
    """The settings of the fused projection for one mode and option set, exactly as
    :func:`mipslam.render.rasterize_torch` passes them to the torch reference (cached per option set)."""
    box_mode = mode in ("eaa", "exact")
    dilation = footprint.MODE_DILATION.get(mode, 0.0)
    values = {
        "near": near_plane, "far": far_plane,
        "extent_sigma": footprint.EXACT_K_SIGMA if mode == "exact" else k_sigma,
        "extent_pad": 0.5 if box_mode else 0.0, "extent_dilation": dilation,
        "filter_scale": float(filter_3d_scale or 0.0),
        "dilation": dilation, "dilation_sq": dilation * dilation,
        "energy": 1.0 if mode in footprint.ENERGY_PRESERVING else 0.0, "eaa": 1.0 if mode == "eaa" else 0.0,
        "max_nodes": float(max_nodes), "gamma": gamma, "single_node_sigma": single_node_sigma,
        "box_variance": footprint.EAA_BOX_VARIANCE,
        "radius_sigma": k_sigma, "radius_pad": 0.5 if box_mode else 0.0,
        "cov_floor": projection.COV_FLOOR, "cov_floor_sq": projection.COV_FLOOR * projection.COV_FLOOR,
        "fov_margin": projection.FOV_MARGIN, "max_sigma_px": projection.MAX_SIGMA_PX,
        "max_tangent": projection.MAX_TANGENT,
    }
    return tuple(float(values[name]) for name in _PROJECTION_PARAM_NAMES)


def _params_for(mode: str, options) -> tuple[float, ...]:
    return _projection_params(mode, float(options.near_plane), float(options.far_plane), float(options.k_sigma),
                              float(options.filter_3d_scale or 0.0), int(options.eaa_max_nodes),
                              float(options.eaa_gamma), float(options.eaa_single_node_sigma))


class ProjectFootprints(torch.autograd.Function):
    """Fused projection + footprint parameters + EAA node counts + radii (projection.h), with a hand-written
    backward to means, quats, scales, opacities and the viewmat (K and the sampling rate are constants).

    Inputs: means [N, 3], quats [N, 4], scales [N, 3], opacities [N], viewmat [4, 4], colors [N, C] (only their
    finiteness matters here), K [3, 3], max_sampling_rate [N] or None, then plain settings. Outputs: means2d
    [N, 2] px, depths [N] m, cov [N, 4] (the mode's xx, xy, yy px^2 and det px^4), opacity [N] (the mode's),
    node_counts [N] int32, visible [N] bool, radii [N] px (the last three without gradient), and the number of
    visible Gaussians (int).
    """

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, colors, K, rate, width: int, height: int,
                params: tuple, threads: int):
        means2d, depths, cov, opacity, node_counts, visible, radii, n_visible = load_extension().project_forward(
            means, quats, scales, opacities, colors, viewmat, K, rate, width, height, params, threads)
        ctx.save_for_backward(means, quats, scales, opacities, viewmat, colors, K, rate, visible)
        ctx.settings = (width, height, params, threads)
        ctx.set_materialize_grads(False)
        ctx.mark_non_differentiable(node_counts, visible, radii)
        # The mode's opacity depends on the geometry only through an energy factor (mip, ewa, EAA's single
        # node) or the 3D filter; without them and without an opacity gradient it is a constant, so the
        # rasterizer skips its opacity sums.
        needs = ctx.needs_input_grad
        geometric = params[_PROJECTION_PARAM_NAMES.index("energy")] != 0.0 \
            or params[_PROJECTION_PARAM_NAMES.index("eaa")] != 0.0 \
            or params[_PROJECTION_PARAM_NAMES.index("filter_scale")] != 0.0
        if not (needs[3] or (geometric and (any(needs[:3]) or needs[4]))):
            ctx.mark_non_differentiable(opacity)
        return means2d, depths, cov, opacity, node_counts, visible, radii, n_visible

    @staticmethod
    def backward(ctx, g_means2d, g_depths, g_cov, g_opacity, _g_nodes, _g_visible, _g_radii, _g_count):
        means, quats, scales, opacities, viewmat, colors, K, rate, visible = ctx.saved_tensors
        width, height, params, threads = ctx.settings
        needs = ctx.needs_input_grad
        need_params = any(needs[:4])
        g_means, g_quats, g_scales, g_opacities, g_viewmat = load_extension().project_backward(
            means, quats, scales, opacities, colors, viewmat, K, rate, width, height, params, visible, g_means2d,
            g_depths, g_cov, g_opacity, need_params, bool(needs[4]), threads)
        return (g_means if needs[0] else None, g_quats if needs[1] else None, g_scales if needs[2] else None,
                g_opacities if needs[3] else None, g_viewmat if needs[4] else None) + (None,) * 7


@dataclasses.dataclass(frozen=True)
class FootprintProjection:
    """Per-Gaussian output of the fused projection (aligned with the input order).

    means2d    [N, 2] px    projected centre (-1e6 where not visible)
    depths     [N]    m     camera-frame z (0 where not visible)
    cov        [N, 4]       the mode's sampling covariance (xx, xy, yy) px^2 and its determinant px^4
    opacities  [N]          the mode's opacity (3D filter and energy factor applied; 0 where not visible)
    node_counts[N]    int32 EAA node count (1 in the other modes)
    visible    [N]    bool  finite, in front of the near plane, on screen, opacity > 0
    radii      [N]    px    k-sigma half extent as RenderOutput.radii
    n_visible  int
    """

    means2d: torch.Tensor
    depths: torch.Tensor
    cov: torch.Tensor
    opacities: torch.Tensor
    node_counts: torch.Tensor
    visible: torch.Tensor
    radii: torch.Tensor
    n_visible: int


def project_footprints(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *, mode: str,
                       options) -> FootprintProjection:
    """The fused projection (float32 or float64 CPU tensors; differentiable with respect to means, quats,
    scales, opacities and viewmat). Equals :func:`reference_footprints` (the torch reference) to rounding.
    ``options``: :class:`mipslam.render.RenderOptions`.
    """
    rate = options.max_sampling_rate
    out = ProjectFootprints.apply(means, quats, scales, opacities, viewmat, colors, K, rate, int(width), int(height),
                                  _params_for(mode, options), torch.get_num_threads())
    return FootprintProjection(*out)


def _torch_footprints(proj, mode: str, max_nodes: int, gamma: float, single_node_sigma: float):
    """The torch footprint parameters of projected Gaussians and their EAA node counts (1 outside eaa).

    -> xx, xy, yy, det [N] (the mode's sampling covariance), opacity [N], node counts [N] int64
    """
    return footprint.mode_footprint(mode, *proj.cov2d.unbind(-1), proj.cov_det, proj.opacities,
                                    max_nodes=int(max_nodes), gamma=gamma, single_node_sigma=single_node_sigma)


def reference_footprints(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *, mode: str,
                         options) -> FootprintProjection:
    """What :func:`project_footprints` computes, in torch (the readable reference):
    :func:`~mipslam.render.projection.project_gaussians` with the mode's extent, then
    :func:`~mipslam.render.footprint.mode_footprint`
    and the radii of :func:`mipslam.render.rasterize_torch`."""
    box_mode = mode in ("eaa", "exact")
    dilation = footprint.MODE_DILATION.get(mode, 0.0)
    proj = projection.project_gaussians(
        means, quats, scales, opacities, colors, viewmat, K, width, height, near_plane=options.near_plane,
        far_plane=options.far_plane, extent_sigma=footprint.EXACT_K_SIGMA if mode == "exact" else options.k_sigma,
        extent_pad=0.5 if box_mode else 0.0, extent_dilation=dilation, filter_3d_scale=options.filter_3d_scale,
        max_sampling_rate=options.max_sampling_rate)
    xx, xy, yy, det, opacity, nodes = _torch_footprints(proj, mode, options.eaa_max_nodes, options.eaa_gamma,
                                                        options.eaa_single_node_sigma)
    with torch.no_grad():
        ext = options.k_sigma * torch.sqrt(torch.maximum(proj.cov2d[:, 0], proj.cov2d[:, 2]) + dilation)
        radii = torch.where(proj.visible, ext + (0.5 if box_mode else 0.0), torch.zeros_like(ext))
    return FootprintProjection(means2d=proj.means2d, depths=proj.depths, cov=torch.stack([xx, xy, yy, det], -1),
                               opacities=opacity, node_counts=nodes.to(torch.int32), visible=proj.visible,
                               radii=radii, n_visible=int(proj.visible.sum()))


# ------------------------------------------------------------------------------------------------
# Rasterization autograd
# ------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _gauss_legendre_f32(order: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss-Legendre nodes and weights (float32, CPU), built once per order."""
    return footprint.gauss_legendre(order, torch.float32, "cpu")


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
    xx, xy, yy, det, opacity, node_counts = _torch_footprints(proj, mode, settings.max_nodes, settings.gamma,
                                                              settings.single_node_sigma)
    gl_nodes, gl_weights = _gauss_legendre_f32(settings.exact_order if mode == "exact" else 1)
    cov = torch.stack([xx, xy, yy, det], -1)
    color, depth, alpha, stats = RasterizeProjected.apply(
        proj.means2d.contiguous(), cov.contiguous(), opacity.contiguous(), proj.depths.contiguous(),
        proj.colors.contiguous(), node_counts.to(torch.int32).contiguous(), MODE_IDS[mode], int(width), int(height),
        float(settings.k_sigma), float(settings.eta), float(settings.tau), gl_nodes, gl_weights,
        torch.get_num_threads())
    return CpuImage(color=color, depth=depth, alpha=alpha, lanes_evaluated=int(stats[0]), pairs=int(stats[1]))


# ------------------------------------------------------------------------------------------------
# Entry point
# ------------------------------------------------------------------------------------------------
def _fused_projection_applies(means, K, options) -> bool:
    """The fused projection treats K and the 3D filter's sampling rate as constants; when either needs a
    gradient (or the rate is not a plain [N] tensor of the means' dtype) the torch projection is used."""
    if K.requires_grad:
        return False
    rate = options.max_sampling_rate
    return rate is None or (not rate.requires_grad and rate.dtype == means.dtype and rate.device == means.device
                            and tuple(rate.shape) == (means.shape[0],))


def rasterize(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *, mode: str, options):
    """:func:`mipslam.render.rasterize` on the compiled backend (shapes and dtypes already checked by it; the
    camera's values are checked here, in C++).

    Two C++ stages, each an autograd function with a hand-written backward: the fused projection
    (:class:`ProjectFootprints`) and the tile rasterizer (:class:`RasterizeProjected`).
    """
    from mipslam.render import RenderOutput

    reason = unsupported_reason(means, colors, mode, options)
    if reason is not None:
        raise BackendUnavailableError(f"rasterize: {reason}")
    load_extension()
    if not _fused_projection_applies(means, K, options):
        return rasterize_unfused(means, quats, scales, opacities, colors, viewmat, K, width, height, mode=mode,
                                 options=options)
    if options.pose_only:
        means, quats, scales, opacities, colors = (t.detach() for t in (means, quats, scales, opacities, colors))
    threads = torch.get_num_threads()
    try:
        means2d, depths, cov, opacity, node_counts, visible, radii, n_visible = ProjectFootprints.apply(
            means, quats, scales, opacities, viewmat, colors, K, options.max_sampling_rate, width, height,
            _params_for(mode, options), threads)
    except ValueError as exc:  # the camera checks of projection.h (TORCH_CHECK_VALUE)
        raise RenderError(str(exc).split("\n")[0]) from None
    gl_nodes, gl_weights = _gauss_legendre_f32(options.exact_order if mode == "exact" else 1)
    color, depth, alpha, _stats = RasterizeProjected.apply(
        means2d, cov, opacity, depths, colors.contiguous(), node_counts, MODE_IDS[mode], width, height,
        float(options.k_sigma), float(options.eaa_eta), float(options.eaa_tau), gl_nodes, gl_weights, threads)
    depth_normalized = None
    if options.normalized_depth:
        depth_normalized = torch.where(alpha > 1e-6, depth / alpha.clamp_min(1e-6), torch.zeros_like(depth))
    return RenderOutput(color=color, depth=depth, alpha=alpha, depth_normalized=depth_normalized, means2d=means2d,
                        radii=radii, visible=visible, n_visible=n_visible, depths=depths, mode=mode,
                        backend="cpu")


def rasterize_unfused(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *, mode: str,
                      options):
    """The cpu backend with the torch projection (autograd through ~100 tensor operations) in front of the
    C++ rasterizer: the path before the fused projection, kept for gradients with respect to K or the 3D
    filter's sampling rate, and as the benchmark's baseline."""
    from mipslam.render import _check_camera_values, rasterize_torch

    _check_camera_values(viewmat, K)
    out = rasterize_torch(means, quats, scales, opacities, colors, viewmat, K, width, height, mode, options,
                          rasterizer=rasterize_projected)
    return dataclasses.replace(out, backend="cpu")
