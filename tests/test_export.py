"""Mesh export: TSDF fusion of the map rendered at the keyframes gives a mesh on the scene's surface."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import data_synth
from mipslam.cli import main
from mipslam.errors import EvaluationError, MipslamError
from mipslam.evaluation.render_eval import load_render_context
from mipslam.export import VOXEL_MAX_M, VOXEL_MIN_M, auto_voxel_size, export_mesh, open3d_message
from test_render_eval import KEYFRAME_POSITIONS, make_tiny_run

o3d = pytest.importorskip("open3d", reason="Open3D (and its system library libusb-1.0) is needed for mesh export")

VOXEL = 0.04


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    return make_tiny_run(tmp_path_factory.mktemp("export"))


def test_mesh_vertices_lie_on_the_scene_surface(tiny_run, tmp_path):
    result = export_mesh(tiny_run, tmp_path / "mesh.ply", voxel_size=VOXEL)
    assert result.path.is_file() and result.keyframes == len(KEYFRAME_POSITIONS)
    assert result.vertices > 200 and result.triangles > 200 and result.method == "voxel_block_grid"
    assert result.voxel_source == "given" and 0 < result.tsdf_memory_mb < 50
    mesh = o3d.io.read_triangle_mesh(str(result.path))
    vertices = np.asarray(mesh.vertices)  # [V, 3] world metres
    assert len(vertices) == result.vertices and np.isfinite(vertices).all()
    colors = np.asarray(mesh.vertex_colors)
    assert colors.shape == vertices.shape and 0.0 <= colors.min() and colors.max() <= 1.0 and colors.std() > 0.01

    # Distance to the true surface along the viewing ray of the first keyframe: project each vertex into that
    # camera and compare its depth with the exact depth data_synth renders there.
    context = load_render_context(tiny_run)
    T_wc = data_synth.ground_truth_poses(context.sequence_root)[KEYFRAME_POSITIONS[0]]
    scene = data_synth.load_scene(context.sequence_root)
    k = context.intrinsics
    _, depth_gt = data_synth.render_view(scene, T_wc, k, supersample=1)
    points_c = (vertices - T_wc[:3, 3]) @ T_wc[:3, :3]  # [V, 3] camera frame
    z = points_c[:, 2]
    u = np.round(k.fx * points_c[:, 0] / z + k.cx).astype(int)
    v = np.round(k.fy * points_c[:, 1] / z + k.cy).astype(int)
    seen = (z > 0) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    assert seen.mean() > 0.5
    error = np.abs(z[seen] - depth_gt[v[seen], u[seen]])
    # the map's depth is the unprojected exact depth; fusion adds at most about a voxel (plus depth edges)
    assert np.median(error) < 0.5 * VOXEL, np.median(error)
    assert np.mean(error < 2 * VOXEL) > 0.85, np.mean(error < 2 * VOXEL)


def test_automatic_voxel_size_is_half_a_pixel_at_the_median_depth(tiny_run, tmp_path):
    assert auto_voxel_size(2.0, 100.0) == pytest.approx(0.01)  # e.g. Replica at 300x170: fx 150, 2-3 m
    assert auto_voxel_size(0.1, 1000.0) == VOXEL_MIN_M and auto_voxel_size(10.0, 20.0) == VOXEL_MAX_M
    assert auto_voxel_size(float("nan"), 100.0) == VOXEL_MAX_M
    result = export_mesh(tiny_run, tmp_path / "auto.ply")
    context = load_render_context(tiny_run)
    median = float(result.voxel_source.split("median depth ")[1].split(" m")[0])
    assert result.voxel_size == pytest.approx(auto_voxel_size(median, context.intrinsics.fx), rel=0.01)
    assert result.sdf_trunc == pytest.approx(4 * result.voxel_size)
    lo, hi = np.array(result.bounds_min), np.array(result.bounds_max)
    assert np.isfinite(lo).all() and np.all(hi >= lo) and 0.5 < (hi - lo).max() < 20  # metres


def test_tsdf_memory_is_bounded(tiny_run, tmp_path):
    with pytest.raises(EvaluationError, match="--memory-limit"):
        export_mesh(tiny_run, tmp_path / "fine.ply", voxel_size=0.005, memory_limit_mb=1.0)
    assert not (tmp_path / "fine.ply").exists()


def test_no_silent_switch_between_tsdf_implementations(tiny_run, tmp_path):
    # The legacy ScalableTSDFVolume integrates nothing in some Open3D builds (open3d-cpu 0.20): then the export
    # fails and names the other implementation, instead of quietly using it.
    try:
        result = export_mesh(tiny_run, tmp_path / "scalable.ply", voxel_size=VOXEL, method="scalable")
    except EvaluationError as error:
        assert "--tsdf voxel_block_grid" in str(error)
    else:
        assert result.method == "scalable" and result.vertices > 200
    with pytest.raises(MipslamError, match="not one of"):
        export_mesh(tiny_run, tmp_path / "x.ply", method="auto")


def test_open3d_messages_lose_colour_codes_and_source_locations():
    raw = RuntimeError("\x1b[1;31m[Open3D Error] (void open3d::f(const Tensor&)) /src/VoxelBlockGrid.cpp:180: "
                       "Unsupported input data type combination. Expected (float, float)\n\x1b[0;m")
    assert open3d_message(raw) == "Unsupported input data type combination. Expected (float, float)"


def test_bad_requests_are_refused(tiny_run, tmp_path):
    with pytest.raises(MipslamError, match="unknown mesh format"):
        export_mesh(tiny_run, tmp_path / "mesh.xyz")
    with pytest.raises(MipslamError, match="voxel size"):
        export_mesh(tiny_run, tmp_path / "mesh.ply", voxel_size=-1.0)
    assert not (tmp_path / "mesh.ply").exists()


def test_cli_export(tiny_run, tmp_path, capfd):
    out = tmp_path / "sub" / "room.obj"
    assert main(["export", str(tiny_run), "--mesh", str(out), "--voxel-size", "0.06", "--scale", "0.5"]) == 0
    captured = capfd.readouterr()  # file descriptors: Open3D prints from C++
    assert out.is_file() and "vertices" in captured.out
    for text in (captured.out, captured.err):
        assert "[Open3D" not in text and "\x1b[" not in text, text
    assert not list(out.parent.glob(".*partial*"))
    assert main(["export", str(tmp_path / "missing"), "--mesh", str(out)]) == 2
    assert main(["export", str(tiny_run), "--mesh", str(out), "--memory-limit", "0.5", "--overwrite"]) == 2
    assert "--memory-limit" in capfd.readouterr().err
