"""Structural similarity (SSIM) as a differentiable function of two images, for losses and for the evaluation.

``SSIM = (2 mu_x mu_y + C1)(2 sigma_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(sigma_x^2 + sigma_y^2 + C2))`` (Wang et al.,
2004) with Gaussian-weighted local moments (window ``window_size`` px, std-dev ``sigma`` px), ``C1 = (0.01 L)^2``,
``C2 = (0.03 L)^2``, per channel, averaged over channels and pixels. ``padding="same"`` convolves with zero padding of
``window // 2`` pixels and averages the full map, as 3D Gaussian Splatting's ``utils/loss_utils.ssim`` does (the
photometric loss ``(1 - l) L1 + l (1 - SSIM)`` of Kerbl et al., 2023, and the evaluation of the Gaussian-splatting
SLAM papers); ``"valid"`` averages only windows inside the image. Images are float, channels last, ``[..., H, W, C]``.

:func:`ssim` is the readable torch reference. :func:`ssim_loss` (``1 - SSIM``, the loss term) computes the same value
with the compiled CPU library's kernel (``mipslam/render/cpu/ssim_loss.h``: separable blurs, an analytic backward,
the target's moments optionally cached by :class:`SSIMTargetCache`) where it can, 7-15x faster than autograd
through :func:`ssim` (docs/renderer_cpu.md, section 3d), and falls back to :func:`ssim` elsewhere.
"""
from __future__ import annotations

import collections
import functools
import weakref
from typing import Literal

import torch
from torch.autograd.function import once_differentiable

__all__ = ["gaussian_window_1d", "ssim", "ssim_loss", "SSIMTargetCache", "COMPILED_MAX_WINDOW"]

#: The largest window the compiled kernel takes (ssim_loss.h's MAX_TAPS); larger ones use the torch reference.
COMPILED_MAX_WINDOW = 31


def gaussian_window_1d(size: int, sigma: float, *, dtype=torch.float64, device=None) -> torch.Tensor:  # [size]
    """Normalised sampled Gaussian ``exp(-(x - size//2)^2 / (2 sigma^2))`` (the 1D factor of the SSIM window)."""
    x = torch.arange(size, dtype=torch.float64, device=device) - (size // 2)
    g = torch.exp(-(x * x) / (2.0 * sigma * sigma))
    return (g / g.sum()).to(dtype)


def _check_images(name: str, image: torch.Tensor, target: torch.Tensor, window_size: int) -> None:
    if image.shape != target.shape or image.dim() < 3:
        raise ValueError(f"{name}: images must share a shape [..., H, W, C], got {tuple(image.shape)} and "
                         f"{tuple(target.shape)}")
    if window_size % 2 != 1:
        raise ValueError(f"{name}: window size must be odd, got {window_size}")


def ssim(
    image: torch.Tensor,  # [..., H, W, C] in [0, max_value]
    target: torch.Tensor,  # [..., H, W, C], the same shape
    *,
    window_size: int = 11,
    sigma: float = 1.5,
    padding: Literal["same", "valid"] = "same",
    max_value: float = 1.0,
) -> torch.Tensor:  # [...]
    """SSIM per image (module docstring); differentiable with respect to both images. Raises ValueError on
    mismatched shapes, an even window or a ``valid`` window larger than the image."""
    _check_images("SSIM", image, target, window_size)
    if padding not in ("same", "valid"):
        raise ValueError(f"SSIM: padding must be 'same' or 'valid', got {padding!r}")
    batch_shape = image.shape[:-3]
    height, width, channels = image.shape[-3:]
    if padding == "valid" and (height < window_size or width < window_size):
        raise ValueError(f"SSIM: 'valid' padding needs images of at least {window_size} px, got {height}x{width}")
    x = image.reshape(-1, height, width, channels).permute(0, 3, 1, 2)  # [B, C, H, W]
    y = target.reshape(-1, height, width, channels).permute(0, 3, 1, 2)
    g = gaussian_window_1d(window_size, sigma, dtype=x.dtype, device=x.device)
    weight_rows = g.view(1, 1, window_size, 1).expand(channels, 1, window_size, 1)
    weight_cols = g.view(1, 1, 1, window_size).expand(channels, 1, 1, window_size)
    pad = window_size // 2 if padding == "same" else 0

    def blur(z: torch.Tensor) -> torch.Tensor:  # [B, C, H, W] -> [B, C, H', W'], separable Gaussian
        z = torch.nn.functional.conv2d(z, weight_rows, padding=(pad, 0), groups=channels)
        return torch.nn.functional.conv2d(z, weight_cols, padding=(0, pad), groups=channels)

    c1, c2 = (0.01 * max_value) ** 2, (0.03 * max_value) ** 2
    mu_x, mu_y = blur(x), blur(y)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    sigma_xx = blur(x * x) - mu_xx
    sigma_yy = blur(y * y) - mu_yy
    sigma_xy = blur(x * y) - mu_xy
    ssim_map = ((2 * mu_xy + c1) * (2 * sigma_xy + c2)) / ((mu_xx + mu_yy + c1) * (sigma_xx + sigma_yy + c2))
    return ssim_map.mean(dim=(1, 2, 3)).reshape(batch_shape)


# ------------------------------------------------------------------------------------------------
# The loss term, with the compiled kernel
# ------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _window_float32(window_size: int, sigma: float) -> torch.Tensor:  # [window_size], read-only
    return gaussian_window_1d(window_size, sigma, dtype=torch.float32)


class SSIMTargetCache:
    """The blurred moments (``mu_y``, ``E[y^2]``, [2, H, W, C]) of :func:`ssim_loss`'s targets, per target tensor,
    so that the compiled kernel blurs a target once, not once per call: mapping scores the same keyframe images
    thousands of times (a cached call takes about a quarter less time than an uncached one).

    An entry belongs to one tensor object (held weakly: the entry goes when the tensor does) and is used only while
    the tensor's version counter, data pointer, shape, strides and the window are those it was computed from, so an
    in-place change of the target recomputes it. Pass the same tensor objects (a keyframe's stored image), not a new
    view per call. At most ``max_entries`` entries, least recently used dropped first. Not thread-safe.
    """

    def __init__(self, max_entries: int = 256):
        if max_entries < 1:
            raise ValueError(f"SSIMTargetCache: max_entries must be at least 1, got {max_entries}")
        self.max_entries = int(max_entries)
        self.hits = self.misses = 0
        self._entries: collections.OrderedDict[int, tuple] = collections.OrderedDict()

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        self._entries.clear()

    def moments(self, target: torch.Tensor, window_size: int, sigma: float, compute) -> torch.Tensor:
        """The moments of ``target`` for this window: the stored ones when still valid, else ``compute()``'s
        (stored)."""
        key = id(target)
        stamp = (target._version, target.data_ptr(), tuple(target.shape), target.stride(), window_size, float(sigma))
        entry = self._entries.get(key)
        if entry is not None and entry[0]() is target and entry[1] == stamp:
            self._entries.move_to_end(key)
            self.hits += 1
            return entry[2]
        self.misses += 1
        moments = compute()
        entries = self._entries

        def forget(ref, key=key):  # the target died: drop its entry (unless the id was reused meanwhile)
            held = entries.get(key)
            if held is not None and held[0] is ref:
                del entries[key]

        entries[key] = (weakref.ref(target, forget), stamp, moments)
        entries.move_to_end(key)
        while len(entries) > self.max_entries:
            entries.popitem(last=False)
        return moments


class _CompiledSSIMLoss(torch.autograd.Function):
    """``1 - SSIM`` of one CPU float32 image [H, W, C] in one call of the compiled kernel, which also returns the
    gradient (the loss is a scalar: the backward scales the saved gradient image)."""

    @staticmethod
    def forward(ctx, image, target, moments, window, c1, c2, library):
        value, grad = library.ssim(image.detach().contiguous(), target, moments, window, c1, c2, gradients=True,
                                   grad_scale=-1.0, threads=torch.get_num_threads())
        ctx.save_for_backward(grad)
        return torch.tensor(1.0 - value, dtype=torch.float32)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_output):
        (grad,) = ctx.saved_tensors
        return grad * grad_output, None, None, None, None, None, None


def _compiled_library(image: torch.Tensor, target: torch.Tensor, window_size: int):
    """The compiled library when it can compute this loss (else None): one CPU float32 image [H, W, C]."""
    if (image.dim() != 3 or image.dtype != torch.float32 or target.dtype != torch.float32
            or image.device.type != "cpu" or target.device.type != "cpu" or image.numel() == 0
            or window_size > COMPILED_MAX_WINDOW):
        return None
    from mipslam.render import compiled_library  # here: the losses do not import the renderer at import time

    return compiled_library()


def ssim_loss(
    image: torch.Tensor,  # [..., H, W, C] in [0, max_value]
    target: torch.Tensor,  # [..., H, W, C], the same shape; a constant (no gradient)
    *,
    window_size: int = 11,
    sigma: float = 1.5,
    max_value: float = 1.0,
    cache: SSIMTargetCache | None = None,
    backend: Literal["auto", "cpu", "torch"] = "auto",
) -> torch.Tensor:  # []
    """``1 - SSIM(image, target)`` with "same" padding (3DGS's structural loss term): one minus the mean of the
    SSIM map over pixels, channels and images, as a [] tensor differentiable with respect to ``image``; the target
    gets no gradient.

    ``backend="auto"`` computes it with the compiled CPU library (``ssim_loss.h``: value and analytic gradient in one
    call) for a CPU float32 image [H, W, C] and a window of at most :data:`COMPILED_MAX_WINDOW` taps where the library
    is built, and with the torch reference ``1 - ssim(image, target.detach()).mean()`` otherwise (CUDA, float64,
    a batch, no compiler, ``MIPSLAM_CPU_BACKEND=0``); both give the same value and gradient to float rounding
    (tests/test_ssim_loss.py). ``"torch"`` forces the reference; ``"cpu"`` raises
    :class:`~mipslam.errors.BackendUnavailableError` where the compiled kernel cannot run. ``cache``: an
    :class:`SSIMTargetCache` that keeps the target's blurred moments between calls (compiled path only). Raises
    ValueError like :func:`ssim`. The compiled kernel supports no double backward.
    """
    _check_images("ssim_loss", image, target, window_size)
    if backend not in ("auto", "cpu", "torch"):
        raise ValueError(f"ssim_loss: backend must be 'auto', 'cpu' or 'torch', got {backend!r}")
    given, target = target, target.detach()  # the cache keys on the caller's tensor object
    library = None if backend == "torch" else _compiled_library(image, target, window_size)
    if library is None:
        if backend == "cpu":
            from mipslam.errors import BackendUnavailableError

            raise BackendUnavailableError(
                "ssim_loss: the compiled kernel takes one CPU float32 image [H, W, C] and a window of at most "
                f"{COMPILED_MAX_WINDOW} taps, with the compiled library built (got {image.dtype} "
                f"{list(image.shape)} on {image.device}, window {window_size})")
        return 1.0 - ssim(image, target, window_size=window_size, sigma=sigma, max_value=max_value).mean()
    window = _window_float32(int(window_size), float(sigma))
    target = target.contiguous()
    threads = torch.get_num_threads()

    def compute_moments() -> torch.Tensor:
        return library.ssim_moments(target, window, threads)

    moments = None if cache is None else cache.moments(given, window_size, sigma, compute_moments)
    c1, c2 = (0.01 * max_value) ** 2, (0.03 * max_value) ** 2
    if image.requires_grad and torch.is_grad_enabled():
        return _CompiledSSIMLoss.apply(image, target, moments, window, c1, c2, library)
    value, _ = library.ssim(image.contiguous(), target, moments, window, c1, c2, gradients=False, threads=threads)
    return torch.tensor(1.0 - value, dtype=torch.float32)
