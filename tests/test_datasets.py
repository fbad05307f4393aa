"""Dataset readers on tiny folders written here with cv2, and on the real sequences in ../shared/data."""
from __future__ import annotations

import json
import os
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from mipslam.config import DatasetConfig
from mipslam.datasets import (
    RGBDSequence,
    ReplicaSequence,
    SyntheticSequence,
    TUMSequence,
    associate_timestamps,
    downscale_color,
    downscale_depth,
    make_sequence,
)
from mipslam.datasets.tum import poses_at_times
from mipslam.errors import ConfigError, DatasetError
from mipslam.geometry import project, quat_wxyz_to_rotmat, rigidity_error, se3_from_rt, se3_inverse, so3_exp, transform_points, unproject_depth

W, H = 16, 12


# ----------------------------------------------------------------------------- writers of tiny fixtures

def pose_at(t: float) -> torch.Tensor:
    """A smooth camera-to-world pose: constant angular velocity about a fixed axis, linear translation.  -> [4, 4]"""
    axis = torch.tensor([0.3, -0.8, 0.5], dtype=torch.float64)
    axis = axis / axis.norm()
    R = so3_exp(axis * (0.2 + 0.9 * t))
    trans = torch.tensor([0.5 + 0.7 * t, -0.2 + 0.1 * t, 1.0 - 0.4 * t], dtype=torch.float64)
    return se3_from_rt(R, trans)


def make_images(n: int, rng: np.random.Generator, width: int = W, height: int = H):
    colors = [rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in range(n)]  # BGR as written
    depths = [rng.integers(1000, 30000, (height, width), dtype=np.uint16) for _ in range(n)]
    for depth in depths:
        depth[0, 0] = 0  # a hole
    return colors, depths


def write_replica(root: Path, n: int = 6, ext: str = "png", cam: bool = True, traj: bool = True, seed: int = 0):
    rng = np.random.default_rng(seed)
    (root / "results").mkdir(parents=True)
    colors, depths = make_images(n, rng)
    for i in range(n):
        assert cv2.imwrite(str(root / "results" / f"frame{i:06d}.{ext}"), colors[i])
        assert cv2.imwrite(str(root / "results" / f"depth{i:06d}.png"), depths[i])
    poses = [pose_at(i / 30) for i in range(n)]
    if traj:
        lines = [" ".join(f"{v:.17g}" for v in T.flatten().tolist()) for T in poses]
        (root / "traj.txt").write_text("\n".join(lines) + "\n")
    if cam:
        params = {"camera": {"w": W, "h": H, "fx": 20.0, "fy": 21.0, "cx": 7.5, "cy": 5.5, "scale": 6553.5}}
        (root / "cam_params.json").write_text(json.dumps(params))
    return colors, depths, poses


def write_tum(root: Path, n: int = 6, seed: int = 0, gt_span: tuple[float, float] | None = None, name_hint: str = ""):
    """rgb at 1000 + i/30; depth 4 ms later; ground truth at 100 Hz (t = 1000 + k/100) over gt_span seconds."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True)
    (root / "rgb").mkdir()
    (root / "depth").mkdir()
    colors, depths = make_images(n, rng)
    rgb_lines = [f"# color images{name_hint}", "# timestamp filename"]
    depth_lines = ["# depth maps", "# timestamp filename"]
    for i in range(n):
        t_rgb, t_depth = 1000.0 + i / 30, 1000.0 + i / 30 + 0.004
        assert cv2.imwrite(str(root / "rgb" / f"{t_rgb:.6f}.png"), colors[i])
        assert cv2.imwrite(str(root / "depth" / f"{t_depth:.6f}.png"), depths[i])
        rgb_lines.append(f"{t_rgb:.6f} rgb/{t_rgb:.6f}.png")
        depth_lines.append(f"{t_depth:.6f} depth/{t_depth:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    start, end = gt_span if gt_span is not None else (-0.05, n / 30 + 0.05)
    gt_lines = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    from mipslam.geometry import quat_wxyz_to_xyzw, rotmat_to_quat_wxyz

    for k in range(int(round(start * 100)), int(round(end * 100)) + 1):
        t = k / 100
        T = pose_at(t)
        q = quat_wxyz_to_xyzw(rotmat_to_quat_wxyz(T[:3, :3]))
        values = [1000.0 + t, *T[:3, 3].tolist(), *q.tolist()]
        gt_lines.append(" ".join(f"{v:.12f}" for v in values))
    (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    return colors, depths


def tum_cfg(root: Path, **kw) -> DatasetConfig:
    kw.setdefault("camera", "freiburg1")
    return DatasetConfig(kind="tum", path=str(root), **kw)


# ----------------------------------------------------------------------------- Replica

def test_replica_tiny_fixture_values_poses_and_protocol(tmp_path):
    colors, depths, poses = write_replica(tmp_path / "rep")
    seq = make_sequence(DatasetConfig(kind="replica", path=str(tmp_path / "rep")))
    assert isinstance(seq, ReplicaSequence) and isinstance(seq, RGBDSequence)
    assert len(seq) == 6 and seq.timestamp_kind == "index"
    assert seq.intrinsics.fx == 20.0 and seq.intrinsics.fy == 21.0 and seq.intrinsics.cx == 7.5
    assert (seq.intrinsics.width, seq.intrinsics.height) == (W, H)
    assert seq.depth_scale == 6553.5
    np.testing.assert_array_equal(seq.timestamps, np.arange(6, dtype=np.float64))
    np.testing.assert_array_equal(seq.source_indices, np.arange(6))
    assert seq.gt_T_wc.dtype == torch.float64 and seq.gt_T_wc.shape == (6, 4, 4) and seq.gt_valid.all()
    for i in (0, 4):
        frame = seq[i]
        assert frame.index == i and frame.timestamp == float(i)
        assert frame.color.dtype == torch.float32 and frame.color.shape == (H, W, 3)
        expected_rgb = colors[i][..., ::-1].astype(np.float32) / 255.0  # the file is BGR
        np.testing.assert_allclose(frame.color.numpy(), expected_rgb, atol=1e-7)
        np.testing.assert_allclose(frame.depth.numpy(), depths[i].astype(np.float32) / 6553.5, rtol=1e-6)
        assert frame.depth[0, 0] == 0.0
        torch.testing.assert_close(frame.T_wc_gt, poses[i], rtol=0, atol=1e-12)
    with pytest.raises(IndexError):
        seq[6]
    with pytest.raises(IndexError):
        seq[-1]


def test_replica_selection_first_stride_max(tmp_path):
    write_replica(tmp_path / "rep", n=10)
    seq = ReplicaSequence(tmp_path / "rep", DatasetConfig(first_frame=1, stride=3, max_frames=2))
    np.testing.assert_array_equal(seq.source_indices, [1, 4])
    np.testing.assert_array_equal(seq.timestamps, [1.0, 4.0])
    torch.testing.assert_close(seq[1].T_wc_gt, pose_at(4 / 30), rtol=0, atol=1e-12)
    all_after = ReplicaSequence(tmp_path / "rep", DatasetConfig(first_frame=7, stride=2))
    np.testing.assert_array_equal(all_after.source_indices, [7, 9])


def test_replica_jpg_accepted_png_preferred_and_config_overrides(tmp_path):
    write_replica(tmp_path / "rep", n=3, ext="jpg", cam=False)
    with pytest.raises(DatasetError) as info:
        ReplicaSequence(tmp_path / "rep")
    assert "cam_params.json" in str(info.value) and "dataset.fx" in str(info.value)
    cfg = DatasetConfig(fx=30.0, fy=30.0, cx=7.5, cy=5.5)
    seq = ReplicaSequence(tmp_path / "rep", cfg)
    assert seq.intrinsics.fx == 30.0 and (seq.intrinsics.width, seq.intrinsics.height) == (W, H)
    assert seq.frame_paths[0][0].suffix == ".jpg" and seq[2].color.shape == (H, W, 3)
    # a lossless .png next to the .jpg wins
    png = np.full((H, W, 3), 77, np.uint8)
    cv2.imwrite(str(tmp_path / "rep" / "results" / "frame000001.png"), png)
    seq = ReplicaSequence(tmp_path / "rep", cfg)
    assert seq.frame_paths[1][0].suffix == ".png"
    assert torch.allclose(seq[1].color, torch.full((H, W, 3), 77 / 255))
    # config values override cam_params.json value by value
    write_replica(tmp_path / "rep2", n=2)
    seq = ReplicaSequence(tmp_path / "rep2", DatasetConfig(fy=50.0, depth_scale=1000.0))
    assert (seq.intrinsics.fx, seq.intrinsics.fy, seq.depth_scale) == (20.0, 50.0, 1000.0)


def test_replica_without_traj_has_no_ground_truth(tmp_path):
    write_replica(tmp_path / "rep", n=2, traj=False)
    seq = ReplicaSequence(tmp_path / "rep")
    assert seq.gt_T_wc is None and not seq.gt_valid.any() and seq[0].T_wc_gt is None


# ----------------------------------------------------------------------------- TUM

def test_associate_timestamps_greedy_one_to_one():
    rgb = np.array([0.00, 0.030, 0.033, 0.100, 0.200])
    depth = np.array([0.005, 0.031, 0.101, 0.150])
    pairs = associate_timestamps(rgb, depth, 0.02)
    # 0.030 and 0.033 both want 0.031: the closer one (0.030, diff 0.001) gets it, 0.033 stays single
    assert pairs == [(0, 0), (1, 1), (3, 2)]
    assert len({j for _, j in pairs}) == len(pairs)
    assert associate_timestamps(rgb, depth, 0.0005) == []
    assert associate_timestamps(rgb, depth, 0.0011) == [(1, 1), (3, 2)]


def test_tum_tiny_fixture_association_and_interpolated_ground_truth(tmp_path):
    colors, depths = write_tum(tmp_path / "tum", n=6)
    seq = make_sequence(tum_cfg(tmp_path / "tum"))
    assert isinstance(seq, TUMSequence) and isinstance(seq, RGBDSequence)
    assert len(seq) == 6 and seq.timestamp_kind == "time" and seq.depth_scale == 5000.0
    assert (seq.intrinsics.fx, seq.intrinsics.fy, seq.intrinsics.cx, seq.intrinsics.cy) == (517.3, 516.5, 318.6, 255.3)
    assert (seq.intrinsics.width, seq.intrinsics.height) == (W, H)
    np.testing.assert_allclose(seq.timestamps, 1000.0 + np.arange(6) / 30, atol=1e-6)
    assert seq.gt_valid.all()
    # frames at i/30 fall between 100 Hz samples (except every third); interpolation recovers the analytic pose
    for i in range(6):
        t = round(seq.timestamps[i] - 1000.0, 6)
        expected = pose_at(t)
        assert (seq.gt_T_wc[i][:3, 3] - expected[:3, 3]).abs().max() < 1e-9
        assert (seq.gt_T_wc[i][:3, :3] - expected[:3, :3]).abs().max() < 1e-9
    frame = seq[5]
    np.testing.assert_allclose(frame.color.numpy(), colors[5][..., ::-1] / 255.0, atol=1e-7)
    np.testing.assert_allclose(frame.depth.numpy(), depths[5] / 5000.0, rtol=1e-6)
    assert frame.timestamp == seq.timestamps[5] and frame.T_wc_gt is not None


def test_tum_frames_outside_ground_truth_are_marked_invalid(tmp_path):
    write_tum(tmp_path / "tum", n=6, gt_span=(0.0, 0.07))  # ground truth covers only the first 3 frames (+ 20 ms)
    seq = TUMSequence(tmp_path / "tum", tum_cfg(tmp_path / "tum"))
    # frame 3 at 0.1 s: nearest sample 0.07 is 30 ms away (> 20 ms tolerance)
    np.testing.assert_array_equal(seq.gt_valid, [True, True, True, False, False, False])
    assert torch.isfinite(seq.gt_T_wc).all()
    assert torch.equal(seq.gt_T_wc[4], torch.eye(4, dtype=torch.float64))
    assert seq[4].T_wc_gt is None and seq[2].T_wc_gt is not None


def test_poses_at_times_nearest_at_the_ends_and_exact_hits():
    gt_t = np.array([0.0, 0.01, 0.02])
    gt_T = torch.stack([pose_at(t) for t in gt_t])
    T, valid = poses_at_times(gt_t, gt_T, np.array([0.01, 0.005, 0.035, 0.05, -0.015]), 0.02)
    np.testing.assert_array_equal(valid, [True, True, True, False, True])
    assert torch.equal(T[0], gt_T[1])  # exact timestamp: the sample itself
    assert torch.equal(T[2], gt_T[2]) and torch.equal(T[4], gt_T[0])  # beyond the ends: nearest within tolerance
    torch.testing.assert_close(T[1], pose_at(0.005), rtol=0, atol=1e-12)


def test_tum_camera_presets_guess_and_explicit_intrinsics(tmp_path):
    write_tum(tmp_path / "rgbd_dataset_freiburg2_desk", n=2)
    seq = TUMSequence(tmp_path / "rgbd_dataset_freiburg2_desk")
    assert (seq.intrinsics.fx, seq.intrinsics.cy) == (520.9, 249.7)
    seq = TUMSequence(tmp_path / "rgbd_dataset_freiburg2_desk", DatasetConfig(camera="freiburg3"))
    assert seq.intrinsics.fx == 535.4
    write_tum(tmp_path / "mine", n=2)
    with pytest.raises(DatasetError) as info:
        TUMSequence(tmp_path / "mine")
    assert str(tmp_path / "mine") in str(info.value) and "dataset.camera" in str(info.value)
    cfg = DatasetConfig(fx=585.0, fy=585.0, cx=320.0, cy=240.0, depth_scale=1000.0)
    seq = TUMSequence(tmp_path / "mine", cfg)
    assert (seq.intrinsics.fx, seq.intrinsics.cx, seq.depth_scale) == (585.0, 320.0, 1000.0)
    assert (seq.intrinsics.width, seq.intrinsics.height) == (W, H)  # from the images
    seq = TUMSequence(tmp_path / "mine", DatasetConfig(camera="freiburg1", fx=500.0))
    assert (seq.intrinsics.fx, seq.intrinsics.fy) == (500.0, 516.5)
    write_tum(tmp_path / "hdr", n=2, name_hint=" rgbd_dataset_freiburg3_office")
    assert TUMSequence(tmp_path / "hdr").intrinsics.fx == 535.4  # named in the rgb.txt header
    with pytest.raises(ConfigError, match="freiburg1"):
        TUMSequence(tmp_path / "mine", DatasetConfig(camera="freiburg_1"))
    with pytest.raises(DatasetError, match="dataset.width"):
        TUMSequence(tmp_path / "mine", DatasetConfig(fx=1.0, fy=1.0, cx=1.0, cy=1.0, width=64, height=48))


# ----------------------------------------------------------------------------- synthetic

def write_synth_json(root: Path, layout: str, **over):
    meta = {
        "format_version": 1, "generator": "data_synth", "layout": layout, "trajectory": "loop", "seed": 3,
        "frames": 4, "intrinsics": {"fx": 14.0, "fy": 14.5, "cx": 7.5, "cy": 5.5, "width": W, "height": H},
        "depth_scale": 6553.5 if layout == "replica" else 5000.0, "fps": 30.0, "scene": {"room": [4, 3, 2.5]},
        "sensor": {"depth_noise": 0.0},
    }
    meta.update(over)
    (root / "synth.json").write_text(json.dumps(meta, indent=1))


@pytest.mark.parametrize("layout", ["replica", "tum"])
def test_synthetic_reads_synth_json_and_delegates(tmp_path, layout):
    root = tmp_path / "synth"
    if layout == "replica":
        write_replica(root, n=4, cam=False)
    else:
        write_tum(root, n=4)
    write_synth_json(root, layout)
    seq = make_sequence(DatasetConfig(kind="synthetic", path=str(root), downscale=2))
    assert isinstance(seq, SyntheticSequence) and isinstance(seq, RGBDSequence)
    assert seq.layout == layout and seq.meta["trajectory"] == "loop" and len(seq) == 4
    assert seq.full_intrinsics.fx == 14.0 and seq.full_intrinsics.cy == 5.5
    assert seq.intrinsics == seq.full_intrinsics.scaled(0.5)
    assert seq.timestamp_kind == ("index" if layout == "replica" else "time")
    frame = seq[3]
    assert frame.color.shape == (H // 2, W // 2, 3) and frame.depth.shape == (H // 2, W // 2)
    assert seq.gt_valid.all() and frame.T_wc_gt is not None
    assert seq.depth_scale == (6553.5 if layout == "replica" else 5000.0)


def test_synthetic_rejects_missing_or_foreign_synth_json(tmp_path):
    root = tmp_path / "synth"
    write_replica(root, n=2)
    with pytest.raises(DatasetError) as info:
        SyntheticSequence(root)
    assert info.value.path == root / "synth.json"
    write_synth_json(root, "replica", format_version=2)
    with pytest.raises(DatasetError, match="format_version"):
        SyntheticSequence(root)
    write_synth_json(root, "colmap")
    with pytest.raises(DatasetError, match="layout"):
        SyntheticSequence(root)
    (root / "synth.json").write_text('{\n "format_version": 1,\n "layout": \n}')
    with pytest.raises(DatasetError) as info:
        SyntheticSequence(root)
    assert info.value.path == root / "synth.json" and info.value.line == 4


def test_make_sequence_needs_a_path():
    with pytest.raises(DatasetError, match="dataset.path"):
        make_sequence(DatasetConfig(kind="tum", path=""))


# ----------------------------------------------------------------------------- downscaling

def test_downscale_color_is_the_block_mean_and_crops():
    rng = np.random.default_rng(1)
    color = rng.random((7, 11, 3)).astype(np.float32)
    small = downscale_color(color, 2)
    assert small.shape == (3, 5, 3)
    np.testing.assert_allclose(small[1, 2], color[2:4, 4:6].reshape(-1, 3).mean(0), rtol=1e-6)
    assert downscale_color(color, 1) is color


def test_downscale_depth_keeps_a_step_edge_a_step():
    depth = np.full((8, 9), 2.0, np.float32)
    depth[:, :3] = 1.0  # edge between columns 2 and 3: blocks of 2 (cols 2-3) straddle it
    depth += np.linspace(0, 0.01, 9, dtype=np.float32)[None, :]  # a slight slant inside each surface
    small = downscale_depth(depth, 2)
    assert small.shape == (4, 4)
    # the straddling block takes the near surface (mean of its near samples), never something in between
    np.testing.assert_allclose(small[:, 1], depth[0, 2], rtol=1e-6)
    assert np.all((small < 1.02) | (small > 1.99))
    np.testing.assert_allclose(small[:, 2], depth[0, 4:6].mean(), rtol=1e-6)  # inside a surface: the mean


def test_downscale_depth_needs_enough_valid_samples():
    depth = np.array([[1.0, 0.0, 3.0, 3.0], [0.0, 0.0, 0.0, np.nan]], np.float32)
    small = downscale_depth(depth, 2)
    # left block: 1 valid of 4 < half -> invalid; right block: 2 valid (nan is invalid) -> 3.0
    np.testing.assert_array_equal(small, [[0.0, 3.0]])
    assert downscale_depth(np.full((4, 4), np.inf, np.float32), 2).max() == 0.0


def _reference_downscale_depth(depth: np.ndarray, factor: int, edge_gap: float = 0.05) -> np.ndarray:
    """The rule of mipslam.datasets.images written block by block: sort the valid samples, keep the run
    before the first relative gap above edge_gap, average it; a block needs half its samples valid."""
    h, w = depth.shape[0] // factor, depth.shape[1] // factor
    out = np.zeros((h, w), np.float32)
    for i in range(h):
        for j in range(w):
            block = depth[i * factor:(i + 1) * factor, j * factor:(j + 1) * factor].astype(np.float64).ravel()
            valid = np.sort(block[np.isfinite(block) & (block > 0)])
            if valid.size < max(1, int(np.ceil(0.5 * factor * factor))):
                continue
            end = 1
            while end < valid.size and valid[end] / valid[end - 1] <= 1.0 + edge_gap:
                end += 1
            out[i, j] = np.float32(valid[:end].sum() / end)
    return out


@pytest.mark.parametrize("factor", [2, 3, 4])
def test_downscale_matches_the_block_by_block_rule(factor):
    rng = np.random.default_rng(factor)
    depth = rng.uniform(0.3, 6.0, (26, 37)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.3] = 0.0  # holes
    depth[rng.random(depth.shape) < 0.2] *= 1.5  # step edges inside blocks
    depth[0, :5], depth[1, :4] = np.nan, np.inf
    np.testing.assert_array_equal(downscale_depth(depth, factor), _reference_downscale_depth(depth, factor))
    color = rng.integers(0, 256, (26, 37, 3)).astype(np.float32) / np.float32(255)
    h, w = 26 // factor, 37 // factor
    blocks = color[:h * factor, :w * factor].reshape(h, factor, w, factor, 3).astype(np.float64)
    np.testing.assert_array_equal(downscale_color(color, factor), blocks.mean(axis=(1, 3)).astype(np.float32))


@pytest.mark.parametrize("factor", [2, 3])
def test_downscaled_intrinsics_follow_the_pixel_centre_rule(tmp_path, factor):
    write_replica(tmp_path / "rep", n=2)  # 16 x 12
    full = ReplicaSequence(tmp_path / "rep")
    small = ReplicaSequence(tmp_path / "rep", DatasetConfig(downscale=factor))
    i = small.intrinsics
    assert (i.width, i.height) == (W // factor, H // factor)
    # a 3-D point projects to the same continuous position on the image plane at both resolutions:
    # u_small = (u_full + 0.5) / factor - 0.5
    points = torch.tensor([[0.1, -0.2, 1.5], [-0.3, 0.25, 2.0]], dtype=torch.float64)
    uv_full, _ = project(points, full.intrinsics.matrix(torch.float64))
    uv_small, _ = project(points, i.matrix(torch.float64))
    torch.testing.assert_close(uv_small, (uv_full + 0.5) / factor - 0.5, rtol=0, atol=1e-12)
    frame = small[0]
    assert frame.color.shape == (i.height, i.width, 3) and frame.intrinsics == i
    # every downscaled depth value is a real surface: within 5 % of some sample of its block
    raw = full[0].depth.numpy()
    for v in range(i.height):
        for u in range(i.width):
            value = float(frame.depth[v, u])
            if value > 0:
                block = raw[v * factor:(v + 1) * factor, u * factor:(u + 1) * factor]
                block = block[block > 0]
                assert np.min(np.abs(block - value) / block) <= 0.05 + 1e-6


def test_downscale_larger_than_the_image_is_an_error(tmp_path):
    write_replica(tmp_path / "rep", n=1)
    with pytest.raises(DatasetError, match="downscale"):
        ReplicaSequence(tmp_path / "rep", DatasetConfig(downscale=20))


# ----------------------------------------------------------------------------- real data

def reprojection_depth_error(frame_a, frame_b, stride: int = 4) -> float:
    """Median |z_pred - z_b| (m) of frame a's points seen in frame b, through the ground-truth poses."""
    K = frame_a.intrinsics.matrix(torch.float64)
    points_a = unproject_depth(frame_a.depth.double(), K)[::stride, ::stride].reshape(-1, 3)
    points_a = points_a[points_a[:, 2] > 0]
    T_ba = se3_inverse(frame_b.T_wc_gt) @ frame_a.T_wc_gt
    points_b = transform_points(T_ba, points_a)
    uv, _ = project(points_b, K)
    u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
    h, w = frame_b.depth.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (points_b[:, 2] > 0)
    z_b = frame_b.depth.double()[v[inside], u[inside]]
    ok = z_b > 0
    return float((points_b[inside][ok, 2] - z_b[ok]).abs().median())


def test_real_replica_room0(replica_room0_path):
    seq = make_sequence(DatasetConfig(kind="replica", path=str(replica_room0_path)))
    assert len(seq) == 20 and (seq.intrinsics.width, seq.intrinsics.height) == (1200, 680)
    assert (seq.intrinsics.fx, seq.intrinsics.cx, seq.intrinsics.cy, seq.depth_scale) == (600.0, 599.5, 339.5, 6553.5)
    np.testing.assert_array_equal(seq.timestamps, np.arange(20, dtype=np.float64))
    assert float(rigidity_error(seq.gt_T_wc).max()) < 1e-6
    steps = (seq.gt_T_wc[1:, :3, 3] - seq.gt_T_wc[:-1, :3, 3]).norm(dim=-1)
    assert float(steps.max()) < 0.1  # a hand-held-like trajectory: centimetres per frame
    first, last = seq[0], seq[19]
    for frame in (first, last):
        assert frame.color.shape == (680, 1200, 3) and frame.depth.shape == (680, 1200)
        assert 0.0 <= float(frame.color.min()) and float(frame.color.max()) <= 1.0 and float(frame.color.std()) > 0.05
        valid = frame.depth[frame.depth > 0]
        assert valid.numel() > 0.95 * frame.depth.numel()
        assert 0.3 < float(valid.median()) < 6.0 and float(valid.max()) < 15.0  # metres in a room
    # scale and pose convention together: frame 0's depth, moved by the ground truth, predicts frame 19's
    assert reprojection_depth_error(first, last) < 0.005  # measured 0.0009; inverted poses give 0.22


def test_real_tum_fr1_xyz(tum_fr1_xyz_path):
    seq = make_sequence(DatasetConfig(kind="tum", path=str(tum_fr1_xyz_path)))
    assert len(seq) == 10 and (seq.intrinsics.width, seq.intrinsics.height) == (640, 480)
    assert (seq.intrinsics.fx, seq.intrinsics.fy, seq.intrinsics.cx, seq.intrinsics.cy) == (517.3, 516.5, 318.6, 255.3)
    assert seq.depth_scale == 5000.0
    dt = np.diff(seq.timestamps)
    assert seq.timestamps[0] == pytest.approx(1305031102.1658) and np.all((dt > 0.02) & (dt < 0.05))
    assert seq.gt_valid.all() and float(rigidity_error(seq.gt_T_wc).max()) < 1e-9
    # the sample's frame timestamps are ground-truth timestamps: the pose is that line, unchanged
    # (groundtruth.txt: "1305031102.1658 1.3434 0.6271 1.6606 0.6583 0.6112 -0.2938 -0.3266")
    assert seq.gt_T_wc[0][:3, 3].tolist() == pytest.approx([1.3434, 0.6271, 1.6606], abs=1e-12)
    q_wxyz = torch.tensor([-0.3266, 0.6583, 0.6112, -0.2938], dtype=torch.float64)
    torch.testing.assert_close(seq.gt_T_wc[0][:3, :3], quat_wxyz_to_rotmat(q_wxyz), rtol=0, atol=1e-12)
    first, last = seq[0], seq[9]
    for frame in (first, last):
        assert frame.color.shape == (480, 640, 3) and frame.depth.shape == (480, 640)
        assert float(frame.color.std()) > 0.05
        valid = frame.depth[frame.depth > 0]
        assert valid.numel() > 0.5 * frame.depth.numel()
        assert 0.4 < float(valid.median()) < 4.0 and float(valid.max()) < 10.0
    assert reprojection_depth_error(first, last) < 0.025  # measured 0.014; inverted poses give 0.059


def test_real_tum_downscaled(tum_fr1_xyz_path):
    seq = make_sequence(DatasetConfig(kind="tum", path=str(tum_fr1_xyz_path), downscale=4, stride=3, max_frames=3))
    np.testing.assert_array_equal(seq.source_indices, [0, 3, 6])
    i = seq.intrinsics
    assert (i.width, i.height) == (160, 120)
    assert i.cx == pytest.approx((318.6 + 0.5) / 4 - 0.5) and i.fx == pytest.approx(517.3 / 4)
    frame = seq[1]
    assert frame.depth.shape == (120, 160) and frame.color.shape == (120, 160, 3)
    valid = frame.depth[frame.depth > 0]
    assert valid.numel() > 0.5 * frame.depth.numel() and 0.4 < float(valid.median()) < 4.0


# ----------------------------------------------------------------------------- lens distortion

def test_lens_undistortion_moves_a_distorted_point_to_its_pinhole_position():
    from mipslam.datasets.images import LensUndistortion

    w, h, camera, coefficients = 64, 48, (50.0, 52.0, 31.5, 23.5), (0.4, 0.0, 0.001, -0.002, 0.0)
    K = np.array([[50.0, 0, 31.5], [0, 52.0, 23.5], [0, 0, 1]])
    ray = np.array([[[0.42, 0.3, 1.0]]])  # a camera-frame point away from the centre
    pinhole = ray[0, 0, :2] / ray[0, 0, 2] * [50.0, 52.0] + [31.5, 23.5]
    distorted, _ = cv2.projectPoints(ray, np.zeros(3), np.zeros(3), K, np.array(coefficients))
    du, dv = distorted.reshape(2)
    color = np.zeros((h, w, 3), np.float32)
    depth = np.zeros((h, w), np.float32)
    color[int(round(dv)) - 1:int(round(dv)) + 2, int(round(du)) - 1:int(round(du)) + 2] = 1.0  # a 3x3 bright spot
    depth[int(round(dv)) - 1:int(round(dv)) + 2, int(round(du)) - 1:int(round(du)) + 2] = 2.0
    undistortion = LensUndistortion(camera, coefficients, (w, h))
    out_color, out_depth = undistortion.color(color), undistortion.depth(depth)
    assert out_color.shape == (h, w, 3) and out_depth.shape == (h, w)
    vv, uu = np.nonzero(out_color[..., 0] > 0.5)
    assert abs(uu.mean() - pinhole[0]) < 1.0 and abs(vv.mean() - pinhole[1]) < 1.0
    assert abs(pinhole[0] - du) > 2.0  # the distortion did move the point
    assert set(np.unique(out_depth)) <= {0.0, 2.0}  # nearest sampling: no mixed depths


def test_dataset_distortion_undistorts_frames_and_rejects_bad_coefficients(tmp_path):
    from mipslam.datasets.images import LensUndistortion

    write_tum(tmp_path / "seq", n=2)
    raw = TUMSequence(tmp_path / "seq", tum_cfg(tmp_path / "seq"))
    coefficients = (0.1, -0.05, 0.0, 0.0)
    seq = TUMSequence(tmp_path / "seq", tum_cfg(tmp_path / "seq", distortion=coefficients))
    i = raw.intrinsics
    expected = LensUndistortion((i.fx, i.fy, i.cx, i.cy), coefficients, (i.width, i.height))
    np.testing.assert_array_equal(seq[1].color.numpy(), expected.color(raw[1].color.numpy()))
    np.testing.assert_array_equal(seq[1].depth.numpy(), expected.depth(raw[1].depth.numpy()))
    assert seq.intrinsics == raw.intrinsics
    same = TUMSequence(tmp_path / "seq", tum_cfg(tmp_path / "seq", distortion=()))
    assert torch.equal(same[1].color, raw[1].color)
    with pytest.raises(ConfigError, match="dataset.distortion"):
        DatasetConfig(distortion=(0.1, 0.2, 0.3))
    with pytest.raises(ConfigError, match="dataset.distortion"):
        DatasetConfig(distortion=(0.1, float("nan"), 0.0, 0.0))


# ----------------------------------------------------------------------------- depth not registered to colour

def test_depth_registration_with_the_colour_camera_itself_changes_nothing():
    from mipslam.datasets.images import DepthRegistration

    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 3.0, (24, 32)).astype(np.float32)
    depth[3, 4] = 0.0  # no measurement stays none
    camera = (30.0, 31.0, 15.5, 11.5)
    out = DepthRegistration(camera, np.eye(4), camera, (32, 24))(depth)
    np.testing.assert_array_equal(out, depth)


def test_depth_registration_moves_a_depth_cameras_images_onto_the_colour_cameras(tmp_path):
    """data_synth renders the same frames with registered depth and with the depth of a second camera 3 cm aside
    with 1.1x the focal length (a raw Kinect's); registered with that calibration, the second agrees with the
    first wherever both measure, and the nearer surface wins where the moved points overlap."""
    import data_synth
    from mipslam.datasets.images import DepthRegistration

    common = dict(layout="tum", trajectory="loop", width=64, height=48, frames=2, seed=3, supersample=1)
    data_synth.generate(tmp_path / "registered", **common)
    data_synth.generate(tmp_path / "raw", depth_baseline=0.03, depth_focal_ratio=1.1, **common)
    def synthetic(name, **kw):
        return make_sequence(DatasetConfig(kind="synthetic", path=str(tmp_path / name), **kw))

    registered, raw = synthetic("registered"), synthetic("raw")
    k = raw.intrinsics
    depth_camera = (1.1 * k.fx, 1.1 * k.fy, k.cx, k.cy)
    moved = synthetic("raw", depth_intrinsics=depth_camera, depth_extrinsics=(0.03, 0.0, 0.0))
    truth, unregistered, depth = registered[1].depth.numpy(), raw[1].depth.numpy(), moved[1].depth.numpy()
    both = (truth > 0) & (depth > 0)
    assert both.mean() > 0.7  # the narrower depth camera sees most of the colour image
    error = np.abs(depth[both] - truth[both]) / truth[both]
    error_unregistered = np.abs(unregistered[both] - truth[both]) / truth[both]
    assert np.percentile(error, 99) < 0.005 and np.median(error) < 0.3 * np.median(error_unregistered)
    # read at half the resolution: the depth is downscaled first, then registered at the delivered resolution
    half_truth = synthetic("registered", downscale=2)[1].depth.numpy()
    half = synthetic("raw", downscale=2, depth_intrinsics=depth_camera, depth_extrinsics=(0.03, 0.0, 0.0))[1].depth
    assert half.shape == half_truth.shape
    both = (half.numpy() > 0) & (half_truth > 0)
    assert both.mean() > 0.6
    half_unregistered = synthetic("raw", downscale=2)[1].depth.numpy()
    relative = np.abs(half.numpy()[both] - half_truth[both]) / half_truth[both]
    assert np.median(relative) < 0.5 * np.median(np.abs(half_unregistered[both] - half_truth[both]) / half_truth[both])
    # a rotation vector in the extrinsics: a camera turned by 2 degrees about y
    T_cd = np.eye(4)
    T_cd[:3, :3] = cv2.Rodrigues(np.array([0.0, np.radians(2.0), 0.0]))[0]
    turned = DepthRegistration(depth_camera, T_cd, (k.fx, k.fy, k.cx, k.cy), (k.width, k.height))
    rotated = synthetic("raw", depth_intrinsics=depth_camera, depth_extrinsics=(0.0, 0.0, 0.0, 0.0, np.radians(2.0), 0.0))
    np.testing.assert_array_equal(rotated[1].depth.numpy(), turned(unregistered))


def test_depth_registration_keeps_the_nearest_surface():
    from mipslam.datasets.images import DepthRegistration

    depth = np.full((10, 10), 2.0, np.float32)
    depth[:, 5] = 1.0  # a near pole in front of a wall
    camera = (10.0, 10.0, 4.5, 4.5)
    T_cd = np.eye(4)
    T_cd[0, 3] = 0.1  # the depth camera 10 cm to the right: the pole moves 1 px, the wall 0.5 px, and covers it
    out = DepthRegistration(camera, T_cd, camera, (10, 10))(depth)
    assert np.all(out[:, 6] == 1.0) and set(np.unique(out)) <= {0.0, 1.0, 2.0}


def test_depth_of_another_size_needs_the_depth_camera_and_bad_calibrations_are_refused(tmp_path):
    write_tum(tmp_path / "seq", n=2)
    for path in sorted((tmp_path / "seq" / "depth").iterdir()):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(path), cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2),
                                          interpolation=cv2.INTER_NEAREST))
    with pytest.raises(DatasetError, match="registered at the same size"):
        TUMSequence(tmp_path / "seq", tum_cfg(tmp_path / "seq"))[0]
    i = TUMSequence(tmp_path / "seq", tum_cfg(tmp_path / "seq")).intrinsics
    half = (i.fx / 2, i.fy / 2, (i.cx - 0.5) / 2, (i.cy - 0.5) / 2)
    frame = TUMSequence(tmp_path / "seq", tum_cfg(tmp_path / "seq", depth_intrinsics=half))[0]
    assert frame.depth.shape == frame.color.shape[:2] and float((frame.depth > 0).float().mean()) > 0.95
    for bad in ({"depth_intrinsics": (500.0, 500.0, 320.0)}, {"depth_intrinsics": (0.0, 500.0, 320.0, 240.0)},
                {"depth_extrinsics": (0.02, 0.0)}, {"depth_extrinsics": (0.02, 0.0, float("inf"))}):
        key = next(iter(bad))
        with pytest.raises(ConfigError, match=f"dataset.{key}"):
            DatasetConfig(**bad)
    with pytest.raises(ConfigError, match="librealsense registers"):
        DatasetConfig(kind="realsense", depth_extrinsics=(0.025, 0.0, 0.0))


# ----------------------------------------------------------------------------- the frame cache

def test_frame_cache_reads_ahead_once_and_gives_the_same_frames(tmp_path):
    from mipslam.datasets import FrameCache

    write_replica(tmp_path / "rep")
    sequence = make_sequence(DatasetConfig(kind="replica", path=str(tmp_path / "rep")))
    assert sequence.random_access
    reads = []

    class Counting:  # the real reader, counting its reads
        random_access = True

        def __len__(self):
            return len(sequence)

        def __getitem__(self, index):
            reads.append(index)
            return sequence[index]

    cache = FrameCache(Counting(), torch.device("cpu"), capacity=2, read_ahead=True)
    try:
        for index in range(len(sequence)):
            frame = cache[index]
            cache.prefetch(index + 1)  # past the end: nothing
            cache.prefetch(index + 1)  # already on its way: nothing
            assert torch.equal(frame.color, sequence[index].color) and torch.equal(frame.depth, sequence[index].depth)
        assert sorted(reads) == list(range(len(sequence)))
    finally:
        cache.close()
    assert torch.equal(cache[0].depth, sequence[0].depth)  # after close: read in the caller's thread


def test_frame_cache_hands_each_frame_read_ahead_to_its_hook_on_the_reader_thread(tmp_path):
    import threading

    from mipslam.datasets import FrameCache

    write_replica(tmp_path / "rep")
    sequence = make_sequence(DatasetConfig(kind="replica", path=str(tmp_path / "rep")))
    seen = []
    cache = FrameCache(sequence, torch.device("cpu"), capacity=2, read_ahead=True)
    cache.on_read_ahead = lambda frame: seen.append((frame.index, threading.current_thread().name, frame.color))
    try:
        first = cache[0]  # read in the caller's thread: no hook
        cache.prefetch(1)
        second = cache[1]
    finally:
        cache.close()
    assert first.index == 0 and [index for index, _, _ in seen] == [1]
    assert seen[0][1].startswith("mipslam-read") and seen[0][2] is second.color  # the very image delivered


def test_frame_cache_adjusts_a_marked_frame_once_at_its_next_read(tmp_path):
    from mipslam.datasets import FrameCache

    write_replica(tmp_path / "rep")
    sequence = make_sequence(DatasetConfig(kind="replica", path=str(tmp_path / "rep")))
    adjusted = []

    def brighten(frame):  # stands in for the run's sensor timing: the same change at every read
        adjusted.append(frame.index)
        return replace(frame, color=frame.color * 0.5)

    cache = FrameCache(sequence, torch.device("cpu"), capacity=2)
    cache.adjust = brighten
    raw = cache[0]
    assert adjusted == [0]  # a frame read from the sequence is adjusted as it is cached
    cache.put(replace(raw, color=sequence[0].color))  # e.g. tracking's own copy, taken before its motion is known
    cache.adjust_when_read(0)
    assert adjusted == [0]  # nothing until it is read
    assert torch.equal(cache[0].color, sequence[0].color * 0.5) and adjusted == [0, 0]
    assert torch.equal(cache[0].color, sequence[0].color * 0.5) and adjusted == [0, 0]  # once
    cache.adjust_when_read(0)
    cache.put(replace(raw, color=sequence[0].color * 0.5))  # adjusted elsewhere
    cache[0]
    assert adjusted == [0, 0]  # put() answers the mark
    cache.adjust_when_read(1)
    cache[1], cache[2], cache[3]  # frame 1 leaves the cache before it is read again: its mark goes with it
    assert 1 not in cache._adjust_at_read


def test_kept_frames_are_not_read_again_within_the_byte_budget(tmp_path):
    from mipslam.datasets import FrameCache

    write_replica(tmp_path / "rep")
    sequence = make_sequence(DatasetConfig(kind="replica", path=str(tmp_path / "rep")))
    reads = []

    class Counting:
        random_access = False

        def __len__(self):
            return len(sequence)

        def __getitem__(self, index):
            reads.append(index)
            return sequence[index]

    frame_bytes = sequence[0].color.numel() * 4 + sequence[0].depth.numel() * 4
    cache = FrameCache(Counting(), torch.device("cpu"), capacity=1, kept_bytes=2 * frame_bytes)
    for index in range(len(sequence)):
        cache[index]
        if index < 3:
            cache.keep(index)  # three keyframes; the budget holds the newest two
    reads.clear()
    assert torch.equal(cache[1].color, sequence[1].color) and torch.equal(cache[2].depth, sequence[2].depth)
    assert reads == []
    cache[0]  # dropped from the kept frames: read again, with the same values
    assert reads == [0]
    unbounded = FrameCache(Counting(), torch.device("cpu"), capacity=1, kept_bytes=0)
    unbounded.keep(0)
    reads.clear()
    unbounded[1], unbounded[0]
    assert reads == [1, 0]  # no budget: nothing is kept


def test_frame_cache_reads_a_frame_itself_when_the_read_ahead_thread_is_late(tmp_path):
    import threading

    from mipslam.datasets import FrameCache

    write_replica(tmp_path / "rep")
    sequence = make_sequence(DatasetConfig(kind="replica", path=str(tmp_path / "rep")))
    release, reads = threading.Event(), []

    class Starved:  # the reader thread gets no CPU until released (other processes busy on every core)
        random_access = True

        def __len__(self):
            return len(sequence)

        def __getitem__(self, index):
            in_reader = threading.current_thread().name.startswith("mipslam-read")
            reads.append((index, in_reader))
            if in_reader:
                release.wait(timeout=30)
            return sequence[index]

    cache = FrameCache(Starved(), torch.device("cpu"), capacity=2, read_ahead=True)
    try:
        cache[0]
        cache.prefetch(1)
        cache.prefetch(2)  # queued behind frame 1's read: cancelled when frame 2 is read in the caller's thread
        assert torch.equal(cache[1].color, sequence[1].color)
        assert torch.equal(cache[2].depth, sequence[2].depth)
        assert (1, False) in reads and (2, False) in reads and (2, True) not in reads
    finally:
        release.set()
        cache.close()


@pytest.mark.skipif(not (sys.platform.startswith("linux") and hasattr(os, "SCHED_IDLE")),
                    reason="per-thread SCHED_IDLE is Linux's")
def test_frame_cache_reads_ahead_at_idle_priority(tmp_path):
    import threading

    from mipslam.datasets import FrameCache

    write_replica(tmp_path / "rep")
    sequence = make_sequence(DatasetConfig(kind="replica", path=str(tmp_path / "rep")))
    policies = {}

    class Recording:
        random_access = True

        def __len__(self):
            return len(sequence)

        def __getitem__(self, index):
            policies[threading.current_thread().name.startswith("mipslam-read")] = os.sched_getscheduler(0)
            return sequence[index]

    cache = FrameCache(Recording(), torch.device("cpu"), capacity=2, read_ahead=True)
    try:
        cache[0]
        cache.prefetch(1)
        cache._pending[1].result(timeout=30)
    finally:
        cache.close()
    assert policies == {False: os.SCHED_OTHER, True: os.SCHED_IDLE}  # the caller's thread keeps its class


def test_frame_cache_read_ahead_error_surfaces_when_the_frame_is_asked_for(tmp_path):
    from mipslam.datasets import FrameCache

    write_replica(tmp_path / "rep")
    sequence = make_sequence(DatasetConfig(kind="replica", path=str(tmp_path / "rep")))
    sequence.frame_paths[2][0].write_bytes(b"")  # frame 2's colour image is now empty
    cache = FrameCache(sequence, torch.device("cpu"), capacity=2, read_ahead=True)
    try:
        cache.prefetch(2)
        cache[1]
        with pytest.raises(DatasetError, match="empty"):
            cache[2]
    finally:
        cache.close()
