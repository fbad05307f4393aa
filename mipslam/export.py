"""Mesh export: fuse the map's rendered colour and depth at the keyframes into a TSDF and extract a triangle mesh.

``mipslam export RUN_DIR --mesh mesh.ply``. For every keyframe of ``keyframes.txt`` (final keyframe poses ``T_wc``)
the map (``map.ply``) is rendered at ``scale`` times the mapping resolution (``run.json``) with the run's render
config; pixels whose accumulated opacity is at least ``min_alpha`` contribute their alpha-normalised depth
``sum(T alpha z) / alpha`` and colour ``C / alpha`` (the rest are left out, so half-transparent edges add no
surface). Each view is integrated as soon as it is rendered (Curless and Levoy, 1996) with the pinhole intrinsics
(pixel centres at integers, as Open3D and OpenCV use) and extrinsic ``T_cw``; marching cubes gives the mesh,
written atomically in the format of the file's extension (.ply, .obj, .off, .stl, .gltf, .glb).

TSDF: Open3D's ``t.geometry.VoxelBlockGrid`` (hashed blocks of 4^3 voxels; tsdf float32, weight and colour
uint16: 12 bytes a voxel; the block table grows with the observed surface) by default, or the legacy
``pipelines.integration.ScalableTSDFVolume`` when asked. There is no silent switch between them: an empty result
is an error that names the other one. The fusion stops with an error that says which option to change when its
estimated peak (voxels, block table and meshing: :data:`PEAK_PER_VOXEL_BYTE` times the voxel storage) would pass
``memory_limit_mb``, so a too fine voxel cannot exhaust the machine. Peak resident memory of the whole command on
the 20-frame Replica room0 run: 0.59 GB (``/usr/bin/time -v mipslam export RUN --mesh m.ply``).

Voxel size: given, else half the footprint of one rendered pixel at the median rendered depth,
``0.5 * median(z) / fx`` at the render resolution, clamped to [0.005, 0.1] m: marching cubes resolves features about
two voxels wide, so this keeps the lateral detail of the depth maps, and a finer voxel only costs memory (0.93 cm
for Replica room0 mapped at 300x170, fx 150, median depth 2.8 m). The median comes from up to
:data:`VOXEL_SAMPLE_KEYFRAMES` evenly spaced keyframes. Truncation distance: given, else 4 voxels; depth beyond
``depth_max`` (default: no limit) is ignored.

Open3D's own console messages (ANSI-coloured, on stdout) are silenced while it works (shown with ``--debug``);
its errors become :class:`~mipslam.errors.EvaluationError` with plain text.
"""
from __future__ import annotations

import contextlib
import logging
import math
import os
import re
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

__all__ = ["MeshExportResult", "RenderedKeyframe", "TSDF_METHODS", "auto_voxel_size", "export_mesh",
           "render_keyframe", "TsdfFusion"]

VOXEL_PIXELS = 0.5  # voxel = this many rendered pixel footprints at the median depth (module docstring)
VOXEL_MIN_M, VOXEL_MAX_M = 0.005, 0.1
TRUNCATION_VOXELS = 4.0
VOXEL_SAMPLE_KEYFRAMES = 8  # keyframes rendered to choose the voxel size (evenly spaced, reused for the fusion)
BLOCK_RESOLUTION = 4  # voxels per side of a block: small blocks hug the thin truncation band (peak RSS 586 MB, 631 at 8^3)
BYTES_PER_VOXEL = 4 + 2 + 3 * 2  # tsdf float32, weight uint16, colour 3 x uint16
INITIAL_BLOCKS = 4096  # initial hash-map capacity (about 25 MB), grown as blocks are observed
BLOCKS_PER_CALL = 2048  # blocks handed to one Open3D integrate call (see TsdfFusion.integrate)
GROWTH = 1.25  # capacity growth factor of the block hash map when a view needs more room
DEFAULT_MEMORY_LIMIT_MB = 2048.0
# Peak of the fusion per byte of voxels: the block table (hash, slack) and marching cubes' temporaries come on top;
# Replica room0, 20 frames: 65 MB of voxels, +81 MB at the table's sizing, +132 MB while meshing.
PEAK_PER_VOXEL_BYTE = 3.5
MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".gltf", ".glb")
TSDF_METHODS = ("voxel_block_grid", "scalable")


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
    voxel_source: str  # how the voxel size was chosen
    sdf_trunc: float  # metres
    width: int
    height: int
    mode: str
    method: str  # one of TSDF_METHODS
    tsdf_memory_mb: float  # voxel storage of the fused grid (VoxelBlockGrid; 0 for the legacy volume)
    bounds_min: tuple[float, float, float]  # metres, world frame
    bounds_max: tuple[float, float, float]

    def describe(self) -> str:
        size = " x ".join(f"{hi - lo:.2f}" for lo, hi in zip(self.bounds_min, self.bounds_max))
        memory = f", {self.tsdf_memory_mb:.0f} MB of voxels" if self.tsdf_memory_mb else ""
        return (f"mesh written to {self.path}: {self.vertices} vertices, {self.triangles} triangles, {size} m, from "
                f"{self.keyframes} keyframes rendered at {self.width}x{self.height} ({self.mode}); voxel "
                f"{self.voxel_size * 100:.2f} cm ({self.voxel_source}), truncation {self.sdf_trunc * 100:.2f} cm, "
                f"TSDF: {self.method}{memory}")


def auto_voxel_size(median_depth: float, fx: float) -> float:
    """``VOXEL_PIXELS * median_depth / fx`` (one pixel footprint, metres), clamped to [0.005, 0.1]."""
    if not (math.isfinite(median_depth) and median_depth > 0):
        return VOXEL_MAX_M
    return float(min(VOXEL_MAX_M, max(VOXEL_MIN_M, VOXEL_PIXELS * median_depth / fx)))


def render_keyframe(context, T_wc: np.ndarray, intrinsics, *, mode: str, min_alpha: float = 0.5) -> RenderedKeyframe:
    """Colour and alpha-normalised depth of the map seen from ``T_wc`` [4, 4] at ``intrinsics``."""
    T_cw = se3_inverse(torch.tensor(np.array(T_wc), dtype=torch.float64)).to(torch.float32)  # [4, 4]
    with torch.no_grad():
        rendered = render_view(context.gaussians, T_cw, intrinsics, context.config.render, mode=mode)
    alpha = rendered.alpha.detach().cpu().to(torch.float64)  # [h, w]
    keep = alpha >= min_alpha
    safe = alpha.clamp_min(1e-6)
    depth = torch.where(keep, rendered.depth.detach().cpu().to(torch.float64) / safe, 0.0)  # [h, w]
    color = torch.where(keep[..., None], rendered.color.detach().cpu().to(torch.float64) / safe[..., None], 0.0)
    color_u8 = (color.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).numpy()
    return RenderedKeyframe(np.ascontiguousarray(color_u8), depth.to(torch.float32).numpy(),
                            np.asarray(T_wc, dtype=np.float64))


# ----------------------------------------------------------------------------- Open3D

def _import_open3d():
    try:
        import open3d
    except ImportError as error:  # OSError of a missing libusb surfaces as ImportError too
        raise BackendUnavailableError(
            f"mesh export needs Open3D, which cannot be imported ({error}); install it with 'pip install open3d-cpu' "
            "and, on Debian/Ubuntu, the system library libusb-1.0-0 (apt-get install libusb-1.0-0)") from error
    return open3d


_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]|\[[0-9;]*m")
_OPEN3D_PREFIX = re.compile(r"^\s*\[Open3D (?:Error|WARNING|INFO|DEBUG)\]\s*(?:\(.*\)\s+\S+:\d+:\s*)?", re.DOTALL)


def open3d_message(error: BaseException) -> str:
    """An Open3D exception's text without ANSI colour codes, the '[Open3D Error]' tag and the C++ location."""
    text = _ANSI.sub("", str(error)).strip()
    return _OPEN3D_PREFIX.sub("", text).strip() or text


@contextlib.contextmanager
def _open3d_quiet(o3d, what: str):
    """Silence Open3D's console messages (all of them with --debug), and turn its errors into EvaluationError."""
    level = o3d.utility.VerbosityLevel.Debug if logger.isEnabledFor(logging.DEBUG) else o3d.utility.VerbosityLevel.Error
    with o3d.utility.VerbosityContextManager(level):
        try:
            yield
        except RuntimeError as error:
            raise EvaluationError(f"{what}: Open3D failed: {open3d_message(error)}") from None


class TsdfFusion:
    """A TSDF fed one view at a time (:meth:`integrate`) and meshed once (:meth:`extract`). See the module docstring.

    method: "voxel_block_grid" (default) or "scalable". memory_limit_mb bounds the VoxelBlockGrid's estimated peak
    (:data:`PEAK_PER_VOXEL_BYTE` times its voxel storage); the legacy volume is not bounded.
    """

    def __init__(self, intrinsics, *, voxel_size: float, sdf_trunc: float, depth_max: float | None = None,
                 method: str = "voxel_block_grid", memory_limit_mb: float = DEFAULT_MEMORY_LIMIT_MB):
        if method not in TSDF_METHODS:
            raise MipslamError(f"mesh export: TSDF method {method!r} is not one of {', '.join(TSDF_METHODS)}")
        self.o3d = _import_open3d()
        self.intrinsics, self.method = intrinsics, method
        self.voxel_size, self.sdf_trunc, self.depth_max = float(voxel_size), float(sdf_trunc), depth_max
        self.memory_limit_mb = float(memory_limit_mb)
        self.views = 0
        self.voxel_memory_mb = 0.0
        self._block_mb = BLOCK_RESOLUTION**3 * BYTES_PER_VOXEL / 2**20
        o3d = self.o3d
        with _open3d_quiet(o3d, "mesh export"):
            if method == "scalable":
                self._volume = o3d.pipelines.integration.ScalableTSDFVolume(
                    voxel_length=self.voxel_size, sdf_trunc=self.sdf_trunc,
                    color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
                self._camera = o3d.camera.PinholeCameraIntrinsic(
                    int(intrinsics.width), int(intrinsics.height), float(intrinsics.fx), float(intrinsics.fy),
                    float(intrinsics.cx), float(intrinsics.cy))
            else:
                o3c = o3d.core
                self._K = o3c.Tensor(np.array([[intrinsics.fx, 0.0, intrinsics.cx], [0.0, intrinsics.fy, intrinsics.cy],
                                               [0.0, 0.0, 1.0]]), o3c.float64)
                self._grid = o3d.t.geometry.VoxelBlockGrid(
                    attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.uint16, o3c.uint16),
                    attr_channels=((1), (1), (3)), voxel_size=self.voxel_size, block_resolution=BLOCK_RESOLUTION,
                    block_count=INITIAL_BLOCKS, device=o3c.Device("CPU:0"))

    @property
    def memory_mb(self) -> float:
        """Voxel storage of the blocks observed so far (VoxelBlockGrid; 0 for the legacy volume)."""
        if self.method != "voxel_block_grid":
            return 0.0
        if self._grid is None:  # extracted
            return self.voxel_memory_mb
        return self._grid.hashmap().size() * self._block_mb

    def _far(self, view: RenderedKeyframe) -> float:
        return float(self.depth_max) if self.depth_max is not None else float(view.depth.max()) + 1.0

    def _tensor_view(self, view: RenderedKeyframe):
        """(depth image, colour image, T_cw, depth_max) of a view in Open3D's tensor types."""
        o3d, o3c = self.o3d, self.o3d.core
        depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(view.depth, dtype=np.float32)))
        # float depth takes float colour; the uint16 colour channels store 0..255
        color = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(view.color, dtype=np.float32)))
        return depth, color, o3c.Tensor(np.linalg.inv(view.T_wc), o3c.float64), self._far(view)

    def _blocks(self, depth, T_cw, far):
        """Coordinates [M, 3] of the blocks within the truncation band of the view's points."""
        # From every pixel's point: the depth-image overload samples every 4th pixel, which leaves block-sized
        # holes wherever 4 pixels span more than a block plus the truncation band (far walls).
        points = self.o3d.t.geometry.PointCloud.create_from_depth_image(depth, self._K, T_cw, depth_scale=1.0,
                                                                        depth_max=far, stride=1)
        return self._grid.compute_unique_block_coordinates(points, trunc_voxel_multiplier=self.sdf_trunc / self.voxel_size)

    def reserve_for(self, views: list[RenderedKeyframe]) -> None:
        """Size the block table for the union of these views' blocks (VoxelBlockGrid; fewer rehashes later)."""
        if self.method != "voxel_block_grid" or not views:
            return
        with _open3d_quiet(self.o3d, "mesh export"):
            coordinates = []
            for view in views:
                depth, _, T_cw, far = self._tensor_view(view)
                coordinates.append(self._blocks(depth, T_cw, far).numpy())
            union = np.unique(np.concatenate(coordinates), axis=0)
            self._check_memory(len(union), f"for {len(views)} of the keyframes")
            hashmap = self._grid.hashmap()
            if len(union) + BLOCKS_PER_CALL > hashmap.capacity():
                hashmap.reserve(len(union) + BLOCKS_PER_CALL)

    def _check_memory(self, blocks: int, where: str) -> None:
        if PEAK_PER_VOXEL_BYTE * blocks * self._block_mb > self.memory_limit_mb:
            raise EvaluationError(
                f"mesh export: the TSDF would need more than --memory-limit {self.memory_limit_mb:.0f} MB at a "
                f"{self.voxel_size * 100:.2f} cm voxel ({blocks} blocks of {BLOCK_RESOLUTION}^3 voxels {where}); use a "
                "larger --voxel-size, a --depth-max, or raise --memory-limit")

    def integrate(self, view: RenderedKeyframe) -> None:
        o3d = self.o3d
        with _open3d_quiet(o3d, "mesh export"):
            if self.method == "scalable":
                rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
                    o3d.geometry.Image(view.color), o3d.geometry.Image(view.depth), depth_scale=1.0,
                    depth_trunc=self._far(view), convert_rgb_to_intensity=False)
                self._volume.integrate(rgbd, self._camera, np.linalg.inv(view.T_wc))  # extrinsic = T_cw
            else:
                depth, color, T_cw, far = self._tensor_view(view)
                blocks = self._blocks(depth, T_cw, far)
                hashmap = self._grid.hashmap()
                _, known = hashmap.find(blocks)
                blocks_after = hashmap.size() + blocks.shape[0] - int(known.to(o3d.core.int64).sum().item())
                self._check_memory(blocks_after, f"after {self.views + 1} keyframes")
                # Open3D makes room for every block it is handed, new or already there, by doubling its table when
                # short. Handing it a bounded chunk at a time (each block's voxels are updated independently) into a
                # table sized here for this view's new blocks keeps the table close to the surface's size.
                if blocks_after + BLOCKS_PER_CALL > hashmap.capacity():
                    hashmap.reserve(max(blocks_after + BLOCKS_PER_CALL, int(GROWTH * hashmap.capacity())))
                for start in range(0, blocks.shape[0], BLOCKS_PER_CALL):
                    self._grid.integrate(blocks[start:start + BLOCKS_PER_CALL], depth, color, self._K, self._K, T_cw,
                                         depth_scale=1.0, depth_max=far,
                                         trunc_voxel_multiplier=self.sdf_trunc / self.voxel_size)
        self.views += 1

    def extract(self):
        """The fused surface with vertex colours in [0, 1] and normals: an ``open3d.t.geometry.TriangleMesh``
        (VoxelBlockGrid, normals from the TSDF gradient) or a legacy ``open3d.geometry.TriangleMesh`` (scalable).

        Call once: the voxels are released."""
        o3d = self.o3d
        with _open3d_quiet(o3d, "mesh export"):
            if self.method == "scalable":
                mesh = self._volume.extract_triangle_mesh()
                mesh.compute_vertex_normals()
                return mesh
            # weights are whole numbers of views: > 0.5 keeps every voxel seen at least once
            mesh = self._grid.extract_triangle_mesh(weight_threshold=0.5)
            self.voxel_memory_mb = self.memory_mb
            self._grid = None
            if "colors" in mesh.vertex:
                mesh.vertex.colors = (mesh.vertex.colors / 255.0).clip(0.0, 1.0)
        return mesh


def _mesh_arrays(mesh) -> tuple[np.ndarray, int]:
    """Vertex positions [V, 3] and the triangle count of a tensor or legacy Open3D mesh."""
    if hasattr(mesh, "vertex"):
        return mesh.vertex.positions.numpy(), int(mesh.triangle.indices.shape[0]) if "indices" in mesh.triangle else 0
    return np.asarray(mesh.vertices), len(mesh.triangles)


# ----------------------------------------------------------------------------- export

def _evenly_spaced(count: int, most: int) -> list[int]:
    if count <= most:
        return list(range(count))
    return sorted({int(round(k * (count - 1) / (most - 1))) for k in range(most)})


def export_mesh(run_dir: str | Path, mesh_path: str | Path, *, voxel_size: float | None = None,
                sdf_trunc: float | None = None, depth_max: float | None = None, scale: float = 1.0,
                mode: str | None = None, min_alpha: float = 0.5, method: str = "voxel_block_grid",
                memory_limit_mb: float = DEFAULT_MEMORY_LIMIT_MB) -> MeshExportResult:
    """Fuse the run's map rendered at its keyframes into a TSDF and write the mesh to ``mesh_path``."""
    mesh_path = Path(mesh_path)
    if mesh_path.suffix.lower() not in MESH_SUFFIXES:
        raise MipslamError(f"{mesh_path}: unknown mesh format '{mesh_path.suffix}'; use one of {', '.join(MESH_SUFFIXES)}")
    for name, value in (("voxel size", voxel_size), ("truncation", sdf_trunc), ("depth_max", depth_max),
                        ("memory limit", memory_limit_mb)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise MipslamError(f"mesh export: {name} must be a positive number, got {value}")
    if not (math.isfinite(scale) and scale > 0):
        raise MipslamError(f"mesh export: scale must be positive, got {scale}")
    if method not in TSDF_METHODS:
        raise MipslamError(f"mesh export: TSDF method {method!r} is not one of {', '.join(TSDF_METHODS)}")
    folder = RunFolder(run_dir)
    context = load_render_context(folder.root)
    if not folder.keyframes.is_file():
        raise EvaluationError(f"{folder.keyframes}: missing; the run has no keyframes to fuse")
    keyframes = read_tum_trajectory(folder.keyframes)
    if len(keyframes) == 0:
        raise EvaluationError(f"{folder.keyframes}: no keyframes to fuse")
    mode = mode or context.config.render.mode
    intrinsics = context.intrinsics.scaled(scale)
    poses = np.asarray(keyframes.T_wc)  # [K, 4, 4]

    def render(position: int) -> RenderedKeyframe:
        return render_keyframe(context, poses[position], intrinsics, mode=mode, min_alpha=min_alpha)

    # Evenly spaced keyframes rendered first choose the voxel size and size the TSDF; they are fused with the rest.
    rendered = {p: render(p) for p in _evenly_spaced(len(poses), VOXEL_SAMPLE_KEYFRAMES)}
    if voxel_size is None:
        depths = np.concatenate([v.depth[v.depth > 0] for v in rendered.values()])
        if depths.size == 0:
            raise EvaluationError(f"{folder.map_ply}: the map renders nothing opaque at the keyframes {sorted(rendered)}; "
                                  "nothing to fuse (give --voxel-size to fuse the others)")
        median = float(np.median(depths))
        voxel_size = auto_voxel_size(median, intrinsics.fx)
        voxel_source = f"{VOXEL_PIXELS:g} pixel at the median depth {median:.2f} m"
    else:
        voxel_source = "given"
    sdf_trunc = sdf_trunc if sdf_trunc is not None else TRUNCATION_VOXELS * voxel_size
    fusion = TsdfFusion(intrinsics, voxel_size=voxel_size, sdf_trunc=sdf_trunc, depth_max=depth_max, method=method,
                        memory_limit_mb=memory_limit_mb)
    fusion.reserve_for(list(rendered.values()))
    for position in range(len(poses)):
        view = rendered.pop(position, None) or render(position)
        fusion.integrate(view)
    mesh = fusion.extract()
    points, triangles = _mesh_arrays(mesh)
    vertices = len(points)
    if vertices == 0:
        hint = ("Open3D's ScalableTSDFVolume integrated nothing (some Open3D builds, e.g. open3d-cpu 0.20, do so); "
                "use --tsdf voxel_block_grid" if method == "scalable" else
                "the map renders no opaque surface at the keyframes; try a larger --voxel-size or --scale")
        raise EvaluationError(f"{folder.root}: TSDF fusion produced an empty mesh (voxel {voxel_size} m, truncation "
                              f"{sdf_trunc} m); {hint}")
    _write_mesh_atomic(fusion.o3d, mesh, mesh_path)
    logger.info("mesh: %d vertices, %d triangles -> %s", vertices, triangles, mesh_path)
    return MeshExportResult(mesh_path, vertices, triangles, len(poses), float(voxel_size), voxel_source,
                            float(sdf_trunc), intrinsics.width, intrinsics.height, mode, method, fusion.memory_mb,
                            tuple(float(x) for x in points.min(axis=0)), tuple(float(x) for x in points.max(axis=0)))


def _write_mesh_atomic(o3d, mesh, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.{os.getpid()}.partial{path.suffix}")
    try:
        with _open3d_quiet(o3d, str(path)):
            if hasattr(mesh, "vertex") and path.suffix.lower() == ".ply":  # no copy into the legacy type
                written = o3d.t.io.write_triangle_mesh(str(temporary), mesh)
            else:  # the tensor writer names an .obj's material file after the temporary name
                mesh = mesh.to_legacy() if hasattr(mesh, "vertex") else mesh
                written = o3d.io.write_triangle_mesh(str(temporary), mesh, print_progress=False)
        if not written:
            raise MipslamError(f"{path}: Open3D could not write the mesh (is the folder writable?)")
        os.replace(temporary, path)
    finally:
        if temporary.exists():
            temporary.unlink()
