"""The frame loop end to end on tiny synthetic sequences: outputs, resume, final refinement, bad frames,
observer timings and progress. Tracking and mapping alone: tests/test_tracking.py, tests/test_mapping.py."""
from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from mipslam.mapping import MappingOptions
from mipslam.checkpoint import load_latest_checkpoint
from mipslam.cli import main
from mipslam.io.ply import read_map_ply
from mipslam.io.tum import read_tum_trajectory
from mipslam.pipeline import PipelineHooks, run_slam
from mipslam.state import SLAMState
from tiny_runs import REPO, TINY, tiny_config


def test_run_writes_every_output_and_a_readable_map(tiny_sequence, tmp_path, caplog):
    run_dir = tmp_path / "run"
    with caplog.at_level(logging.INFO, logger="mipslam.run_control"):
        summary = run_slam(tiny_config(tiny_sequence), run_dir)
    # stderr is not a terminal here: progress comes as log lines, after the first frame and after the last
    progress = [r.getMessage() for r in caplog.records if r.getMessage().startswith("frame ")]
    assert progress[0].startswith("frame 1/6, ") and progress[-1].startswith("frame 6/6, "), progress
    assert all("frames/s" in line and "keyframes" in line and "Gaussians" in line and "tracking loss" in line
               for line in progress)
    for name in ("config.yaml", "traj_est.txt", "traj_gt.txt", "keyframes.txt", "map.ply", "metrics.json",
                 "timings.json", "frames.json", "run.json"):
        assert (run_dir / name).is_file(), name
    assert list((run_dir / "checkpoints").glob("checkpoint-*.ckpt"))
    est = read_tum_trajectory(run_dir / "traj_est.txt")
    assert len(est.timestamps) == 6 and np.isfinite(est.T_wc).all()
    gmap = read_map_ply(run_dir / "map.ply")
    assert len(gmap) == summary.gaussians > 0
    metrics = json.loads((run_dir / "metrics.json").read_text())
    ate = metrics["trajectory"]["ate"]["rmse"]
    assert metrics["trajectory"]["protocol"]["num_matched"] == 6
    assert ate < 0.03, f"ATE {ate:.4f} m on a 6-frame synthetic sequence"
    timings = json.loads((run_dir / "timings.json").read_text())
    assert set(timings["stages"]) >= {"tracking", "keyframe", "mapping", "loop", "pgo"}
    assert all(len(stage["per_frame_s"]) == 6 for stage in timings["stages"].values())
    assert timings["stages"]["tracking"]["per_frame_s"][0] < 0.5  # the renderer's loading is not charged to frame 0
    assert summary.flagged == 0


def test_cli_synth_run_eval_smoke(tmp_path):
    seq, run_dir = tmp_path / "seq", tmp_path / "run"
    assert main(["synth", "--out", str(seq), "--format", "tum", "--trajectory", "line", "--width", "32", "--height",
                 "24", "--frames", "4", "--supersample", "2"]) == 0
    args = ["run", str(REPO / "mipslam" / "configs" / "synthetic.yaml"), "--preset", "fast", "--out", str(run_dir),
            "--set", f"dataset.path={seq}"]
    for item in TINY:
        args += ["--set", item]
    assert main(args) == 0
    assert main(["eval", str(run_dir)]) == 0
    assert json.loads((run_dir / "metrics.json").read_text())["trajectory"]["ate"]["count"] == 4
    assert main(["run", "synthetic", "--set", "tracking.iteratons=3"]) == 2
    assert main(["eval", str(tmp_path / "missing")]) == 2


# With a final refinement the first session refines its own outputs at frame 4; the continuation must start
# from the state the frames left, not from that refined map.
@pytest.mark.parametrize("extra", [(), ("refine.passes=2",)], ids=["plain", "final_refinement"])
def test_resume_equals_uninterrupted_run(tiny_sequence, tmp_path, extra):
    full_dir, split_dir = tmp_path / "full", tmp_path / "split"
    run_slam(tiny_config(tiny_sequence, *extra), full_dir, evaluate=False)
    # Stop after frame 3 (max_frames may differ on resume), then continue to the end.
    run_slam(tiny_config(tiny_sequence, "dataset.max_frames=4", *extra), split_dir, evaluate=False)
    run_slam(tiny_config(tiny_sequence, *extra), split_dir, resume=True, evaluate=False)
    full = read_tum_trajectory(full_dir / "traj_est.txt")
    split = read_tum_trajectory(split_dir / "traj_est.txt")
    np.testing.assert_array_equal(full.timestamps, split.timestamps)
    np.testing.assert_allclose(split.T_wc, full.T_wc, atol=1e-6)
    map_full, map_split = read_map_ply(full_dir / "map.ply"), read_map_ply(split_dir / "map.ply")
    assert len(map_full) == len(map_split)
    torch.testing.assert_close(map_split.means, map_full.means, atol=1e-5, rtol=0)
    torch.testing.assert_close(map_split.colors_raw, map_full.colors_raw, atol=1e-5, rtol=0)
    # the checkpoint carries the timings: the resumed run's timings.json covers both sessions
    timings = json.loads((split_dir / "timings.json").read_text())
    assert timings["frames"] == 6 and len(timings["stages"]["tracking"]["per_frame_s"]) == 6


def test_final_refinement_keeps_the_trajectory_improves_the_map_and_repeats_exactly(tiny_sequence, tmp_path):
    plain_dir, refined_dir = tmp_path / "plain", tmp_path / "refined"
    run_slam(tiny_config(tiny_sequence, "eval.frames=keyframes"), plain_dir)
    refined = tiny_config(tiny_sequence, "eval.frames=keyframes", "refine.passes=4", "refine.lr_poses=0")
    run_slam(refined, refined_dir)
    np.testing.assert_array_equal(read_tum_trajectory(refined_dir / "traj_est.txt").T_wc,
                                  read_tum_trajectory(plain_dir / "traj_est.txt").T_wc)

    def psnr_db(run_dir: Path) -> float:
        return json.loads((run_dir / "metrics.json").read_text())["render"]["rows"][0]["psnr"]

    # PSNR on the training views (the keyframes), which the refinement fits: +0.27 dB when written
    assert psnr_db(refined_dir) > psnr_db(plain_dir) + 0.15, (psnr_db(plain_dir), psnr_db(refined_dir))
    refine_s = json.loads((refined_dir / "timings.json").read_text())["stages"]["refine"]["per_frame_s"]
    assert len(refine_s) == 6 and refine_s[:-1] == [0.0] * 5 and refine_s[-1] > 0
    # The checkpoint holds the state before the refinement: resuming the finished run refines it again, the same way.
    first = read_map_ply(refined_dir / "map.ply")
    run_slam(refined, refined_dir, resume=True)
    again = read_map_ply(refined_dir / "map.ply")
    torch.testing.assert_close(again.means, first.means, atol=0, rtol=0)
    torch.testing.assert_close(again.colors_raw, first.colors_raw, atol=0, rtol=0)


def test_resume_refuses_an_incompatible_config(tiny_sequence, tmp_path):
    from mipslam.errors import CheckpointError

    run_slam(tiny_config(tiny_sequence, "dataset.max_frames=2"), tmp_path / "r", evaluate=False)
    with pytest.raises(CheckpointError, match="render.mode"):
        run_slam(tiny_config(tiny_sequence, "render.mode=point"), tmp_path / "r", resume=True, evaluate=False)


def test_black_frame_without_depth_is_flagged_and_nothing_is_nan(tiny_sequence, tmp_path):
    seq = tmp_path / "seq"
    shutil.copytree(tiny_sequence, seq)
    cv2.imwrite(str(seq / "results" / "frame000003.png"), np.zeros((30, 40, 3), np.uint8))
    cv2.imwrite(str(seq / "results" / "depth000003.png"), np.zeros((30, 40), np.uint16))
    run_dir = tmp_path / "run"
    summary = run_slam(tiny_config(seq), run_dir)
    frames = json.loads((run_dir / "frames.json").read_text())
    assert frames["flagged"] == [3]
    assert frames["frames"][3]["status"] == "too_few_valid_pixels"
    assert summary.frames == 6
    est = read_tum_trajectory(run_dir / "traj_est.txt")
    assert np.isfinite(est.T_wc).all()
    gmap = read_map_ply(run_dir / "map.ply")
    for tensor in (gmap.means, gmap.log_scales, gmap.opacity_logits, gmap.colors_raw, gmap.quats_wxyz):
        assert torch.isfinite(tensor).all()
    # Tracking recovers after the bad frame.
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["tracking_failures"]["frames"] == [3]


def test_tracked_poses_survive_a_checkpoint_and_old_checkpoints_fall_back_to_the_poses(tiny_sequence, tmp_path):
    # every frame a keyframe and a large pose rate: mapping visibly moves the keyframes away from their tracked poses
    config = tiny_config(tiny_sequence, "mapping.lr_poses=1e-3", "keyframes.covisibility_threshold=1.0")
    run_slam(config, tmp_path / "run", evaluate=False)
    checkpoint = load_latest_checkpoint(tmp_path / "run" / "checkpoints")
    state = SLAMState.from_checkpoint(checkpoint.tensors, checkpoint.metadata, MappingOptions.from_config(config.mapping), torch.device("cpu"))
    moved = [float((f.T_wc - f.T_wc_tracked).abs().max()) for f in state.frames if f.keyframe_id > 0]
    assert moved and max(moved) > 1e-4, moved
    torch.testing.assert_close(torch.stack([f.T_wc_tracked for f in state.frames]),
                               checkpoint.tensors["frames.T_wc_tracked"], rtol=0, atol=0)
    old = {k: v for k, v in checkpoint.tensors.items() if k != "frames.T_wc_tracked"}
    state = SLAMState.from_checkpoint(old, checkpoint.metadata, MappingOptions.from_config(config.mapping), torch.device("cpu"))
    for frame in state.frames:
        torch.testing.assert_close(frame.T_wc_tracked, frame.T_wc, rtol=0, atol=0)


def test_depth_taken_late_and_a_rolling_shutter_are_undone_and_resume_exactly(tmp_path):
    """A TUM-layout sequence whose depth comes 0.4 frame intervals after the colour (data_synth --depth-delay) and
    whose colour rows are read over 0.6 of an interval (--rolling-shutter): the run moves each depth image and
    each colour image's rows with its tracked motion, the same way again when it resumes."""
    import data_synth

    sequence = tmp_path / "seq"
    data_synth.generate(sequence, layout="tum", trajectory="loop", width=40, height=30, frames=6, seed=0,
                        supersample=2, depth_delay=0.4, rolling_shutter=0.6)
    full_dir, split_dir, off_dir = tmp_path / "full", tmp_path / "split", tmp_path / "off"
    on = (f"dataset.rolling_shutter_readout_s={0.6 / 30}",)
    depth_time = PipelineHooks(constants={"tracking.align_depth_time": True})  # a tracking constant, off in a run
    run_slam(tiny_config(sequence, *on), full_dir, evaluate=False, hooks=depth_time)
    run_slam(tiny_config(sequence, *on, "dataset.max_frames=4"), split_dir, evaluate=False, hooks=depth_time)
    run_slam(tiny_config(sequence, *on), split_dir, resume=True, evaluate=False, hooks=depth_time)
    full = read_tum_trajectory(full_dir / "traj_est.txt")
    np.testing.assert_allclose(read_tum_trajectory(split_dir / "traj_est.txt").T_wc, full.T_wc, atol=1e-6)
    torch.testing.assert_close(read_map_ply(split_dir / "map.ply").means, read_map_ply(full_dir / "map.ply").means,
                               atol=1e-5, rtol=0)
    run_slam(tiny_config(sequence), off_dir, evaluate=False)  # off by default
    assert not np.array_equal(read_tum_trajectory(off_dir / "traj_est.txt").T_wc, full.T_wc)


def test_colour_rows_moved_when_a_frame_is_read_again_equal_those_moved_right_after_tracking(tmp_path, monkeypatch):
    """A rolling shutter alone: the cache moves a frame's colour rows when a later stage reads it (mapping a
    keyframe), by the motion of its record; the same images as moving every frame right after its tracking."""
    import data_synth
    from mipslam.sensor_sync import SensorTiming

    sequence = tmp_path / "seq"
    data_synth.generate(sequence, layout="tum", trajectory="loop", width=40, height=30, frames=6, seed=0,
                        supersample=2, rolling_shutter=0.6)
    on = (f"dataset.rolling_shutter_readout_s={0.6 / 30}",)
    run_slam(tiny_config(sequence, *on), tmp_path / "lazy", evaluate=False)
    monkeypatch.setattr(SensorTiming, "moves_colour_only", lambda timing, frame: False)  # every frame moved at once
    run_slam(tiny_config(sequence, *on), tmp_path / "eager", evaluate=False)
    for name in ("traj_est.txt", "map.ply"):
        assert (tmp_path / "lazy" / name).read_bytes() == (tmp_path / "eager" / name).read_bytes()
    monkeypatch.undo()
    run_slam(tiny_config(sequence, *on, "dataset.max_frames=4"), tmp_path / "split", evaluate=False)
    run_slam(tiny_config(sequence, *on), tmp_path / "split", resume=True, evaluate=False)
    np.testing.assert_allclose(read_tum_trajectory(tmp_path / "split" / "traj_est.txt").T_wc,
                               read_tum_trajectory(tmp_path / "lazy" / "traj_est.txt").T_wc, atol=1e-6)


def test_the_final_refinement_reads_the_recorded_images_at_half_the_cameras_resolution_or_finer(tiny_sequence):
    from mipslam.datasets import make_sequence
    from mipslam.pipeline import final_refinement_images

    for downscale, width in ((1, 40), (2, 20), (4, 20)):  # 40x30 frames: the refinement never reads below 1/2
        config = tiny_config(tiny_sequence, f"dataset.downscale={downscale}")
        sequence = make_sequence(config.dataset)
        images = final_refinement_images(config, sequence)
        if downscale <= 2:
            assert images is sequence
        assert images[3].color.shape[1] == width and images[3].intrinsics.width == width

    class Stream:  # a live camera: frames cannot be read again
        random_access = False

    assert final_refinement_images(tiny_config(tiny_sequence), Stream()) is None


def test_a_run_registers_depth_from_a_camera_of_its_own(tmp_path):
    """End to end: a TUM-layout sequence whose depth comes from a second camera (data_synth --depth-baseline and
    --depth-focal-ratio) runs with that camera's calibration, every frame tracked, outputs finite, and resumes
    exactly. (The registration itself: tests/test_datasets.py.)"""
    import data_synth

    data_synth.generate(tmp_path / "raw", layout="tum", trajectory="loop", width=40, height=30, frames=6, seed=0,
                        supersample=2, depth_baseline=0.025, depth_focal_ratio=1.1)
    k = json.loads((tmp_path / "raw" / "synth.json").read_text())["intrinsics"]
    calibration = (f"dataset.depth_intrinsics=[{1.1 * k['fx']},{1.1 * k['fy']},{k['cx']},{k['cy']}]",
                   "dataset.depth_extrinsics=[0.025,0,0]")
    summary = run_slam(tiny_config(tmp_path / "raw", *calibration), tmp_path / "full", evaluate=False)
    assert summary.frames == 6 and summary.flagged == 0 and summary.gaussians > 0
    full = read_tum_trajectory(tmp_path / "full" / "traj_est.txt").T_wc
    assert np.isfinite(full).all() and bool(torch.isfinite(read_map_ply(tmp_path / "full" / "map.ply").means).all())
    run_slam(tiny_config(tmp_path / "raw", *calibration, "dataset.max_frames=4"), tmp_path / "split", evaluate=False)
    run_slam(tiny_config(tmp_path / "raw", *calibration), tmp_path / "split", resume=True, evaluate=False)
    np.testing.assert_allclose(read_tum_trajectory(tmp_path / "split" / "traj_est.txt").T_wc, full, atol=1e-6)
