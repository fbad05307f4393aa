"""Rendering evaluation: metrics and protocol on a tiny run, the multi-scale table, ground truth at each scale
(exact data_synth renders; area resampling for real data), the native and the mapping resolution, frame sets
(MonoGS's novel views and the keyframes as separate rows), the map's size, LPIPS availability, the CLI flags.

The run folders here are built directly (no tracking): a data_synth sequence, a map of one Gaussian per pixel
unprojected from the exact depth of two keyframes, and the ground-truth poses as the estimate. That is a real
map that renders the scene, so the metrics have known good ranges, and it takes a second instead of minutes.
"""
from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import data_synth
from mipslam.config import config_to_yaml, load_config
from mipslam.datasets import make_sequence
from mipslam.errors import ConfigError, EvaluationError
from mipslam.evaluation.image_metrics import resize_area
from mipslam.evaluation.render_eval import (
    AreaResampledGroundTruth,
    FrameInfo,
    RenderEvalOptions,
    SyntheticGroundTruth,
    auto_frame_step,
    evaluate_render,
    frame_selections,
    load_render_context,
    novel_view_frames,
    pick_detail_crop,
    select_frames,
    synth_supersample,
)
from mipslam.evaluation.run_eval import evaluate_run
from mipslam.gaussians import GaussianMap, GaussianParameters, gaussians_from_rgbd
from mipslam.io.ply import write_map_ply
from mipslam.io.run_folder import write_json_atomic, write_text_atomic
from mipslam.io.tum import write_tum_trajectory

WIDTH, HEIGHT, FRAMES, SUPERSAMPLE = 48, 36, 3, 2
KEYFRAME_POSITIONS = (0, 2)


def make_tiny_run(root: Path, *, kind: str = "synthetic", downscale: int = 1, trajectory: str = "line",
                  frames: int = FRAMES, keyframes: tuple[int, ...] = KEYFRAME_POSITIONS, width: int = WIDTH,
                  height: int = HEIGHT) -> Path:
    """A complete run folder (the files 'mipslam run' writes) for a data_synth sequence (3 frames by default),
    mapped by unprojecting the exact depth of the keyframes (frames 0 and 2) at the ground-truth poses."""
    default = (frames, width, height) == (FRAMES, WIDTH, HEIGHT)
    sequence_dir = root / ("sequence" if default else f"sequence_{frames}_{width}x{height}")
    if not (sequence_dir / "synth.json").is_file():
        data_synth.generate(sequence_dir, layout="replica", trajectory=trajectory, width=width, height=height,
                            frames=frames, seed=3, supersample=SUPERSAMPLE)
    run_dir = root / (f"run_{kind}_{downscale}" if default and keyframes == KEYFRAME_POSITIONS
                      else f"run_{kind}_{downscale}_{frames}_{width}x{height}_kf{'-'.join(map(str, keyframes))}")
    run_dir.mkdir(parents=True)
    config = load_config("synthetic",
                         overrides=[f"dataset.path={sequence_dir}", f"dataset.kind={kind}",
                                    f"dataset.downscale={downscale}", "dataset.depth_scale=6553.5"])
    sequence = make_sequence(config.dataset)
    frames = [sequence[i] for i in range(len(sequence))]
    batches = [gaussians_from_rgbd(frames[i].color, frames[i].depth, frames[i].intrinsics.matrix(),
                                   frames[i].T_wc_gt.to(torch.float32), initial_opacity=0.95, scale_factor=0.5,
                                   anchor_keyframe=k,
                                   created_frame=i)
               for k, i in enumerate(keyframes)]
    write_map_ply(run_dir / "map.ply", GaussianMap(GaussianParameters.concatenate(batches)))
    count = sum(len(b) for b in batches)
    poses = torch.stack([f.T_wc_gt for f in frames])  # [N, 4, 4]
    stamps = np.asarray(sequence.timestamps, dtype=np.float64)
    write_tum_trajectory(run_dir / "traj_est.txt", stamps, poses)
    write_tum_trajectory(run_dir / "traj_gt.txt", stamps, poses)
    write_tum_trajectory(run_dir / "keyframes.txt", stamps[list(keyframes)], poses[list(keyframes)])
    write_text_atomic(run_dir / "config.yaml", config_to_yaml(config))
    keyframe_ids = {i: k for k, i in enumerate(keyframes)}
    write_json_atomic(run_dir / "frames.json", {"flagged": [], "frames": [
        {"index": i, "timestamp": float(stamps[i]), "status": "ok", "tracking_loss": 0.01, "tracking_iterations": 10,
         "keyframe_id": keyframe_ids.get(i, -1),
         "gaussians": sum(len(b) for b, kf in zip(batches, keyframes) if kf <= i)}
        for i in range(len(frames))]})
    k = sequence.intrinsics
    write_json_atomic(run_dir / "run.json", {
        "dataset": {"kind": kind, "name": sequence.name, "root": str(sequence.root), "timestamp_kind": "index",
                    "frames": len(sequence), "has_ground_truth": True,
                    "intrinsics": {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy, "width": k.width, "height": k.height}},
        "frames_processed": len(frames), "keyframes": len(keyframes), "gaussians": count})
    tracking = [0.0, 0.6, 0.4, *[0.5] * (len(frames) - 3)][:len(frames)]
    mapping = [1.2, 0.0, 0.8, *[0.4] * (len(frames) - 3)][:len(frames)]
    write_json_atomic(run_dir / "timings.json", {"frames": len(frames), "total_s": sum(tracking) + sum(mapping),
                                                 "frames_per_second": 1.0, "stages": {
        "tracking": {"total_s": sum(tracking), "per_frame_s": tracking},
        "mapping": {"total_s": sum(mapping), "per_frame_s": mapping}}})
    return run_dir


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    return make_tiny_run(tmp_path_factory.mktemp("render_eval"))


def test_metrics_on_a_tiny_run_are_finite_and_state_the_protocol(tiny_run):
    result = evaluate_render(tiny_run, RenderEvalOptions(frames="all", lpips=False, showcase=False))
    (row,) = result.rows
    assert (row.views, row.scale, row.mode, row.frames, row.width, row.height) == (
        "all", 1.0, "eaa", FRAMES, WIDTH, HEIGHT)
    assert 18.0 < row.psnr < 60.0 and math.isfinite(row.psnr)
    assert 0.5 < row.ssim <= 1.0
    assert row.depth_l1 is not None and 0.0 <= row.depth_l1 < 0.1  # metres
    # the keyframes are re-rendered from the pixels they were built from; the frame between them is a novel view
    views = {v.frame_index: v for v in result.views}
    assert views[0].is_keyframe and not views[1].is_keyframe
    assert result.row(1.0, "eaa") is row and result.row(1.0, "eaa", "all") is row
    with pytest.raises(KeyError):
        result.row(1.0, "eaa", "novel")
    metrics = result.to_dict()
    json.dumps(metrics)  # plain JSON
    protocol = metrics["protocol"]
    assert protocol["frames"]["evaluated"] == [0, 1, 2] and protocol["frames"]["set"] == "all"
    (selection,) = protocol["frames"]["views"]
    assert selection["views"] == "all" and selection["evaluated"] == [0, 1, 2] and selection["every"] == 1
    assert "estimated" in protocol["pose"] and protocol["exposure"].startswith("no exposure compensation")
    assert protocol["ground_truth"]["source"].startswith("exact")
    reference = protocol["scale_reference"]
    assert protocol["resolution"] == reference["resolution"] == "native"
    assert reference["size"] == reference["native_resolution"] == reference["mapping_resolution"] == [WIDTH, HEIGHT]
    assert metrics["rows"][0]["views"] == "all" and metrics["lpips"].startswith("unavailable: disabled")
    assert metrics["rows"][0]["lpips"] is None
    assert [(f["frame"], f["views"], f["keyframe"]) for f in metrics["per_frame"]] == [
        (0, "all", True), (1, "all", False), (2, "all", True)]


def test_evaluate_run_adds_the_render_section_and_the_map_size(tiny_run):
    metrics = evaluate_run(tiny_run, report=False,
                           render_options=RenderEvalOptions(frames="non_keyframes", lpips=False, showcase=False))
    assert metrics["trajectory"]["ate"]["rmse"] < 1e-6  # the estimate is the ground truth here
    render = metrics["render"]
    assert render["protocol"]["frames"]["evaluated"] == [1]
    assert render["protocol"]["frames"]["meaning"].startswith("non-keyframes")
    assert render["rows"][0]["views"] == "non_keyframes" and math.isfinite(render["rows"][0]["psnr"])
    # one Gaussian per pixel of the two 48x36 keyframes, 17 float32 properties (+ the sampling rate) each
    gaussians = render["protocol"]["map"]["gaussians"]
    size = (tiny_run / "map.ply").stat().st_size
    assert gaussians == 2 * WIDTH * HEIGHT and metrics["map"] == {
        "file": "map.ply", "gaussians": gaussians, "ply_mb": round(size / 1e6, 3)}
    assert 17 * 4 * gaussians < size < 19 * 4 * gaussians + 4096


def test_multiscale_table_has_every_scale_and_mode(tiny_run):
    scales, modes = (0.25, 1.0, 2.0), ("point", "mip", "ewa", "eaa")
    result = evaluate_render(tiny_run, RenderEvalOptions(frames="all", scales=scales, modes=modes, every=3,
                                                         lpips=False, showcase=False))
    assert [(r.views, r.scale, r.mode) for r in result.rows] == [("all", s, m) for s in scales for m in modes]
    assert result.protocol["frames"]["evaluated"] == [0] and result.protocol["frames"]["views"][0]["every"] == 3
    for row in result.rows:
        assert (row.width, row.height) == (round(row.scale * WIDTH), round(row.scale * HEIGHT))
        assert row.frames == 1 and math.isfinite(row.psnr) and -1.0 <= row.ssim <= 1.0
    # The map's Gaussians have a std-dev of half a pixel at scale 1, an eighth at 1/4: there point sampling
    # (dilated by 0.3 px^2 without opacity compensation) overestimates each one's coverage and the box filter
    # does not (measured: eaa 29.0 dB, mip 28.9, point 22.3 over the three frames).
    assert result.row(0.25, "eaa").psnr > result.row(0.25, "point").psnr + 3.0
    assert result.row(0.25, "eaa").psnr > result.row(0.25, "mip").psnr - 1.0


def test_synthetic_ground_truth_is_data_synth_render_at_that_scale(tiny_run):
    context = load_render_context(tiny_run)
    truth = context.ground_truth()
    assert isinstance(truth, SyntheticGroundTruth) and context.native_intrinsics() == context.intrinsics
    scene = data_synth.load_scene(context.sequence_root)
    poses = data_synth.ground_truth_poses(context.sequence_root)
    for scale in (0.25, 2.0):
        view = truth.view(1, scale)
        color, depth = data_synth.render_view(scene, poses[1], context.intrinsics.scaled(scale),
                                              supersample=synth_supersample(SUPERSAMPLE, scale))
        assert view.color.shape == (round(HEIGHT * scale), round(WIDTH * scale), 3)
        np.testing.assert_allclose(view.color.numpy(), np.round(color * 255) / 255, atol=1e-6)
        np.testing.assert_array_equal(view.depth.numpy(), depth)
    # at scale 1 the ground truth is exactly the sequence's own 8-bit frame
    png = cv2.imread(str(context.sequence_root / "results" / "frame000001.png"), cv2.IMREAD_COLOR)[..., ::-1]
    np.testing.assert_allclose(truth.view(1, 1.0).color.numpy() * 255, png.astype(np.float32), atol=1e-3)


def test_synth_supersample_keeps_the_ray_density_of_the_sequence():
    assert synth_supersample(4, 1.0) == 4 and synth_supersample(4, 2.0) == 4
    assert synth_supersample(4, 0.5) == 8 and synth_supersample(2, 0.125) == 16 and synth_supersample(4, 0.125) == 16


def test_real_data_ground_truth_is_area_resampled_from_the_originals(tmp_path):
    run = make_tiny_run(tmp_path, kind="replica", downscale=2)
    context = load_render_context(run)
    assert (context.intrinsics.width, context.intrinsics.height) == (WIDTH // 2, HEIGHT // 2)
    truth = context.ground_truth(resolution="mapping")
    assert isinstance(truth, AreaResampledGroundTruth)
    png = cv2.imread(str(context.sequence_root / "results" / "frame000002.png"), cv2.IMREAD_COLOR)[..., ::-1]
    original = torch.from_numpy(png.astype(np.float64) / 255.0)  # [36, 48, 3]
    view = truth.view(2, 0.5)  # half the mapping resolution = 1/4 of the original
    assert view.color.shape == (HEIGHT // 4, WIDTH // 4, 3)
    np.testing.assert_allclose(view.color.numpy(), resize_area(original, 0.25).numpy(), atol=1e-6)
    # an integer factor is the mean of each 4x4 block (computed here without resize_area) ...
    blocks = original.reshape(HEIGHT // 4, 4, WIDTH // 4, 4, 3).mean(dim=(1, 3))
    np.testing.assert_allclose(view.color.numpy(), blocks.numpy(), atol=1e-6)
    # ... which bilinear sampling is not (it reads 2x2 of every 16 pixels and aliases the textures)
    bilinear = cv2.resize(png, (WIDTH // 4, HEIGHT // 4), interpolation=cv2.INTER_LINEAR).astype(np.float64) / 255
    assert np.abs(bilinear - blocks.numpy()).max() > 0.02
    # at the mapping resolution it equals the dataset's own 2x2 area downscale
    frame = make_sequence(context.config.dataset)[2]
    np.testing.assert_allclose(truth.view(2, 1.0).color.numpy(), frame.color.numpy(), atol=1e-5)
    result = evaluate_render(context, RenderEvalOptions(resolution="mapping", scales=(0.5, 1.0, 2.0), lpips=False,
                                                        showcase=False))
    assert result.protocol["ground_truth"]["resampling"] == "area"
    assert [(r.width, r.height) for r in result.rows] == [(12, 9), (24, 18), (48, 36)]
    assert all(math.isfinite(r.psnr) for r in result.rows)


def test_native_resolution_renders_the_whole_original_image_of_a_downscaled_run(tmp_path):
    # 49x37 at downscale 2: the run mapped the 48x36 crop at 24x18; native renders all 49x37 pixels
    run = make_tiny_run(tmp_path, kind="replica", downscale=2, width=49, height=37)
    context = load_render_context(run)
    native = context.native_intrinsics()
    assert (context.intrinsics.width, context.intrinsics.height) == (24, 18)
    assert (native.width, native.height) == (49, 37)
    on_disk = make_sequence(replace(context.config.dataset, downscale=1)).intrinsics
    assert native == on_disk  # the original focal lengths and principal point, not the mapping ones rescaled
    truth = context.ground_truth()  # native by default
    assert isinstance(truth, AreaResampledGroundTruth)
    png = cv2.imread(str(context.sequence_root / "results" / "frame000001.png"), cv2.IMREAD_COLOR)[..., ::-1]
    original = torch.from_numpy(png.astype(np.float64) / 255.0)  # [37, 49, 3]
    np.testing.assert_allclose(truth.view(1, 1.0).color.numpy(), original.numpy(), atol=1e-6)  # uncropped
    np.testing.assert_allclose(truth.view(1, 0.5).color.numpy(), resize_area(original, 0.5).numpy(), atol=1e-6)

    result = evaluate_render(context, RenderEvalOptions(frames="all", scales=(0.5, 1.0), lpips=False,
                                                        showcase=False))
    assert [(r.scale, r.width, r.height) for r in result.rows] == [(0.5, 24, 18), (1.0, 49, 37)]
    assert all(math.isfinite(r.psnr) and r.frames == FRAMES for r in result.rows)
    reference = result.protocol["scale_reference"]
    assert reference["resolution"] == "native" and reference["size"] == reference["native_resolution"] == [49, 37]
    assert reference["mapping_resolution"] == [24, 18] and reference["dataset_downscale"] == 2
    assert reference["intrinsics"] == {"fx": native.fx, "fy": native.fy, "cx": native.cx, "cy": native.cy,
                                       "width": 49, "height": 37}
    assert "whole" in result.protocol["ground_truth"]["color"]
    mapping = evaluate_render(context, RenderEvalOptions(frames="all", resolution="mapping", lpips=False,
                                                         showcase=False))
    assert (mapping.rows[0].width, mapping.rows[0].height) == (24, 18)
    assert mapping.protocol["scale_reference"]["size"] == [24, 18]
    # the exact data_synth ground truth at native scale 1 is the sequence's own full-resolution frame
    exact = context.ground_truth("exact")
    assert isinstance(exact, SyntheticGroundTruth)
    np.testing.assert_allclose(exact.view(1, 1.0).color.numpy() * 255, png.astype(np.float32), atol=1e-3)


def _monogs_eval_frames(n: int, kf_indices: list[int], interval: int = 5) -> list[int]:
    """MonoGS utils/eval_utils.py eval_rendering's frame loop, verbatim."""
    chosen = []
    for idx in range(0, n, interval):
        if idx in kf_indices:
            continue
        chosen.append(idx)
    return chosen


def test_split_selects_monogs_novel_views_and_the_keyframes():
    keyframe_positions = [0, 3, 5, 10, 11, 20, 33]
    kf_ids = {p: k for k, p in enumerate(keyframe_positions)}
    # index = 2 x position (a run read at stride 2): the rule reads positions in frames.json
    frames = [FrameInfo(p, 2 * p, float(p), kf_ids.get(p, -1)) for p in range(37)]
    novel = novel_view_frames(frames)
    assert [f.position for f in novel] == _monogs_eval_frames(37, keyframe_positions) == [15, 25, 30, 35]
    assert [f.index for f in novel] == [30, 50, 60, 70]
    novel_sel, training = frame_selections(frames, "split", None, cells=1)
    assert (novel_sel.views, novel_sel.every, novel_sel.frames) == ("novel", 5, tuple(novel))
    assert novel_sel.in_set == 37 - len(keyframe_positions)
    assert (training.views, training.every, [f.position for f in training.frames]) == (
        "training", 1, keyframe_positions)
    assert novel_sel.to_dict()["evaluated"] == [30, 50, 60, 70] and novel_sel.to_dict()["positions"] == [15, 25, 30, 35]
    # every given: the novel views' position step
    novel3, _ = frame_selections(frames, "split", 3, cells=1)
    assert [f.position for f in novel3.frames] == _monogs_eval_frames(37, keyframe_positions, 3)
    # the training views take the automatic step: at most 50 keyframes (8 for a multi-cell table)
    many = [FrameInfo(p, p, float(p), p if p % 2 == 0 else -1) for p in range(240)]  # 120 keyframes
    _, training = frame_selections(many, "split", None, cells=1)
    assert training.every == 3 and [f.position for f in training.frames] == list(range(0, 240, 6))
    _, training = frame_selections(many, "split", None, cells=4)
    assert training.every == 15 and len(training.frames) == 8
    # a single set stays one selection named by the set
    (single,) = frame_selections(frames, "non_keyframes", None, cells=1)
    assert single.views == "non_keyframes" and len(single.frames) == 30


def test_split_evaluates_novel_and_training_views_as_separate_rows(tmp_path):
    run = make_tiny_run(tmp_path, frames=7, keyframes=(0, 2, 6))
    metrics = evaluate_run(run, report=False)  # the run's own eval config: split, native
    assert metrics["evaluation"]["label"] is None
    render = metrics["render"]
    assert [(r["views"], r["frames"]) for r in render["rows"]] == [("novel", 1), ("training", 3)]
    frames = render["protocol"]["frames"]
    assert frames["set"] == "split" and frames["evaluated"] == [0, 2, 5, 6]
    novel, training = frames["views"]
    assert (novel["views"], novel["evaluated"], novel["every"]) == ("novel", [5], 5) and "MonoGS" in novel["rule"]
    assert (training["views"], training["evaluated"]) == ("training", [0, 2, 6])
    assert sorted((f["frame"], f["views"], f["keyframe"]) for f in render["per_frame"]) == [
        (0, "training", True), (2, "training", True), (5, "novel", False), (6, "training", True)]
    # the keyframes are re-rendered from the pixels they were built from; frame 5 is a novel view
    rows = {r["views"]: r for r in render["rows"]}
    assert rows["training"]["psnr"] > rows["novel"]["psnr"] and math.isfinite(rows["novel"]["psnr"])
    result = evaluate_render(run, RenderEvalOptions(lpips=False, showcase=False))
    assert result.view_sets == ("novel", "training")
    assert result.row(1.0, "eaa").views == "novel" and result.row(1.0, "eaa", "training").frames == 3
    # every 6: positions 0 and 6 are keyframes, so no novel view qualifies and only the training rows remain
    (row,) = evaluate_render(run, RenderEvalOptions(every=6, lpips=False, showcase=False)).rows
    assert row.views == "training"


def test_old_run_config_without_resolution_evaluates_at_native_resolution(tmp_path):
    run = make_tiny_run(tmp_path, kind="replica", downscale=2)
    text = (run / "config.yaml").read_text()
    assert "resolution: native" in text
    old = "\n".join(line for line in text.splitlines() if "resolution:" not in line).replace("frames: split",
                                                                                             "frames: all")
    (run / "config.yaml").write_text(old + "\n")
    metrics = evaluate_run(run, report=False)
    assert metrics["evaluation"]["label"] is None
    assert metrics["render"]["protocol"]["resolution"] == "native"
    assert [(r["views"], r["width"], r["height"]) for r in metrics["render"]["rows"]] == [("all", WIDTH, HEIGHT)]


def test_frame_sets_and_automatic_step():
    frames = [FrameInfo(k, k, float(k), kf) for k, kf in enumerate([0, -1, -1, 1, -1, 2])]
    assert [f.index for f in select_frames(frames, "keyframes", 1)] == [0, 3, 5]
    assert [f.index for f in select_frames(frames, "non_keyframes", 1)] == [1, 2, 4]
    assert [f.index for f in select_frames(frames, "all", 2)] == [0, 2, 4]
    assert auto_frame_step(40, 1) == 1 and auto_frame_step(120, 1) == 3
    assert auto_frame_step(8, 20) == 1 and auto_frame_step(60, 20) == 8
    with pytest.raises(EvaluationError):
        select_frames(frames, "training", 1)
    with pytest.raises(ConfigError):
        RenderEvalOptions(modes=("box",))
    with pytest.raises(ConfigError):
        RenderEvalOptions(scales=(0.5, -1.0))


def test_empty_frame_set_is_an_error(tiny_run, tmp_path):
    data = json.loads((tiny_run / "frames.json").read_text())
    copy = tmp_path / "run"
    copy.mkdir()
    for name in ("config.yaml", "run.json", "traj_est.txt", "map.ply"):
        (copy / name).write_bytes((tiny_run / name).read_bytes())
    for frame in data["frames"]:
        frame["keyframe_id"] = 0
    (copy / "frames.json").write_text(json.dumps(data))
    with pytest.raises(EvaluationError, match="non_keyframes"):
        evaluate_render(copy, RenderEvalOptions(frames="non_keyframes", lpips=False, showcase=False))


def test_detail_crop_finds_the_textured_region():
    image = torch.full((40, 60, 3), 0.5)
    yy, xx = torch.meshgrid(torch.arange(40), torch.arange(60), indexing="ij")
    checker = ((yy // 2 + xx // 2) % 2).float()
    image[20:, 36:] = checker[20:, 36:, None]
    x0, y0, x1, y1 = pick_detail_crop(image, fraction=0.4)
    assert x0 >= 0.55 and y0 >= 0.45 and x1 <= 1.0 and y1 <= 1.0
    assert math.isclose(x1 - x0, 0.4) and math.isclose(y1 - y0, 0.4)


def test_lpips_unavailable_is_stated(tiny_run, monkeypatch, tmp_path):
    monkeypatch.setenv("MIPSLAM_LPIPS_WEIGHTS", str(tmp_path / "missing.ckpt"))
    result = evaluate_render(tiny_run, RenderEvalOptions(every=3, showcase=False))
    assert result.lpips_status.startswith("unavailable:") and "missing.ckpt" in result.lpips_status
    assert result.rows[0].lpips is None and result.protocol["metrics"]["lpips"] == result.lpips_status


def test_lpips_computed_where_the_weights_are_installed(tiny_run):
    from mipslam.evaluation.lpips import LPIPSUnavailableError, find_lpips_alex_weights

    try:
        find_lpips_alex_weights()
    except LPIPSUnavailableError as error:
        pytest.skip(f"LPIPS weights not installed: {error}")
    result = evaluate_render(tiny_run, RenderEvalOptions(scales=(0.5, 1.0), every=3, showcase=False))
    assert result.lpips_status.startswith("computed")
    assert result.row(0.5, "eaa").lpips is None  # 24x18 is below LPIPS's 31 px minimum
    assert 0.0 <= result.row(1.0, "eaa").lpips < 1.0


def test_moved_dataset_leaves_trajectory_metrics_and_says_why(tmp_path):
    run = make_tiny_run(tmp_path)
    (tmp_path / "sequence").rename(tmp_path / "moved")
    metrics = evaluate_run(run, report=False)
    assert "unavailable" in metrics["render"] and "sequence" in metrics["render"]["unavailable"]
    assert metrics["trajectory"]["ate"]["count"] == FRAMES
