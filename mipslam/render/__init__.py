"""Differentiable Gaussian rasterizer (docs/design.md "Renderer contract"; docs/renderer.md).

    from mipslam.render import rasterize
    out = rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height,
                    mode="eaa", backend="auto", **options)

``out.color`` [H, W, C], ``out.depth`` [H, W] (sum of T*alpha*z), ``out.alpha`` [H, W]; the options are
the fields of :class:`RenderOptions`. ``render(gaussians, camera)`` is the same on a map object and a
:class:`Camera`.
"""
from __future__ import annotations

import importlib
import importlib.util
import logging
from dataclasses import dataclass, fields
from types import SimpleNamespace
from functools import lru_cache

import torch

from mipslam.errors import BackendUnavailableError, RenderError
from mipslam.render.footprint import MODES
from mipslam.render.projection import ProjectedGaussians, project_gaussians
from mipslam.render.torch_backend import RenderOutput, check_camera_values as _check_camera_values, rasterize_torch

__all__ = ["rasterize", "rasterize_pose_only", "render", "RenderOptions", "render_option_problems", "RenderOutput",
           "Camera", "MODES", "BACKENDS", "available_backends", "direct_aligner", "compiled_library", "project_gaussians",
           "ProjectedGaussians"]

log = logging.getLogger(__name__)

BACKENDS = ("auto", "torch", "cpu")


@dataclass(frozen=True)
class RenderOptions:
    """Renderer options (keyword arguments of :func:`rasterize`); defaults measured in docs/renderer.md.

    near_plane        metres; Gaussians with camera z <= near_plane are dropped
    far_plane         metres; Gaussians with camera z >= far_plane are dropped (keeps float32 finite)
    k_sigma           k-sigma bound (tile binning, centre-sample cut, EAA clipping)
    eaa_max_nodes     EAA node cap n_max (1 = one moment-matched node everywhere)
    eaa_gamma         EAA anisotropy growth of a sub-pixel splat: n = 2 (1 + gamma ln kappa)
    eaa_eta, eaa_tau  EAA boundary emphasis b(d) = 1 + eta exp(-d / tau) (tau in pixels)
    eaa_single_node_sigma  minor-axis std-dev (px) from which a Gaussian takes 1 node, moment-matched to the pixel
    filter_3d_scale   Mip-Splatting 3D filter strength s (None or 0 = off; the paper uses 0.2)
    max_sampling_rate [N] px/metre per Gaussian for the 3D filter (None: max(fx, fy) / z of this camera)
    pose_only         gradients for viewmat only: the Gaussian parameters are detached (tracking)
    normalized_depth  also return depth / alpha
    appearance_color  also return color_appearance: the colour image again, whose gradient reaches the colours
                      alone (an appearance loss that must not move the geometry or the camera)
    exact_order       Gauss-Legendre order per axis of ``exact`` mode
    tile_size         tile edge in pixels
    pair_budget       max padded (tile pixel x Gaussian x node) evaluations per batch (memory bound)
    checkpoint        recompute each batch in backward instead of storing it (None: when the work is large)
    """

    near_plane: float = 0.01
    far_plane: float = 1e10
    k_sigma: float = 3.0
    eaa_max_nodes: int = 4
    eaa_gamma: float = 0.5
    eaa_eta: float = 0.0
    eaa_tau: float = 0.25
    eaa_single_node_sigma: float = 1.0
    filter_3d_scale: float | None = None
    max_sampling_rate: torch.Tensor | None = None
    pose_only: bool = False
    normalized_depth: bool = False
    appearance_color: bool = False
    exact_order: int = 20
    tile_size: int = 8
    pair_budget: int = 1 << 20
    checkpoint: bool | None = None

    def __post_init__(self):
        for name, message in RenderOptions.problems(self):
            raise RenderError(f"render option: {name} {message}")

    @staticmethod
    def problems(options) -> list[tuple[str, str]]:
        """(option name, what it must be) for every option of ``options`` out of range; empty when all are valid.

        ``options``: a RenderOptions, or any object with its attributes; the render config
        (``mipslam.config.RenderConfig``) checks its renderer options with these rules before it builds any.
        """
        self = options
        checks = [
            ("near_plane", self.near_plane > 0, "must be positive (metres)"),
            ("far_plane", self.far_plane > self.near_plane, "must be larger than near_plane (metres)"),
            ("k_sigma", self.k_sigma > 0, "must be positive"),
            ("eaa_max_nodes", int(self.eaa_max_nodes) == self.eaa_max_nodes and self.eaa_max_nodes >= 1,
             "must be an integer >= 1 (1 = one node everywhere)"),
            ("eaa_gamma", self.eaa_gamma >= 0, "must be >= 0"),
            ("eaa_eta", self.eaa_eta >= 0, "must be >= 0"),
            ("eaa_tau", self.eaa_tau > 0, "must be positive (pixels)"),
            ("eaa_single_node_sigma", self.eaa_single_node_sigma >= 0, "must be >= 0 (px)"),
            ("filter_3d_scale", self.filter_3d_scale is None or self.filter_3d_scale >= 0, "must be >= 0 or None"),
            ("exact_order", self.exact_order >= 1, "must be >= 1"),
            ("tile_size", self.tile_size >= 1, "must be >= 1"),
            ("pair_budget", self.pair_budget >= 1, "must be >= 1"),
        ]
        return [(name, message) for name, ok, message in checks if not ok]


_OPTION_NAMES = frozenset(f.name for f in fields(RenderOptions))


def render_option_problems(**values) -> list[tuple[str, str]]:
    """:meth:`RenderOptions.problems` of the defaults with ``values`` replacing some of them (not raising)."""
    unknown = sorted(set(values) - _OPTION_NAMES)
    if unknown:
        raise RenderError(f"render option(s) {unknown} unknown; valid options: {sorted(_OPTION_NAMES)}")
    defaults = {f.name: f.default for f in fields(RenderOptions)}
    return RenderOptions.problems(SimpleNamespace(**{**defaults, **values}))


@dataclass(frozen=True)
class Camera:
    """A pinhole camera to render from.  viewmat [4, 4] = T_cw (world to camera), K [3, 3]"""

    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int


@lru_cache(maxsize=1)
def _cpu_backend_installed() -> bool:
    return importlib.util.find_spec("mipslam.render.cpu") is not None


def _cpu_backend_module():
    """The compiled CPU backend module if present and built, else None."""
    if not _cpu_backend_installed():
        return None
    module = importlib.import_module("mipslam.render.cpu")
    is_available = getattr(module, "is_available", None)
    if is_available is None or not is_available():
        return None
    return module


def available_backends() -> tuple[str, ...]:
    """Backends usable on this machine (``torch`` always)."""
    return ("torch", "cpu") if _cpu_backend_module() is not None else ("torch",)


def compiled_library():
    """The loaded compiled CPU library (:class:`mipslam.render.cpu.Library`) where it is installed and built, else
    None: for callers with a numpy reference of their own (the front-end's guided matching)."""
    cpu = _cpu_backend_module()
    return None if cpu is None else cpu.load_extension()


def direct_aligner(backend: str, device: torch.device):
    """The direct RGB-D alignment for tensors on ``device``: the compiled one
    (:func:`mipslam.render.cpu.align_direct`) where ``backend`` (``render.backend``: auto, torch or cpu) takes the
    compiled CPU library and it is built, else the torch reference (:func:`mipslam.geometry.direct.align_direct`,
    any device). Both take the same arguments and return a :class:`~mipslam.geometry.direct.DirectResult`."""
    cpu = _cpu_backend_module() if backend != "torch" and device.type == "cpu" else None
    if cpu is not None:
        return cpu.align_direct
    from mipslam.geometry.direct import align_direct

    return align_direct


def rgbd_loss_and_gradients(backend: str, color: torch.Tensor, depth: torch.Tensor, color_gt: torch.Tensor,
                            depth_gt: torch.Tensor, *, gradients: bool = True, **terms):
    """A render's masked RGB-D L1 loss and its gradients (:func:`mipslam.losses.photometric.rgbd_l1_loss_and_gradients`,
    whose keyword arguments ``terms`` are): in one pass of the compiled library
    (:func:`mipslam.render.cpu.backend.rgbd_l1_loss_and_gradients`) where ``backend`` (``render.backend``) takes
    it, it is built and the images are CPU float32 with 1, 3 or 4 colour channels, else in torch. -> (RGBDLoss,
    RGBDLossGradients, or None with ``gradients=False``)."""
    cpu = (_cpu_backend_module() if backend != "torch" and color.device.type == "cpu" and color.dtype == torch.float32
           and color.dim() == 3 else None)
    if cpu is not None and color.shape[-1] in cpu.SUPPORTED_CHANNELS:
        return cpu.rgbd_l1_loss_and_gradients(color, depth, color_gt, depth_gt, gradients=gradients, **terms)
    from mipslam.losses.photometric import rgbd_l1_loss, rgbd_l1_loss_and_gradients

    if not gradients and terms.get("exposure") is None:  # the loss alone: no gradient images to build and drop
        with torch.no_grad():
            return rgbd_l1_loss(color, depth, color_gt, depth_gt, **terms), None
    loss, grads = rgbd_l1_loss_and_gradients(color, depth, color_gt, depth_gt, **terms)
    return loss, grads if gradients else None


def _check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height):
    n = means.shape[0] if means.dim() == 2 else -1
    expected = {"means": (means, (n, 3)), "quats": (quats, (n, 4)), "scales": (scales, (n, 3)),
                "opacities": (opacities, (n,)), "viewmat": (viewmat, (4, 4)), "K": (K, (3, 3))}
    for name, (tensor, shape) in expected.items():
        if not isinstance(tensor, torch.Tensor):
            raise RenderError(f"rasterize: {name} must be a torch.Tensor, got {type(tensor).__name__}")
        if tuple(tensor.shape) != shape:
            raise RenderError(f"rasterize: {name} must have shape {list(shape)}, got {list(tensor.shape)}")
    if not isinstance(colors, torch.Tensor) or colors.dim() != 2 or colors.shape[0] != n:
        raise RenderError(f"rasterize: colors must have shape [N={n}, C], got {getattr(colors, 'shape', None)}")
    tensors = (means, quats, scales, opacities, colors, viewmat, K)
    if any(not t.is_floating_point() for t in tensors) or len({t.dtype for t in tensors}) != 1:
        raise RenderError("rasterize: all inputs must share one floating dtype (float32, or float64 for checks), "
                          f"got {sorted({str(t.dtype) for t in tensors})}")
    if len({t.device for t in tensors}) != 1:
        raise RenderError(f"rasterize: all inputs must be on one device, got {sorted({str(t.device) for t in tensors})}")
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise RenderError(f"rasterize: width and height must be integers >= 1, got {width} x {height}")


def rasterize(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
              colors: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
              mode: str = "eaa", backend: str = "auto", **options) -> RenderOutput:
    """Render 3D Gaussians (docs/renderer.md).

    means [N, 3] world metres, quats [N, 4] wxyz (normalised inside), scales [N, 3] std-devs in metres
    (linear), opacities [N] in [0, 1], colors [N, C] (C = 3 for RGB), viewmat [4, 4] world-to-camera
    (T_cw), K [3, 3]; one float dtype and device for all. Differentiable with respect to all of them
    (viewmat included). Gaussians with NaN/Inf entries are dropped. ``options``: :class:`RenderOptions`.
    """
    if mode not in MODES:
        raise RenderError(f"rasterize: unknown mode '{mode}'; choose one of {', '.join(MODES)}")
    if backend not in BACKENDS:
        raise RenderError(f"rasterize: unknown backend '{backend}'; choose one of {', '.join(BACKENDS)}")
    if not _OPTION_NAMES.issuperset(options):
        unknown = sorted(set(options) - _OPTION_NAMES)
        raise RenderError(f"rasterize: unknown option(s) {unknown}; valid options: {sorted(_OPTION_NAMES)}")
    opts = RenderOptions(**options)
    _check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height)
    width, height = int(width), int(height)

    if backend in ("auto", "cpu") and means.device.type == "cpu":
        cpu = _cpu_backend_module()
        if cpu is not None:
            unsupported = getattr(cpu, "unsupported_reason", lambda *args: None)(means, colors, mode, opts)
            if unsupported is None:
                return cpu.rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height,
                                     mode=mode, options=opts)
            if backend == "cpu":
                raise BackendUnavailableError(f"rasterize: {unsupported}")
            log.debug("rasterize: backend 'auto' uses torch for this call: %s", unsupported)
        elif backend == "cpu":
            reason = (importlib.import_module("mipslam.render.cpu").unavailable_reason()
                      if _cpu_backend_installed() else None) or "it is not built"
            raise BackendUnavailableError(
                f"rasterize: the 'cpu' backend is not available on this machine ({reason}); use backend='torch' "
                "or 'auto'")
    elif backend == "cpu":
        raise BackendUnavailableError(f"rasterize: the 'cpu' backend needs CPU tensors, got {means.device}")
    _check_camera_values(viewmat, K)
    return rasterize_torch(means, quats, scales, opacities, colors, viewmat, K, width, height, mode, opts)


def rasterize_pose_only(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                        colors: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                        mode: str = "eaa", backend: str = "auto", **options):
    """A pose-only render whose backward to ``viewmat`` is written out, for a caller that carries the chain rule
    itself (tracking's step): :class:`mipslam.render.cpu.PoseOnlyRender` (``color``, ``depth``, ``alpha`` and
    ``viewmat_gradient(grad_color, grad_depth)``), the images and gradient :func:`rasterize` with ``pose_only``
    and autograd give, bit for bit. None where the compiled CPU backend cannot take the call (``backend`` torch,
    tensors off the CPU, a mode or option it lacks, a K or sampling rate that needs a gradient): render with
    :func:`rasterize` and autograd there. Arguments as :func:`rasterize`; ``pose_only`` is implied."""
    if mode not in MODES:
        raise RenderError(f"rasterize_pose_only: unknown mode '{mode}'; choose one of {', '.join(MODES)}")
    if backend not in BACKENDS:
        raise RenderError(f"rasterize_pose_only: unknown backend '{backend}'; choose one of {', '.join(BACKENDS)}")
    cpu = _cpu_backend_module() if backend != "torch" else None
    if cpu is None:
        return None
    opts = RenderOptions(**{**options, "pose_only": True})
    if cpu.pose_only_unsupported_reason(means, colors, K, mode, opts) is not None:
        return None
    _check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height)
    return cpu.rasterize_pose_only(means, quats, scales, opacities, colors, viewmat, K, int(width), int(height),
                                   mode=mode, options=opts)


def render(gaussians, camera: Camera, *, mode: str = "eaa", backend: str = "auto", **options) -> RenderOutput:
    """Render a map object (anything with ``means``, ``quats``, ``scales``, ``opacities`` and ``colors``
    tensors in the units of :func:`rasterize`) from a :class:`Camera`."""
    return rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.colors,
                     camera.viewmat, camera.K, camera.width, camera.height, mode=mode, backend=backend, **options)
