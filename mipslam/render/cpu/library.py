"""Locate and load the compiled rasterizer (built at install time by :mod:`mipslam.render.cpu.build`) and call
it with tensors.

The library is a plain C++ shared library with a C interface, loaded with ctypes; each call passes the raw
data pointers of contiguous CPU tensors (checked here: the C side trusts shapes and dtypes) and ctypes
releases the GIL for its duration. Loading takes milliseconds and never compiles. Which build: the
``avx2`` library when this CPU runs AVX2 and FMA (asked of the baseline library, ``__builtin_cpu_supports``),
else ``baseline``; ``MIPSLAM_CPU_ISA=baseline`` forces the baseline one and ``MIPSLAM_CPU_BACKEND=0`` disables
the backend. A missing or stale library (sources changed since the build) makes :func:`load_extension`
raise :class:`~mipslam.errors.BackendUnavailableError` and logs one warning; ``backend="auto"`` then renders
with torch.
"""
from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import functools
import logging
import os
import threading
import time
from pathlib import Path

import numpy as np
import torch

from mipslam.errors import BackendUnavailableError, RenderError

log = logging.getLogger("mipslam.render.cpu")

#: The C interface version this module speaks (mipslam_abi_version in raster_ext.cpp).
ABI_VERSION = 8
_ERROR_BYTES = 2048
_ERR_VALUE, _ERR_MEMORY = 1, 3
REBUILD_HINT = "run ./scripts/setup or python -m mipslam.render.cpu.build"

_p, _i64, _f64 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
_SIGNATURES = {
    "mipslam_abi_version": ([], ctypes.c_int),
    "mipslam_source_hash": ([], ctypes.c_char_p),
    "mipslam_build_info": ([], ctypes.c_char_p),
    "mipslam_cpu_supports_avx2_fma": ([], ctypes.c_int),
    "mipslam_rasterize_bin": ([_p] * 6 + [_i64] * 5 + [_f64, _i64] + [_p] * 4 + [_i64], ctypes.c_int),
    "mipslam_rasterize_release": ([_p], None),
    "mipslam_rasterize_forward": ([_p, _f64, _f64, _p, _p, _i64] + [_p] * 11 + [_i64], ctypes.c_int),
    "mipslam_rasterize_backward": ([_p] * 6 + [_i64] * 5 + [_f64] * 3 + [_p, _p, _i64, _p, _i64, _p, _p, _i64]
                                   + [_p] * 10 + [_i64] * 3 + [_p] * 6 + [_i64], ctypes.c_int),
    "mipslam_project_forward": ([_i64] + [_p] * 5 + [_i64, _i64] + [_p] * 3 + [_i64, _i64, _p, _i64, _i64]
                                + [_p] * 9 + [_i64], ctypes.c_int),
    "mipslam_project_backward": ([_i64] + [_p] * 5 + [_i64, _i64] + [_p] * 3 + [_i64, _i64, _p, _i64] + [_p] * 5
                                 + [_i64] * 3 + [_p] * 6 + [_i64], ctypes.c_int),
    "mipslam_vector_math": ([_p, _p, _i64, _i64], None),
    "mipslam_direct_align": ([_i64] + [_p] * 7 + [_i64, _f64, _f64, _p, _i64, ctypes.c_int, _p, _p, _p, _i64],
                             ctypes.c_int),
    "mipslam_rgbd_l1": ([_p] * 7 + [_i64, _i64, _f64, _i64, _f64, _f64, _i64, _f64] + [_p] * 4, ctypes.c_int),
    "mipslam_ssim": ([_p] * 3 + [_i64] * 3 + [_p, _i64, _f64, _f64, _f64, _i64, _p, _p, _p, _i64], ctypes.c_int),
    "mipslam_ssim_moments": ([_p, _i64, _i64, _i64, _p, _i64, _i64, _p, _p, _i64], ctypes.c_int),
    "mipslam_frustum_rows": ([_p, _p, _i64, _p, _p, _p, _p], ctypes.c_int),
    "mipslam_guided_match": ([_p, _i64, _p, _p, _i64, _f64, _p, _p, _i64, _f64, _i64, _p, _p, _p, _i64], ctypes.c_int),
}


# [16] indices into (W row-major [9], t [3], 0) that give the 4x4 viewmat gradient [[W, t], [0, 0, 0, 0]].
_VIEWMAT_LAYOUT = torch.tensor([0, 1, 2, 9, 3, 4, 5, 10, 6, 7, 8, 11, 12, 12, 12, 12])


@functools.lru_cache(maxsize=64)
def _param_array(params: tuple) -> ctypes.Array:
    """The projection's parameter vector as a C double array (one per option set; read-only in C)."""
    return (ctypes.c_double * len(params))(*params)


def _ptr(t: torch.Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


def _c_array(ctype, values) -> ctypes.Array:
    """A C array of ``values`` (at least one element, so an empty list still passes a valid pointer)."""
    values = list(values)
    return (ctype * max(1, len(values)))(*values)


def _check(t: torch.Tensor, name: str, dtype: torch.dtype, shape: tuple) -> None:
    """The C side trusts these: wrong ones would read out of bounds. (Sub-microsecond attribute tests: this
    runs ~40 times per render.)"""
    if not t.is_cpu or t.dtype != dtype or not t.is_contiguous() or t.shape != shape:
        raise RuntimeError(f"mipslam cpu rasterizer: {name} must be a contiguous CPU {dtype} tensor of shape "
                           f"{list(shape)}, got {t.dtype} {list(t.shape)} on {t.device}")


class Library:
    """One loaded build of the rasterizer (``isa``: "baseline" or "avx2"), called with tensors.

    The methods take and return tensors like the functions of raster_ext.cpp's C interface, which they wrap.
    """

    def __init__(self, path: Path, isa: str):
        self.path, self.isa = Path(path), isa
        self._lib = ctypes.CDLL(str(path))
        for name, (args, result) in _SIGNATURES.items():
            function = getattr(self._lib, name)
            function.argtypes, function.restype = args, result
        self.__file__ = str(path)

    # --- identity -----------------------------------------------------------------------------------
    def abi_version(self) -> int:
        return int(self._lib.mipslam_abi_version())

    def source_hash(self) -> str:
        return self._lib.mipslam_source_hash().decode()

    def build_info(self) -> str:
        """Instruction sets the library was compiled for, e.g. ``"avx2 fma sse2 openmp"``."""
        return self._lib.mipslam_build_info().decode()

    def cpu_supports_avx2_fma(self) -> bool:
        return bool(self._lib.mipslam_cpu_supports_avx2_fma())

    def _call(self, function, *args) -> None:
        err = ctypes.create_string_buffer(_ERROR_BYTES)
        code = function(*args, err, _ERROR_BYTES)
        if code:
            message = err.value.decode(errors="replace")
            if code == _ERR_VALUE:
                raise RenderError(message)
            if code == _ERR_MEMORY:
                raise MemoryError(message)
            raise RuntimeError(message)

    # --- fused projection (projection.h) ------------------------------------------------------------
    def _projection_inputs(self, means, quats, scales, opacities, colors, viewmat, K, rate):
        dtype = means.dtype
        if dtype not in (torch.float32, torch.float64):
            raise RuntimeError(f"mipslam fused projection: float32 or float64 inputs, got {dtype}")
        n = means.shape[0]
        tensors = [t.contiguous() for t in (means, quats, scales, opacities, colors, viewmat, K)]
        if rate is not None:
            tensors.append(rate.contiguous())
        if colors.dim() != 2:
            raise RuntimeError("mipslam fused projection: colors must be [N, C]")
        shapes = [(n, 3), (n, 4), (n, 3), (n,), (n, colors.shape[1]), (4, 4), (3, 3), (n,)]
        for t, name, shape in zip(tensors, ("means", "quats", "scales", "opacities", "colors", "viewmat", "K",
                                            "max_sampling_rate"), shapes):
            _check(t, name, dtype, shape)
        if rate is None:
            tensors.append(None)
        return tensors

    def project_forward(self, means, quats, scales, opacities, colors, viewmat, K, rate, width: int, height: int,
                        params: tuple, threads: int):
        """-> means2d [N, 2], depths [N], cov [N, 4], opacity [N], node_counts [N] int32, visible [N] bool,
        radii [N], n_visible (int); floating outputs in the means' dtype."""
        ins = self._projection_inputs(means, quats, scales, opacities, colors, viewmat, K, rate)
        n, dtype = means.shape[0], means.dtype
        means2d, cov = torch.empty(n, 2, dtype=dtype), torch.empty(n, 4, dtype=dtype)
        depth, opacity, radii = (torch.empty(n, dtype=dtype) for _ in range(3))
        nodes, visible = torch.empty(n, dtype=torch.int32), torch.empty(n, dtype=torch.bool)
        p = _param_array(params)
        n_visible = ctypes.c_int64(0)
        self._call(self._lib.mipslam_project_forward, int(dtype == torch.float64), *map(_ptr, ins[:5]), n,
                   colors.shape[1], *map(_ptr, ins[5:]), int(width), int(height), p, len(params), int(threads),
                   *map(_ptr, (means2d, depth, cov, opacity, nodes, visible, radii)), ctypes.byref(n_visible))
        return means2d, depth, cov, opacity, nodes, visible, radii, int(n_visible.value)

    def project_backward(self, means, quats, scales, opacities, colors, viewmat, K, rate, width: int, height: int,
                         params: tuple, visible, g_means2d, g_depths, g_cov, g_opacity, need_params: bool,
                         need_viewmat: bool, threads: int):
        """Gradients of means [N, 3], quats [N, 4], scales [N, 3], opacities [N] (None unless need_params) and
        viewmat [4, 4] (None unless need_viewmat) from those of project_forward's outputs (None = zero)."""
        ins = self._projection_inputs(means, quats, scales, opacities, colors, viewmat, K, rate)
        n, dtype = means.shape[0], means.dtype
        _check(visible, "visible", torch.bool, (n,))
        grads = []
        for g, name, shape in ((g_means2d, "grad_means2d", (n, 2)), (g_depths, "grad_depth", (n,)),
                               (g_cov, "grad_cov", (n, 4)), (g_opacity, "grad_opacity", (n,))):
            if g is not None:
                g = g.contiguous()
                _check(g, name, dtype, shape)
            grads.append(g)
        outs = [torch.empty(n, 3, dtype=dtype), torch.empty(n, 4, dtype=dtype), torch.empty(n, 3, dtype=dtype),
                torch.empty(n, dtype=dtype)] if need_params else [None] * 4
        g_view = torch.zeros(13, dtype=torch.float64)  # rotation row-major, translation; [12] stays 0
        p = _param_array(params)
        self._call(self._lib.mipslam_project_backward, int(dtype == torch.float64), *map(_ptr, ins[:5]), n,
                   colors.shape[1], *map(_ptr, ins[5:]), int(width), int(height), p, len(params), _ptr(visible),
                   *map(_ptr, grads), int(need_params), int(need_viewmat), int(threads), *map(_ptr, outs),
                   _ptr(g_view))
        g_viewmat = g_view[_VIEWMAT_LAYOUT].view(4, 4).to(dtype) if need_viewmat else None
        return (*outs, g_viewmat)

    # --- direct RGB-D alignment (direct_align.h) -----------------------------------------------------
    def direct_align(self, levels: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, tuple[float, ...]]],
                     T_init: torch.Tensor, iterations: int, alpha_color: float, convergence: float,
                     constants: tuple[float, ...], threads: int = 1) -> tuple[torch.Tensor, int, int, bool]:
        """Gauss-Newton alignment over pyramid ``levels``, coarse to fine, each (points [n, 3], intensity [n],
        channels [7, h, w], (fx, fy, cx, cy)), float32, on ``threads`` threads (the result does not depend on
        them). -> (T [4, 4] float64, steps, residuals used, ran)."""
        count = len(levels)
        tensors = []
        for points, intensity, channels, _ in levels:
            n = points.shape[0]
            _check(points, "points", torch.float32, (n, 3))
            _check(intensity, "intensity", torch.float32, (n,))
            if channels.dim() != 3 or channels.shape[0] != 7:
                raise RuntimeError(f"mipslam direct alignment: channels must be [7, h, w], got {list(channels.shape)}")
            _check(channels, "channels", torch.float32, tuple(channels.shape))
            tensors.append((points, intensity, channels))
        points, intensities, channels = zip(*tensors) if tensors else ((), (), ())
        intrinsics = _c_array(ctypes.c_float, [float(k) for level in levels for k in level[3]])
        T = T_init.detach().to(torch.float64).cpu().contiguous().clone()
        stats = torch.zeros(3, dtype=torch.int64)
        self._call(self._lib.mipslam_direct_align, count, _c_array(ctypes.c_void_p, map(_ptr, points)),
                   _c_array(ctypes.c_void_p, map(_ptr, intensities)), _c_array(ctypes.c_int64, (p.shape[0] for p in points)),
                   _c_array(ctypes.c_void_p, map(_ptr, channels)), _c_array(ctypes.c_int64, (c.shape[1] for c in channels)),
                   _c_array(ctypes.c_int64, (c.shape[2] for c in channels)), intrinsics, int(iterations),
                   float(alpha_color), float(convergence), _c_array(ctypes.c_double, constants), len(constants),
                   int(threads), _ptr(T), _ptr(stats))
        return T, int(stats[0]), int(stats[1]), bool(stats[2])

    # --- the frustum test of tracking's and mapping's map subsets (raster_ext.cpp) ------------------------
    def frustum_rows(self, means: torch.Tensor, scales: torch.Tensor, view: tuple[float, ...],
                     limits: tuple[float, ...]) -> torch.Tensor:
        """Rows of the Gaussians a view can draw, increasing: means and scales [N, 3] float32 (CPU), ``view`` = 12
        numbers of R_cw (row-major) and t_cw, then fx, fy, cx, cy; ``limits`` = width, height, near (m),
        k_sigma, pad (px). -> [M] int64, as :func:`mipslam.rendering.frustum_indices_reference` decides."""
        n = means.shape[0]
        means, scales = means.detach().contiguous(), scales.detach().contiguous()
        _check(means, "means", torch.float32, (n, 3))
        _check(scales, "scales", torch.float32, (n, 3))
        if len(view) != 16 or len(limits) != 5:
            raise RuntimeError(f"mipslam frustum rows: {len(view)} view and {len(limits)} limit numbers (16 and 5)")
        rows = torch.empty(max(1, n), dtype=torch.int64)
        count = np.zeros(1, dtype=np.int64)
        self._call(self._lib.mipslam_frustum_rows, _ptr(means), _ptr(scales), n, _c_array(ctypes.c_double, view),
                   _c_array(ctypes.c_double, limits), _ptr(rows), count.ctypes.data)
        return rows[: int(count[0])].clone()

    # --- the front-end's guided matching (feature_match.h) ---------------------------------------------
    def guided_match(self, keypoints, projections, projection_ids, limit: float, query, train, ratio: float,
                     max_hamming: int):
        """Mutual, ratio-tested Hamming matches between keypoints [M, 2] and the reference points whose projections
        [P, 2] (px, float64; projection_ids [P] int64 into train) lie within ``limit`` px of them; query [M, 32]
        and train [N, 32] uint8 ORB descriptors (numpy arrays). -> [K, 2] int64 (keypoint, reference point) pairs
        by keypoint, as :func:`mipslam.frontend._match_candidates` on :func:`mipslam.frontend._projection_gate`'s pairs."""
        keypoints = np.ascontiguousarray(keypoints, dtype=np.float64).reshape(-1, 2)
        projections = np.ascontiguousarray(projections, dtype=np.float64).reshape(-1, 2)
        projection_ids = np.ascontiguousarray(projection_ids, dtype=np.int64).reshape(-1)
        query = np.ascontiguousarray(query, dtype=np.uint8).reshape(-1, 32)
        train = np.ascontiguousarray(train, dtype=np.uint8).reshape(-1, 32)
        if len(projection_ids) != len(projections) or len(query) != len(keypoints):
            raise RuntimeError(f"mipslam guided matching: {len(projections)} projections with {len(projection_ids)} "
                               f"ids, {len(keypoints)} keypoints with {len(query)} descriptors")
        pairs = np.empty((max(1, len(keypoints)), 2), dtype=np.int64)
        count = np.zeros(1, dtype=np.int64)
        self._call(self._lib.mipslam_guided_match, keypoints.ctypes.data, len(keypoints), projections.ctypes.data,
                   projection_ids.ctypes.data, len(projections), float(limit), query.ctypes.data, train.ctypes.data,
                   len(train), float(ratio), int(max_hamming), pairs.ctypes.data, count.ctypes.data)
        return pairs[: int(count[0])].copy()

    # --- the masked RGB-D L1 loss (rgbd_loss.h) -------------------------------------------------------
    def rgbd_l1(self, color, depth, alpha, color_gt, depth_gt, mask_color, mask_depth, *, alpha_color: float,
                exposure: tuple[float, float] | None, depth_normalise: bool, depth_alpha_floor: float,
                gradients: bool):
        """The loss of rgbd_loss.h: color, color_gt [H, W, C], depth, depth_gt [H, W] float32, alpha [H, W] float32
        (None without ``depth_normalise``), masks [H, W] bool; ``exposure`` (gain, bias) as float32 values or None.
        -> (out [5] float32: total, colour term, depth term, d/d log_gain, d/d bias; counts [2] int64: colour and
        depth pixels; grad_color [H, W, C] and grad_depth [H, W], or None without ``gradients``)."""
        height, width, channels = color.shape
        if depth_normalise and alpha is None:
            raise RuntimeError("mipslam rgbd_l1: depth_normalise needs the render's opacity")
        for t, name, dtype, shape in ((color, "color", torch.float32, (height, width, channels)),
                                      (color_gt, "color_gt", torch.float32, (height, width, channels)),
                                      (depth, "depth", torch.float32, (height, width)),
                                      (alpha, "alpha", torch.float32, (height, width)),
                                      (depth_gt, "depth_gt", torch.float32, (height, width)),
                                      (mask_color, "mask_color", torch.bool, (height, width)),
                                      (mask_depth, "mask_depth", torch.bool, (height, width))):
            if t is not None:
                _check(t, name, dtype, shape)
        out, counts = torch.empty(5, dtype=torch.float32), torch.empty(2, dtype=torch.int64)
        grad_color = torch.empty_like(color) if gradients else None
        grad_depth = torch.empty_like(depth) if gradients else None
        gain, bias = (1.0, 0.0) if exposure is None else exposure
        self._call(self._lib.mipslam_rgbd_l1, *map(_ptr, (color, depth, alpha, color_gt, depth_gt, mask_color,
                                                          mask_depth)), height * width, channels, float(alpha_color),
                   int(exposure is not None), float(gain), float(bias), int(depth_normalise),
                   float(depth_alpha_floor), _ptr(out), _ptr(counts), _ptr(grad_color), _ptr(grad_depth))
        return out, counts, grad_color, grad_depth

    # --- SSIM (ssim_loss.h) --------------------------------------------------------------------------
    @staticmethod
    def _ssim_inputs(target: torch.Tensor, window: torch.Tensor) -> tuple[int, int, int]:
        if target.dim() != 3:
            raise RuntimeError(f"mipslam ssim: images must be [H, W, C], got {list(target.shape)}")
        shape = tuple(target.shape)
        _check(target, "target", torch.float32, shape)
        _check(window, "window", torch.float32, (window.shape[0],))
        return shape

    def ssim(self, image: torch.Tensor, target: torch.Tensor, target_moments: torch.Tensor | None,
             window: torch.Tensor, c1: float, c2: float, *, gradients: bool, grad_scale: float = 1.0,
             threads: int = 1) -> tuple[float, torch.Tensor | None]:
        """Mean SSIM of image and target [H, W, C] float32 with zero "same" padding, the separable window [taps]
        float32 (odd taps, symmetric) and constants c1, c2; ``target_moments`` [2, H, W, C] from
        :meth:`ssim_moments` with the same window, or None. -> (mean as a float, ``grad_scale`` times its gradient
        with respect to the image [H, W, C], or None without ``gradients``)."""
        shape = self._ssim_inputs(target, window)
        _check(image, "image", torch.float32, shape)
        if target_moments is not None:
            _check(target_moments, "target_moments", torch.float32, (2, *shape))
        grad = torch.empty(shape, dtype=torch.float32) if gradients else None
        out = ctypes.c_double(0.0)
        self._call(self._lib.mipslam_ssim, _ptr(image), _ptr(target), _ptr(target_moments), *shape, _ptr(window),
                   window.shape[0], float(c1), float(c2), float(grad_scale), int(threads), ctypes.byref(out),
                   _ptr(grad))
        return out.value, grad

    def ssim_moments(self, target: torch.Tensor, window: torch.Tensor, threads: int = 1) -> torch.Tensor:
        """The target's SSIM moments [2, H, W, C] float32: the blurred target and its blurred square (zero padding,
        the separable ``window`` [taps] float32), which :meth:`ssim` takes as ``target_moments``."""
        shape = self._ssim_inputs(target, window)
        moments = torch.empty((2, *shape), dtype=torch.float32)
        self._call(self._lib.mipslam_ssim_moments, _ptr(target), *shape, _ptr(window), window.shape[0], int(threads),
                   _ptr(moments))
        return moments

    # --- tile rasterizer ------------------------------------------------------------------------------
    @staticmethod
    def _raster_inputs(means2d, cov, opacity, depth, colors, node_counts, gl_nodes, gl_weights):
        n = means2d.shape[0]
        if colors.dim() != 2:
            raise RuntimeError("mipslam cpu rasterizer: colors must be [N, C]")
        for t, name, shape, dtype in ((means2d, "means2d", (n, 2), torch.float32), (cov, "cov", (n, 4), torch.float32),
                                      (opacity, "opacity", (n,), torch.float32), (depth, "depth", (n,), torch.float32),
                                      (colors, "colors", (n, colors.shape[1]), torch.float32),
                                      (node_counts, "node_counts", (n,), torch.int32),
                                      (gl_weights, "gl_weights", tuple(gl_nodes.shape), torch.float32)):
            _check(t, name, dtype, shape)
        if gl_nodes.dim() != 1:
            raise RuntimeError("mipslam cpu rasterizer: gl_nodes must be 1-D")
        return n, colors.shape[1]

    def rasterize_forward(self, means2d, cov, opacity, depth, colors, node_counts, mode_id: int, width: int,
                          height: int, k_sigma: float, eta: float, tau: float, gl_nodes, gl_weights, threads: int):
        """-> color [H, W, C], depth [H, W], alpha [H, W], then the state the backward needs (order [M],
        tile_offsets, isect_ids [P], pair_offsets [M + 1], isect_pos [P], last [H, W]; int32) and stats [2]
        int64 (footprint lanes evaluated, pairs)."""
        n, C = self._raster_inputs(means2d, cov, opacity, depth, colors, node_counts, gl_nodes, gl_weights)
        state, count, pairs = ctypes.c_void_p(), ctypes.c_int64(), ctypes.c_int64()
        self._call(self._lib.mipslam_rasterize_bin, *map(_ptr, (means2d, cov, opacity, depth, colors, node_counts)),
                   n, C, int(mode_id), int(width), int(height), float(k_sigma), int(threads), ctypes.byref(state),
                   ctypes.byref(count), ctypes.byref(pairs))
        try:
            m, p = count.value, pairs.value
            tiles = ((width + 15) // 16) * ((height + 15) // 16)
            i32 = dict(dtype=torch.int32)
            order, tile_offsets, isect_ids = torch.empty(m, **i32), torch.empty(tiles + 1, **i32), torch.empty(p, **i32)
            pair_offsets, isect_pos = torch.empty(m + 1, **i32), torch.empty(p, **i32)
            color = torch.empty(height, width, C)
            depth_img, alpha_img = torch.empty(height, width), torch.empty(height, width)
            last = torch.empty(height, width, **i32)
            stats = torch.zeros(2, dtype=torch.int64)
            self._call(self._lib.mipslam_rasterize_forward, state, float(eta), float(tau), _ptr(gl_nodes),
                       _ptr(gl_weights), gl_nodes.shape[0],
                       *map(_ptr, (order, tile_offsets, isect_ids, pair_offsets, isect_pos, color, depth_img,
                                   alpha_img, last, stats)))
        finally:
            self._lib.mipslam_rasterize_release(state)
        return color, depth_img, alpha_img, order, tile_offsets, isect_ids, pair_offsets, isect_pos, last, stats

    def rasterize_backward(self, means2d, cov, opacity, depth, colors, node_counts, mode_id: int, width: int,
                           height: int, k_sigma: float, eta: float, tau: float, gl_nodes, gl_weights, order,
                           tile_offsets, isect_ids, pair_offsets, isect_pos, last, color, depth_img, alpha_img,
                           grad_color, grad_depth, grad_alpha, need_color_grad: bool, need_opacity_grad: bool,
                           threads: int, grad_color_appearance: torch.Tensor | None = None):
        """Gradient of sum(grad_color * color + grad_depth * depth + grad_alpha * alpha) with respect to
        means2d [N, 2], cov [N, 4], opacity [N], depth [N], colors [N, C] (in this order).

        grad_color_appearance [H, W, C] or None: a second colour-image gradient that only the colours take, as if
        the image it multiplies had been rendered with the geometry held fixed (an appearance-only loss)."""
        n, C = self._raster_inputs(means2d, cov, opacity, depth, colors, node_counts, gl_nodes, gl_weights)
        m, p = order.shape[0], isect_ids.shape[0]
        tiles = ((width + 15) // 16) * ((height + 15) // 16)
        for t, name, shape, dtype in (
                (order, "order", (m,), torch.int32), (tile_offsets, "tile_offsets", (tiles + 1,), torch.int32),
                (isect_ids, "isect_ids", (p,), torch.int32), (pair_offsets, "pair_offsets", (m + 1,), torch.int32),
                (isect_pos, "isect_pos", (p,), torch.int32), (last, "last", (height, width), torch.int32),
                (color, "color", (height, width, C), torch.float32),
                (depth_img, "depth", (height, width), torch.float32),
                (alpha_img, "alpha", (height, width), torch.float32),
                (grad_color, "grad_color", (height, width, C), torch.float32),
                (grad_depth, "grad_depth", (height, width), torch.float32),
                (grad_alpha, "grad_alpha", (height, width), torch.float32)):
            _check(t, name, dtype, shape)
        if grad_color_appearance is not None:
            _check(grad_color_appearance, "grad_color_appearance", torch.float32, (height, width, C))
        # One zero-filled block, cut into the five contiguous outputs: five torch.zeros of a tracking subset's size
        # cost ten times one (0.7 against 0.07 ms at 80000 Gaussians), on every backward.
        block = torch.zeros(n * (8 + C))
        sizes = (2 * n, 4 * n, n, n, C * n)
        outs = tuple(part.view(shape) for part, shape in zip(block.split(sizes), ((n, 2), (n, 4), (n,), (n,), (n, C))))
        self._call(self._lib.mipslam_rasterize_backward,
                   *map(_ptr, (means2d, cov, opacity, depth, colors, node_counts)), n, C, int(mode_id), int(width),
                   int(height), float(k_sigma), float(eta), float(tau), _ptr(gl_nodes), _ptr(gl_weights),
                   gl_nodes.shape[0], _ptr(order), m, _ptr(tile_offsets), _ptr(isect_ids), p,
                   *map(_ptr, (pair_offsets, isect_pos, last, color, depth_img, alpha_img, grad_color, grad_depth,
                               grad_alpha)), None if grad_color_appearance is None else _ptr(grad_color_appearance),
                   int(need_color_grad), int(need_opacity_grad), int(threads),
                   *map(_ptr, outs))
        return outs

    def vector_math(self, x: torch.Tensor, which: int) -> torch.Tensor:
        """Test hook: the kernels' vector exp (which = 0) or erf (1) of a 1-D float32 tensor."""
        _check(x, "x", torch.float32, (x.shape[0],))
        y = torch.empty_like(x)
        self._lib.mipslam_vector_math(_ptr(x), _ptr(y), x.shape[0], int(which))
        return y


# ------------------------------------------------------------------------------------------------
# Loading (once per process)
# ------------------------------------------------------------------------------------------------
#: Where the built libraries are looked for: next to the sources (setup.py and build.py put them there).
LIBRARY_DIR = Path(__file__).resolve().parent
_lock = threading.Lock()
_state: dict = {"library": None, "reason": None, "tried": False, "timed": None}


def _disabled() -> bool:
    return os.environ.get("MIPSLAM_CPU_BACKEND", "1").strip().lower() in ("0", "false", "off", "no")


def load_library(isa: str, folder: Path | None = None) -> Library:
    """Load the build of ``isa`` from ``folder`` (default :data:`LIBRARY_DIR`) after checking that it is current and speaks this ABI.
    Raises BackendUnavailableError with the reason."""
    from mipslam.render.cpu import build  # here, so that python -m mipslam.render.cpu.build runs it fresh

    folder = LIBRARY_DIR if folder is None else Path(folder)
    path = build.library_path(isa, folder)
    if not path.is_file():
        raise BackendUnavailableError(f"the C++ rasterizer is not built ({path.name} is missing; {REBUILD_HINT})")
    try:
        library = Library(path, isa)
    except (OSError, AttributeError) as exc:
        raise BackendUnavailableError(f"cannot load {path}: {exc} ({REBUILD_HINT})") from None
    if library.abi_version() != ABI_VERSION or library.source_hash() != build.source_hash(isa, folder):
        raise BackendUnavailableError(f"{path.name} was built from other sources than those next to it "
                                      f"({REBUILD_HINT})")
    return library


def _load() -> Library:
    from mipslam.render.cpu import build

    if _disabled():
        raise BackendUnavailableError("the cpu backend is disabled by MIPSLAM_CPU_BACKEND=0")
    baseline = load_library("baseline")
    wanted = os.environ.get("MIPSLAM_CPU_ISA", "auto").strip().lower() or "auto"
    if wanted not in ("auto", "baseline", "avx2"):
        raise BackendUnavailableError(f"MIPSLAM_CPU_ISA must be auto, baseline or avx2, got '{wanted}'")
    if wanted == "baseline" or "avx2" not in build.isas():
        return baseline
    if not baseline.cpu_supports_avx2_fma():
        if wanted == "avx2":
            raise BackendUnavailableError("MIPSLAM_CPU_ISA=avx2 but this CPU lacks AVX2 or FMA")
        return baseline
    try:
        return load_library("avx2")
    except BackendUnavailableError as exc:
        if wanted == "avx2":
            raise
        log.warning("using the baseline build of the C++ rasterizer (slower): %s", exc)
        return baseline


def load_extension() -> Library:
    """The loaded library (loaded on the first call, in milliseconds; never compiled here). Raises
    BackendUnavailableError with the reason, after one logged warning per process."""
    timed = _state["timed"]
    if timed is not None:
        return timed
    library = _state["library"]
    if library is not None:
        return library
    with _lock:
        if _state["library"] is not None:
            return _state["library"]
        if _state["tried"]:
            raise BackendUnavailableError(f"the cpu backend is not available: {_state['reason']}")
        _state["tried"] = True
        try:
            _state["library"] = _load()
        except BackendUnavailableError as exc:
            _state["reason"] = str(exc)
            log.warning("mipslam's compiled CPU library is unavailable (CPU rendering falls back to the torch backend, "
                        "the feature front-end's matching to numpy): %s", _state["reason"])
            raise BackendUnavailableError(f"the cpu backend is not available: {_state['reason']}") from None
        return _state["library"]


def warm_up() -> bool:
    """Load the backend now (the pipeline calls this before its frame loop, so no stage is charged for it).
    Returns whether it is available; never raises for a missing build (that is logged once)."""
    return is_available()


def is_available() -> bool:
    """True if the library is built, current and loaded."""
    try:
        load_extension()
    except BackendUnavailableError:
        return False
    return True


def unavailable_reason() -> str | None:
    """Why the library cannot be used (None when it is available)."""
    return None if is_available() else _state["reason"]


@contextlib.contextmanager
def using(library: Library):
    """Make ``library`` the one every call uses inside the block (tests: the baseline build). Not thread-safe."""
    saved = dict(_state)
    _state.update(library=library, reason=None, tried=True, timed=None)
    try:
        yield library
    finally:
        _state.clear()
        _state.update(saved)


def _reset_for_tests() -> None:
    """Forget the load attempt (tests change the environment and load again)."""
    with _lock:
        _state.update(library=None, reason=None, tried=False, timed=None)


# ------------------------------------------------------------------------------------------------
# Kernel timing (benchmarks)
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class KernelTimes:
    """Time spent inside the library's functions, per function name: wall seconds, process CPU seconds (all
    threads: core-seconds, robust to a loaded machine) and call counts."""

    seconds: dict
    cpu_seconds: dict
    calls: dict

    @property
    def total(self) -> float:
        """Wall seconds inside the library."""
        return sum(self.seconds.values())

    @property
    def total_cpu(self) -> float:
        """Process CPU seconds inside the library."""
        return sum(self.cpu_seconds.values())


class _TimedExtension:
    """The library with every tensor-level call timed (wall and process CPU seconds, call count per name)."""

    def __init__(self, library: Library, times: KernelTimes):
        self._library, self._times = library, times

    def __getattr__(self, name):
        attr = getattr(self._library, name)
        if not callable(attr):
            return attr

        def timed(*args, **kwargs):
            start, start_cpu = time.perf_counter(), time.process_time()
            try:
                return attr(*args, **kwargs)
            finally:
                times = self._times
                times.seconds[name] = times.seconds.get(name, 0.0) + time.perf_counter() - start
                times.cpu_seconds[name] = times.cpu_seconds.get(name, 0.0) + time.process_time() - start_cpu
                times.calls[name] = times.calls.get(name, 0) + 1

        return timed


@contextlib.contextmanager
def profile_kernels():
    """Time every call into the library made inside the block (benchmarks: kernel time against the whole
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
