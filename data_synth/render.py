"""Vectorised ray casting of a :class:`~data_synth.scene.Scene` at any pose and intrinsics.

Colour is the box-filtered pixel-footprint average: pixel (u, v) covers the unit square
``[u-0.5, u+0.5] x [v-0.5, v+0.5]`` (docs/design.md), which is split into ``S x S`` equal strata; one
ray through the centre of each stratum, ``(u - 0.5 + (i + 0.5) / S, v - 0.5 + (j + 0.5) / S)``,
and the colour is the mean radiance of the ``S^2`` rays (a midpoint rule of the footprint
integral, error -> 0 as S grows). Depth is exact: the camera-frame z of the surface hit by the
pixel-centre ray. Rays are built in the camera frame with ``z = 1`` (OpenCV axes: x right,
y down, z forward) and rotated into the world, so the ray parameter of a hit is its depth.
"""
from __future__ import annotations

import logging
from typing import Any

import numpy as np

from data_synth.scene import Rays, Scene
from mipslam.errors import RenderError

logger = logging.getLogger(__name__)

MAX_SUPERSAMPLE = 16


def _pose_array(T_wc: Any) -> np.ndarray:
    """Camera-to-world pose as float64 numpy.  T_wc [4, 4] (numpy or torch) -> [4, 4]"""
    if hasattr(T_wc, "detach"):
        T_wc = T_wc.detach().cpu().numpy()
    T = np.asarray(T_wc, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise RenderError(f"T_wc must be a finite 4x4 camera-to-world matrix, got shape {T.shape}")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or abs(np.linalg.det(R) - 1) > 1e-6:
        raise RenderError("T_wc's rotation block is not a rotation (R^T R != I or det R != 1)")
    return T


def _intrinsics_tuple(intrinsics: Any) -> tuple[float, float, float, float, int, int]:
    try:
        fx, fy = float(intrinsics.fx), float(intrinsics.fy)
        cx, cy = float(intrinsics.cx), float(intrinsics.cy)
        width, height = int(intrinsics.width), int(intrinsics.height)
    except AttributeError as error:
        raise RenderError(f"intrinsics need fx, fy, cx, cy, width, height (e.g. mipslam.types.Intrinsics): {error}") from error
    if not (fx > 0 and fy > 0 and width >= 1 and height >= 1):
        raise RenderError(f"invalid intrinsics fx={fx} fy={fy} width={width} height={height}")
    return fx, fy, cx, cy, width, height


def _world_rays(R: np.ndarray, origin: np.ndarray, x: np.ndarray, y: np.ndarray) -> Rays:
    """Rays from the camera centre along camera-frame directions (x, y, 1).  x [M], y [M]"""
    d = tuple(R[k, 0] * x + R[k, 1] * y + R[k, 2] for k in range(3))
    return Rays(None, components=(origin[0:1], origin[1:2], origin[2:3], *d))


def stratum_offsets(supersample: int) -> np.ndarray:
    """Offsets of the stratum centres from the pixel centre.  -> [S] in (-0.5, 0.5)"""
    return (np.arange(supersample, dtype=np.float64) + 0.5) / supersample - 0.5


def render_view(scene: Scene, T_wc: Any, intrinsics: Any, *, supersample: int = 4,
                max_rays_per_chunk: int = 1 << 18) -> tuple[np.ndarray, np.ndarray]:
    """Render colour and exact depth of ``scene`` seen from camera-to-world pose ``T_wc``.

    T_wc: [4, 4] float64 (numpy array or torch tensor), OpenCV camera axes.
    intrinsics: any object with fx, fy, cx, cy (pixels, centres at integers), width, height
    (e.g. :class:`mipslam.types.Intrinsics`; use ``.scaled(f)`` for other resolutions).
    supersample: S, the footprint is integrated with S x S stratified rays (1 = point sampling).
    Returns ``(color [H, W, 3] float32 in [0, 1], depth [H, W] float32 metres, 0 where no surface)``
    as numpy arrays (``torch.from_numpy`` wraps them without a copy).
    """
    if not (isinstance(supersample, (int, np.integer)) and 1 <= supersample <= MAX_SUPERSAMPLE):
        raise RenderError(f"supersample must be an integer in 1..{MAX_SUPERSAMPLE}, got {supersample!r}")
    T = _pose_array(T_wc)
    fx, fy, cx, cy, width, height = _intrinsics_tuple(intrinsics)
    R, origin = T[:3, :3], T[:3, 3]
    offsets = stratum_offsets(int(supersample))
    du = np.tile(offsets, supersample)  # [S^2], u offset varies fastest
    dv = np.repeat(offsets, supersample)  # [S^2]
    n_sub = supersample * supersample
    rows_per_chunk = max(1, int(max_rays_per_chunk) // (width * (n_sub + 1)))

    color = np.zeros((height, width, 3), dtype=np.float32)
    depth = np.zeros((height, width), dtype=np.float32)
    u = np.arange(width, dtype=np.float64)
    missed = 0
    for r0 in range(0, height, rows_per_chunk):
        r1 = min(height, r0 + rows_per_chunk)
        v = np.arange(r0, r1, dtype=np.float64)
        rows = r1 - r0
        # Footprint rays: [rows, W, S^2] directions in the camera frame with z = 1.
        # Footprint rays: [rows, W, S^2] directions in the camera frame (x, y, 1), rotated to the world.
        x = (u[None, :, None] + du[None, None, :] - cx) / fx
        y = (v[:, None, None] + dv[None, None, :] - cy) / fy
        x, y = (np.ascontiguousarray(a).ravel() for a in np.broadcast_arrays(x, y))
        t, prim, face = scene.trace_rays(_world_rays(R, origin, x, y))
        hit = np.isfinite(t)
        t_hit = np.where(hit, t, 0.0)
        points = np.stack([origin[k] + t_hit * (R[k, 0] * x + R[k, 1] * y + R[k, 2]) for k in range(3)], axis=1)
        radiance = scene.radiance(points, prim, face)  # [M, 3], black where missed
        color[r0:r1] = radiance.reshape(rows, width, n_sub, 3).mean(axis=2).astype(np.float32)

        # Pixel-centre rays for the depth: [rows, W].
        xc, yc = (np.ascontiguousarray(a).ravel() for a in np.broadcast_arrays((u[None, :] - cx) / fx, (v[:, None] - cy) / fy))
        t_centre, _, _ = scene.trace_rays(_world_rays(R, origin, xc, yc))
        finite = np.isfinite(t_centre)
        missed += int((~finite).sum())
        depth[r0:r1] = np.where(finite, t_centre, 0.0).reshape(rows, width).astype(np.float32)
    if missed:
        logger.warning("%d pixel-centre rays hit nothing (is the camera outside the room?); their depth is 0", missed)
    np.clip(color, 0.0, 1.0, out=color)
    return color, depth
