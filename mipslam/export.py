"""Mesh export: fuse the map's rendered colour and depth at the keyframes into a TSDF and extract a triangle mesh.

``mipslam export RUN_DIR --mesh mesh.ply``. For every keyframe of ``keyframes.txt`` (final keyframe poses ``T_wc``)
the map (``map.ply``) is rendered at ``scale`` times the mapping resolution (``run.json``) with the run's render
config; pixels whose accumulated opacity is at least ``min_alpha`` contribute their alpha-normalised depth
``sum(T alpha z) / alpha`` and colour ``C / alpha`` (the rest are left out, so half-transparent edges add no
surface). The views are integrated into an Open3D ``ScalableTSDFVolume`` (Curless and Levoy, 1996; RGB8
colour; see :func:`fuse_tsdf` for the VoxelBlockGrid fallback) with the pinhole intrinsics (pixel centres at
integers, as Open3D and OpenCV use) and extrinsic ``T_cw``; marching cubes gives the mesh, written atomically
in the format of the file's extension (.ply, .obj, .off, .stl, .gltf, .glb).

Voxel size: given, else 4 pixel footprints at the median rendered depth, ``4 * median(z) / fx``, clamped to
[0.005, 0.1] m; truncation distance: given, else 4 voxels; depth beyond ``depth_max`` (default: no limit) is
ignored.
"""
from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mipslam.errors import BackendUnavailableError, EvaluationError, MipslamError
from mipslam.evaluation.render_eval import load_render_context
from mipslam.geometry import se3_inverse
from mipslam.io.run_folder import RunFolder
from mipslam.io.tum import read_tum_trajectory
from mipslam.rendering import render_view

logger = logging.getLogger(__name__)

__all__ = ["MeshExportResult", "RenderedKeyframe", "auto_voxel_size", "export_mesh", "fuse_tsdf", "render_keyframes"]

VOXEL_PIXELS = 4.0
VOXEL_MIN_M, VOXEL_MAX_M = 0.005, 0.1
TRUNCATION_VOXELS = 4.0
MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".gltf", ".glb")


@dataclass(frozen=True)
class RenderedKeyframe:
    """One keyframe's rendering for fusion (numpy, CPU).

    color [h, w, 3] uint8; depth [h, w] float32 metres (0 = left out); T_wc [4, 4] float64.
    """

    color: np.ndarray
    depth: np.ndarray
    T_wc: np.ndarray


@dataclass(frozen=True)
class MeshExportResult:
    path: Path
    vertices: int
    triangles: int
    keyframes: int
    voxel_size: float  # metres
    sdf_trunc: float  # metres
    width: int
    height: int
    mode: str
    method: str  # "scalable" | "voxel_block_grid" (see fuse_tsdf)

    def describe(self) -> str:
        return (f"mesh written to {self.path}: {self.vertices} vertices, {self.triangles} triangles from "
                f"{self.keyframes} keyframes rendered at {self.width}x{self.height} ({self.mode}); "
                f"voxel {self.voxel_size * 100:.2f} cm, truncation {self.sdf_trunc * 100:.2f} cm, TSDF: {self.method}")


def auto_voxel_size(median_depth: float, fx: float) -> float:
    """``4 * median_depth / fx`` (4 pixel footprints, metres), clamped to [0.005, 0.1]."""
    if not (math.isfinite(median_depth) and median_depth > 0):
        return VOXEL_MAX_M
    return float(min(VOXEL_MAX_M, max(VOXEL_MIN_M, VOXEL_PIXELS * median_depth / fx)))


def render_keyframes(context, T_wc_keyframes: np.ndarray, *, scale: float = 1.0, mode: str | None = None,
                     min_alpha: float = 0.5) -> list[RenderedKeyframe]:
    """Render colour and alpha-normalised depth of the map at each keyframe pose.  T_wc_keyframes [K, 4, 4]"""
    intrinsics = context.intrinsics.scaled(scale)
    out = []
    for T_wc in T_wc_keyframes:
        T_cw = se3_inverse(torch.tensor(np.array(T_wc), dtype=torch.float64)).to(torch.float32)  # [4, 4]
        with torch.no_grad():
            rendered = render_view(context.gaussians, T_cw, intrinsics, context.config.render, mode=mode)
        alpha = rendered.alpha.detach().cpu().to(torch.float64)  # [h, w]
        keep = alpha >= min_alpha
        safe = alpha.clamp_min(1e-6)
        depth = torch.where(keep, rendered.depth.detach().cpu().to(torch.float64) / safe, 0.0)  # [h, w]
        color = torch.where(keep[..., None], rendered.color.detach().cpu().to(torch.float64) / safe[..., None], 0.0)
        color_u8 = (color.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).numpy()
        out.append(RenderedKeyframe(np.ascontiguousarray(color_u8), depth.to(torch.float32).numpy(),
                                    np.asarray(T_wc, dtype=np.float64)))
    return out


def _import_open3d():
    try:
        import open3d
    except ImportError as error:  # OSError of a missing libusb surfaces as ImportError too
        raise BackendUnavailableError(
            f"mesh export needs Open3D, which cannot be imported ({error}); install it with 'pip install open3d-cpu' "
            "and, on Debian/Ubuntu, the system library libusb-1.0-0 (apt-get install libusb-1.0-0)") from error
    return open3d


TSDF_METHODS = ("auto", "scalable", "voxel_block_grid")


def fuse_tsdf(views: list[RenderedKeyframe], intrinsics, *, voxel_size: float, sdf_trunc: float,
              depth_max: float | None = None, method: str = "auto"):
    """Integrate the views into a TSDF and return ``(legacy TriangleMesh, method used)``.

    method: "scalable" (Open3D's ``pipelines.integration.ScalableTSDFVolume``), "voxel_block_grid" (Open3D's
    ``t.geometry.VoxelBlockGrid``, the same hashed-block TSDF in the tensor API, mesh extracted without a
    weight threshold so single views count as in the legacy volume) or "auto": ScalableTSDFVolume, and the
    VoxelBlockGrid when the former returns an empty mesh from non-empty depth (the open3d-cpu 0.20 wheel's
    ScalableTSDFVolume integrates nothing on the project's machines, even for Open3D's own tutorial inputs).
    """
    if method not in TSDF_METHODS:
        raise MipslamError(f"mesh export: TSDF method {method!r} is not one of {', '.join(TSDF_METHODS)}")
    if method in ("auto", "scalable"):
        mesh = _fuse_scalable(views, intrinsics, voxel_size, sdf_trunc, depth_max)
        if len(mesh.vertices) > 0 or method == "scalable":
            return mesh, "scalable"
        logger.warning("Open3D's ScalableTSDFVolume returned an empty mesh from %d views with depth; "
                       "fusing with its VoxelBlockGrid instead", len(views))
    return _fuse_voxel_block_grid(views, intrinsics, voxel_size, sdf_trunc, depth_max), "voxel_block_grid"


def _far(view: RenderedKeyframe, depth_max: float | None) -> float:
    return float(depth_max) if depth_max is not None else float(view.depth.max()) + 1.0


def _fuse_scalable(views, intrinsics, voxel_size, sdf_trunc, depth_max):
    o3d = _import_open3d()
    volume = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=float(voxel_size), sdf_trunc=float(sdf_trunc),
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
    camera = o3d.camera.PinholeCameraIntrinsic(int(intrinsics.width), int(intrinsics.height), float(intrinsics.fx),
                                               float(intrinsics.fy), float(intrinsics.cx), float(intrinsics.cy))
    for view in views:
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(view.color), o3d.geometry.Image(view.depth), depth_scale=1.0,
            depth_trunc=_far(view, depth_max), convert_rgb_to_intensity=False)
        volume.integrate(rgbd, camera, np.linalg.inv(view.T_wc))  # extrinsic = T_cw
    mesh = volume.extract_triangle_mesh()
    mesh.compute_vertex_normals()
    return mesh


def _fuse_voxel_block_grid(views, intrinsics, voxel_size, sdf_trunc, depth_max):
    o3d = _import_open3d()
    o3c = o3d.core
    device = o3c.Device("CPU:0")
    K = o3c.Tensor(np.array([[intrinsics.fx, 0.0, intrinsics.cx], [0.0, intrinsics.fy, intrinsics.cy],
                             [0.0, 0.0, 1.0]]), o3c.float64)
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)), voxel_size=float(voxel_size), block_resolution=16, block_count=50_000,
        device=device)
    multiplier = float(sdf_trunc) / float(voxel_size)
    for view in views:
        depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(view.depth, dtype=np.float32)))
        color = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(view.color, dtype=np.float32) / 255.0))
        T_cw = o3c.Tensor(np.linalg.inv(view.T_wc), o3c.float64)
        far = _far(view, depth_max)
        blocks = grid.compute_unique_block_coordinates(depth, K, T_cw, depth_scale=1.0, depth_max=far,
                                                       trunc_voxel_multiplier=multiplier)
        grid.integrate(blocks, depth, color, K, K, T_cw, depth_scale=1.0, depth_max=far,
                       trunc_voxel_multiplier=multiplier)
    mesh = grid.extract_triangle_mesh(weight_threshold=0.0).to_legacy()
    mesh.compute_vertex_normals()
    return mesh


def export_mesh(run_dir: str | Path, mesh_path: str | Path, *, voxel_size: float | None = None,
                sdf_trunc: float | None = None, depth_max: float | None = None, scale: float = 1.0,
                mode: str | None = None, min_alpha: float = 0.5, method: str = "auto") -> MeshExportResult:
    """Fuse the run's map rendered at its keyframes into a TSDF and write the mesh to ``mesh_path``."""
    mesh_path = Path(mesh_path)
    if mesh_path.suffix.lower() not in MESH_SUFFIXES:
        raise MipslamError(f"{mesh_path}: unknown mesh format '{mesh_path.suffix}'; use one of {', '.join(MESH_SUFFIXES)}")
    for name, value in (("voxel size", voxel_size), ("truncation", sdf_trunc), ("depth_max", depth_max)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise MipslamError(f"mesh export: {name} must be a positive number of metres, got {value}")
    if not (math.isfinite(scale) and scale > 0):
        raise MipslamError(f"mesh export: scale must be positive, got {scale}")
    folder = RunFolder(run_dir)
    context = load_render_context(folder.root)
    if not folder.keyframes.is_file():
        raise EvaluationError(f"{folder.keyframes}: missing; the run has no keyframes to fuse")
    keyframes = read_tum_trajectory(folder.keyframes)
    if len(keyframes) == 0:
        raise EvaluationError(f"{folder.keyframes}: no keyframes to fuse")
    mode = mode or context.config.render.mode
    views = render_keyframes(context, keyframes.T_wc, scale=scale, mode=mode, min_alpha=min_alpha)
    intrinsics = context.intrinsics.scaled(scale)
    depths = np.concatenate([v.depth[v.depth > 0] for v in views])
    if depths.size == 0:
        raise EvaluationError(f"{folder.map_ply}: the map renders nothing opaque at any keyframe; nothing to fuse")
    if voxel_size is None:
        voxel_size = auto_voxel_size(float(np.median(depths)), intrinsics.fx)
    sdf_trunc = sdf_trunc if sdf_trunc is not None else TRUNCATION_VOXELS * voxel_size
    mesh, method = fuse_tsdf(views, intrinsics, voxel_size=voxel_size, sdf_trunc=sdf_trunc, depth_max=depth_max,
                             method=method)
    vertices, triangles = len(mesh.vertices), len(mesh.triangles)
    if vertices == 0:
        hint = ("Open3D's ScalableTSDFVolume integrated nothing; use --tsdf voxel_block_grid (or auto)"
                if method == "scalable" else "try a larger --voxel-size")
        raise EvaluationError(f"{folder.root}: TSDF fusion produced an empty mesh (voxel {voxel_size} m, truncation "
                              f"{sdf_trunc} m); {hint}")
    _write_mesh_atomic(mesh, mesh_path)
    logger.info("mesh: %d vertices, %d triangles -> %s", vertices, triangles, mesh_path)
    return MeshExportResult(mesh_path, vertices, triangles, len(views), float(voxel_size), float(sdf_trunc),
                            intrinsics.width, intrinsics.height, mode, method)


def _write_mesh_atomic(mesh, path: Path) -> None:
    o3d = _import_open3d()
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.{os.getpid()}.partial{path.suffix}")
    try:
        if not o3d.io.write_triangle_mesh(str(temporary), mesh, print_progress=False):
            raise MipslamError(f"{path}: Open3D could not write the mesh (is the folder writable?)")
        os.replace(temporary, path)
    finally:
        if temporary.exists():
            temporary.unlink()
