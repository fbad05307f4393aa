"""SLAM core end to end on tiny synthetic sequences: tracking, mapping, outputs, resume, bad frames."""
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
from mipslam.checkpoint import load_latest_checkpoint
from mipslam.cli import main
from mipslam.config import RenderConfig, load_config
from mipslam.datasets import make_sequence
from mipslam.gaussians import ActivatedGaussians, GaussianMap, GaussianOptimizer, gaussians_from_rgbd
from mipslam.geometry import se3_exp, se3_inverse, se3_log
from mipslam.io.ply import read_map_ply
from mipslam.io.tum import read_tum_trajectory
from mipslam.mapping import Mapper, MappingView
from mipslam.pipeline import run_slam
from mipslam.rendering import frustum_subset, render_view
from mipslam.state import SLAMState
from mipslam.tracking import Tracker, constant_velocity_prediction
from mipslam.types import Intrinsics

REPO = Path(__file__).resolve().parent.parent

# Small enough for a few seconds per run on 2 cores, large enough for tracking to be meaningful.
TINY = [
    "mapping.first_frame_iterations=30", "mapping.iterations=8", "mapping.densify_pixel_stride=2",
    "tracking.iterations=15", "keyframes.window_size=3", "keyframes.random_past=1", "run.threads=1",
]


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "seq"
    data_synth.generate(out, layout="replica", trajectory="loop", width=40, height=30, frames=6, seed=0, supersample=2)
    return out


def tiny_config(sequence: Path, *extra: str):
    return load_config(REPO / "configs" / "synthetic.yaml", overrides=[f"dataset.path={sequence}", *TINY, *extra])


def test_run_writes_every_output_and_a_readable_map(tiny_sequence, tmp_path):
    run_dir = tmp_path / "run"
    summary = run_slam(tiny_config(tiny_sequence), run_dir)
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
    assert set(timings["stages"]) >= {"tracking", "mapping"}
    assert summary.flagged == 0


def test_cli_synth_run_eval_smoke(tmp_path):
    seq, run_dir = tmp_path / "seq", tmp_path / "run"
    assert main(["synth", "--out", str(seq), "--format", "tum", "--trajectory", "line", "--width", "32", "--height",
                 "24", "--frames", "4", "--supersample", "2"]) == 0
    args = ["run", str(REPO / "configs" / "synthetic.yaml"), "--preset", "fast", "--out", str(run_dir),
            "--set", f"dataset.path={seq}"]
    for item in TINY:
        args += ["--set", item]
    assert main(args) == 0
    assert main(["eval", str(run_dir)]) == 0
    assert json.loads((run_dir / "metrics.json").read_text())["trajectory"]["ate"]["count"] == 4
    assert main(["run", str(REPO / "configs" / "synthetic.yaml"), "--set", "tracking.iteratons=3"]) == 2
    assert main(["eval", str(tmp_path / "missing")]) == 2


# With a final refinement the first session refines its own outputs at frame 4; the continuation must start
# from the state the frames left, not from that refined map.
@pytest.mark.parametrize("extra", [(), ("mapping.final_iterations=10",)], ids=["plain", "final_refinement"])
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


def test_final_refinement_keeps_the_trajectory_improves_the_map_and_repeats_exactly(tiny_sequence, tmp_path):
    plain_dir, refined_dir = tmp_path / "plain", tmp_path / "refined"
    run_slam(tiny_config(tiny_sequence, "eval.frames=keyframes"), plain_dir)
    refined = tiny_config(tiny_sequence, "eval.frames=keyframes", "mapping.final_iterations=40")
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
    import shutil

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


def _map_of_first_frame(sequence_path: Path, iterations: int):
    config = tiny_config(sequence_path)
    sequence = make_sequence(config.dataset)
    frame = sequence[0]
    T_wc = sequence.gt_T_wc[0]
    gmap = GaussianMap.empty()
    optimizer = GaussianOptimizer.from_config(gmap, config.mapping)
    mapper = Mapper(config.mapping, config.render)
    view = MappingView(0, frame.color, frame.depth, T_wc, torch.zeros(2), frame.intrinsics, optimize_pose=False)
    mapper.densify(gmap, optimizer, view, frame_index=0)
    first, last, _ = mapper.optimize(gmap, optimizer, [view], iterations, torch.Generator().manual_seed(0))
    return config, sequence, gmap, first, last


def test_mapping_reduces_the_loss_on_a_fixed_view(tiny_sequence):
    _, _, gmap, first, last = _map_of_first_frame(tiny_sequence, 40)
    assert math.isfinite(first) and last < 0.7 * first, (first, last)
    assert len(gmap) > 0


def test_densifying_a_view_the_map_already_holds_adds_no_copies(tiny_sequence):
    config, sequence, gmap, _, _ = _map_of_first_frame(tiny_sequence, 40)
    frame = sequence[0]
    # Make the mapped surface nearly transparent: every pixel now fails the opacity test, but every
    # Gaussian that would be added lands on an existing centre (mapping raises their opacity instead).
    with torch.no_grad():
        gmap.opacity_logits.fill_(-3.0)
    view = MappingView(0, frame.color, frame.depth, sequence.gt_T_wc[0], torch.zeros(2), frame.intrinsics,
                       optimize_pose=False)
    optimizer = GaussianOptimizer.from_config(gmap, config.mapping)
    before = len(gmap)
    with_check = Mapper(config.mapping, config.render).densify(gmap, optimizer, view, frame_index=1)
    gmap.remove(torch.arange(len(gmap)) >= before, optimizer)
    off = replace(config.mapping, add_min_distance_ratio=0.0)
    without_check = Mapper(off, config.render).densify(gmap, optimizer, view, frame_index=1)
    assert without_check > 0.5 * before  # a second layer over the first
    assert with_check <= 0.05 * without_check, (with_check, without_check)


@pytest.fixture(scope="module")
def one_frame_map(tmp_path_factory):
    # 64x48: at 40x30 the map of one frame is too coarse to pin the pose to a few millimetres.
    seq = tmp_path_factory.mktemp("track") / "seq"
    data_synth.generate(seq, layout="replica", trajectory="loop", width=64, height=48, frames=2, seed=0, supersample=2)
    config, sequence, gmap, _, _ = _map_of_first_frame(seq, 60)
    return seq, config, sequence, gmap.activated().detached()


def _preset_tracking_overrides(preset: str) -> list[str]:
    """The preset's optimiser keys as overrides (read from configs/, so the tests follow a retune)."""
    tracking = load_config(REPO / "configs" / "synthetic.yaml", preset=preset).tracking
    keys = ("optimizer", "lr_translation", "lr_rotation", "convergence_threshold")
    return [f"tracking.{key}={getattr(tracking, key)}" for key in keys]


# adam is the default; rprop as the balanced preset sets it.
_OPTIMIZERS = {"adam": [], "rprop": _preset_tracking_overrides("balanced")}


@pytest.mark.parametrize("optimizer,exposure,render_mode", [
    ("adam", False, None), ("rprop", False, None), ("rprop", True, None),
    ("rprop", False, "mip"),  # the eaa map rendered with Mip-Splatting's footprint (tracking.render_mode)
])
def test_tracking_recovers_a_known_pose_perturbation(one_frame_map, optimizer, exposure, render_mode):
    seq, config, sequence, gaussians = one_frame_map
    frame = sequence[0]
    T_wc_true = sequence.gt_T_wc[0]
    perturbation = se3_exp(torch.tensor([0.015, -0.01, 0.01, 0.01, -0.015, 0.005], dtype=torch.float64))
    T_wc_init = T_wc_true @ perturbation
    settings = tiny_config(seq, "tracking.iterations=80", f"tracking.use_exposure={str(exposure).lower()}",
                           *_OPTIMIZERS[optimizer]).tracking
    settings = replace(settings, render_mode=render_mode)
    assert settings.optimizer == optimizer and config.render.mode == "eaa"
    tracker = Tracker(settings, config.render)
    result = tracker.track(gaussians, frame, T_wc_init, running_loss=None)
    assert result.ok
    if render_mode is not None:  # the key is honoured: the same start in the map's own mode ends elsewhere
        own_mode = Tracker(replace(settings, render_mode=None), config.render).track(gaussians, frame, T_wc_init,
                                                                                      running_loss=None)
        assert own_mode.loss != result.loss
    error_before = se3_log(se3_inverse(T_wc_true) @ T_wc_init)
    error_after = se3_log(se3_inverse(T_wc_true) @ result.T_wc)
    assert error_after[:3].norm() < 0.3 * error_before[:3].norm(), (error_before, error_after)
    assert error_after[3:].norm() < 0.3 * error_before[3:].norm(), (error_before, error_after)


def test_rprop_tracking_stops_early_at_the_pose_adam_reaches_with_every_iteration(one_frame_map):
    # From the true pose, Rprop's steps halve at each sign change, so its next step falls below the
    # threshold well before the cap; Adam keeps stepping by about lr and uses all 80. Both should settle at
    # the same optimum of this coarse one-frame map (a few mm from the true pose).
    seq, config, sequence, gaussians = one_frame_map
    T_wc_true = sequence.gt_T_wc[0]
    ends = {}
    for name, extra in _OPTIMIZERS.items():
        settings = tiny_config(seq, "tracking.iterations=80", *extra).tracking
        result = Tracker(settings, config.render).track(gaussians, sequence[0], T_wc_true, running_loss=None)
        assert result.ok
        ends[name] = (result.iterations, se3_log(se3_inverse(T_wc_true) @ result.T_wc))
    assert ends["rprop"][0] < 40 and ends["adam"][0] == 80, ends
    # Adam still steps by about its rate (2 mm, 4 mrad) at the end, so its best iterate places the optimum
    # only to about a millimetre: float round-off in the map moves it by that much.
    assert (ends["rprop"][1] - ends["adam"][1]).norm() < 2e-3, ends


def test_mapping_moves_a_perturbed_keyframe_pose_towards_the_truth(one_frame_map):
    # Mapping refines the poses of the keyframes it trains on (mapping.lr_poses), with the first keyframe
    # fixed as the anchor. Adam moves a pose by about the rate per step: 3e-4 over 40 steps can undo the
    # perturbation; the default 1e-4 leaves 2.9 mm and 3.6 mrad of its 5.4 / 5.4 (docs/bench.md "Session 13").
    seq = one_frame_map[0]
    config, sequence, gmap, _, _ = _map_of_first_frame(seq, 60)
    mapping = replace(config.mapping, lr_poses=3e-4)
    optimizer = GaussianOptimizer.from_config(gmap, mapping)
    first, second = sequence[0], sequence[1]
    T_wc_true = sequence.gt_T_wc[1]
    perturbation = se3_exp(torch.tensor([0.004, -0.003, 0.002, 0.003, -0.004, 0.002], dtype=torch.float64))
    moved = MappingView(1, second.color, second.depth, T_wc_true @ perturbation, torch.zeros(2),
                        second.intrinsics, optimize_pose=True)
    anchor = MappingView(0, first.color, first.depth, sequence.gt_T_wc[0], torch.zeros(2), first.intrinsics,
                         optimize_pose=False)
    # 40 steps on the moved view (every other step): the roll about the optical axis settles last.
    _, _, refined = Mapper(mapping, config.render).optimize(gmap, optimizer, [moved, anchor], 80,
                                                            torch.Generator().manual_seed(0))
    assert [keyframe_id for keyframe_id, _ in refined] == [1]  # the anchor's pose is never touched
    error_before = se3_log(perturbation)
    error_after = se3_log(se3_inverse(T_wc_true) @ refined[0][1])
    assert error_after[:3].norm() < 0.5 * error_before[:3].norm(), (error_before, error_after)
    assert error_after[3:].norm() < 0.5 * error_before[3:].norm(), (error_before, error_after)


def test_tracking_against_the_frustum_subset_equals_tracking_against_the_whole_map(one_frame_map):
    # A far-away copy of the map (behind the camera and off to the side) cannot be drawn: tracking leaves it
    # out of the projection and must end where tracking the original map ends, with the same loss.
    seq, config, sequence, gaussians = one_frame_map
    frame, T_wc_true = sequence[0], sequence.gt_T_wc[0]
    offset = torch.tensor([0.0, 0.0, -50.0]) @ T_wc_true[:3, :3].T.float()  # 50 m behind the camera
    doubled = type(gaussians)(torch.cat([gaussians.means, gaussians.means + offset]),
                              *(torch.cat([t, t]) for t in (gaussians.quats, gaussians.scales, gaussians.opacities,
                                                            gaussians.colors)))
    T_wc_init = T_wc_true @ se3_exp(torch.tensor([0.01, -0.01, 0.005, 0.01, -0.01, 0.005], dtype=torch.float64))
    settings = tiny_config(seq, "tracking.iterations=30").tracking
    alone = Tracker(settings, config.render).track(gaussians, frame, T_wc_init, running_loss=None)
    culled = Tracker(settings, config.render).track(doubled, frame, T_wc_init, running_loss=None)
    assert culled.ok and culled.iterations == alone.iterations
    assert torch.allclose(culled.T_wc, alone.T_wc, atol=1e-6) and culled.loss == pytest.approx(alone.loss, rel=1e-5)


def test_frustum_subset_renders_like_the_whole_map_from_nearby_poses():
    generator = torch.Generator().manual_seed(0)
    n = 3000
    directions = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator), dim=-1)
    means = directions * (0.5 + 3.0 * torch.rand(n, 1, generator=generator))  # all around the camera
    gaussians = ActivatedGaussians(means, torch.nn.functional.normalize(torch.randn(n, 4, generator=generator), dim=-1),
                                   0.01 + 0.05 * torch.rand(n, 3, generator=generator),
                                   0.2 + 0.8 * torch.rand(n, generator=generator), torch.rand(n, 3, generator=generator))
    intrinsics = Intrinsics(fx=40.0, fy=40.0, cx=31.5, cy=23.5, width=64, height=48)
    config = RenderConfig()
    T_cw = torch.eye(4)
    assert config.frustum_margin == 0.25
    subset = frustum_subset(gaussians, T_cw, intrinsics, config)
    assert 0 < len(subset) < 0.5 * n  # the view sees well under half of a sphere around it
    nearby = se3_exp(torch.tensor([0.01, -0.01, 0.01, 0.02, -0.015, 0.01], dtype=torch.float64)).float()  # ~1.5 deg
    for pose in (T_cw, nearby @ T_cw):
        whole = render_view(gaussians, pose, intrinsics, config)
        part = render_view(subset, pose, intrinsics, config)
        assert whole.n_visible == part.n_visible
        for name in ("color", "depth", "alpha"):
            assert torch.allclose(getattr(whole, name), getattr(part, name), atol=1e-6), name


def test_mapping_a_view_without_the_gaussians_it_cannot_draw_changes_nothing(tiny_sequence):
    # The map of frame 0 plus a copy 50 m behind the camera: with the frustum margin, mapping renders the
    # view without the copy; with an unbounded margin it projects the copy too (which gets zero gradients).
    # The map after the same Adam steps must agree either way, copy included.
    config, sequence, gmap, _, _ = _map_of_first_frame(tiny_sequence, 5)
    T_wc = sequence.gt_T_wc[0]
    copy = gmap.detached()
    shift = torch.tensor([0.0, 0.0, -50.0], dtype=torch.float64) @ T_wc[:3, :3].T
    gmap.add(replace(copy, means=copy.means + shift.float()))
    frame = sequence[0]
    view = MappingView(0, frame.color, frame.depth, T_wc, torch.zeros(2), frame.intrinsics, optimize_pose=False)
    ends = []
    for margin in (0.25, 1e6):
        trial = GaussianMap(gmap.detached())
        optimizer = GaussianOptimizer.from_config(trial, config.mapping)
        mapper = Mapper(config.mapping, replace(config.render, frustum_margin=margin))
        first, last, _ = mapper.optimize(trial, optimizer, [view], 10, torch.Generator().manual_seed(0))
        ends.append((last, trial.detached()))
    assert ends[0][0] == pytest.approx(ends[1][0], rel=1e-5)
    for name in ("means", "log_scales", "opacity_logits", "colors_raw"):
        assert torch.allclose(getattr(ends[0][1], name), getattr(ends[1][1], name), atol=1e-5), name


def test_tracking_renders_the_map_with_its_own_filter_rates(tiny_sequence, tmp_path, monkeypatch):
    """With ``render.filter_3d`` the frozen map that tracking sees keeps its per-Gaussian sampling rates, so
    tracking renders the same filtered map that mapping fitted (before session 12 it fell back to the
    tracked camera's own rate)."""
    seen = []
    original = Tracker.track

    def recording_track(self, gaussians, *args, **kwargs):
        seen.append(gaussians.max_sampling_rate)
        return original(self, gaussians, *args, **kwargs)

    monkeypatch.setattr(Tracker, "track", recording_track)
    run_slam(tiny_config(tiny_sequence, "render.filter_3d=true", "dataset.max_frames=3"), tmp_path / "run",
             evaluate=False)
    assert len(seen) == 2  # frames 1 and 2 (frame 0 starts the map)
    for rates in seen:
        assert rates is not None and not rates.requires_grad and torch.all(rates > 0)


def test_detached_gaussians_keep_their_rates_and_leave_the_graph_and_rows_select_every_field():
    leaf = torch.ones(2, 3, requires_grad=True)
    gaussians = ActivatedGaussians(leaf * 1.0, torch.tensor([[1.0, 0, 0, 0]] * 2), leaf * 0.1, leaf[:, 0] * 0.5,
                                   leaf * 0.2, max_sampling_rate=torch.tensor([10.0, 0.0]))
    frozen = gaussians.detached()
    assert not any(t.requires_grad for t in (frozen.means, frozen.scales, frozen.opacities, frozen.colors))
    assert frozen.max_sampling_rate.tolist() == [10.0, 0.0]
    second = frozen.rows(torch.tensor([1]))
    assert len(second) == 1 and second.max_sampling_rate.tolist() == [0.0]
    assert torch.equal(second.opacities, frozen.opacities[1:]) and torch.equal(second.colors, frozen.colors[1:])
    assert ActivatedGaussians(*(t.detach() for t in (leaf, leaf, leaf, leaf[:, 0], leaf))).detached().max_sampling_rate is None


def test_the_motion_model_moves_with_a_refined_previous_pose_once():
    # Tracked: frame 1 is 2 cm right of frame 0. Mapping then refines frame 1 by 5 mm forward. The prediction for
    # frame 2 repeats the tracked motion from the refined pose; differencing the current poses would add the 5 mm
    # twice (once in the anchor, once in the motion).
    T0 = torch.eye(4, dtype=torch.float64)
    T1_tracked = se3_exp(torch.tensor([0.02, 0.0, 0.0, 0.0, 0.0, 0.01], dtype=torch.float64))
    refinement = se3_exp(torch.tensor([0.0, 0.0, 0.005, 0.0, 0.0, 0.0], dtype=torch.float64))
    T1 = T1_tracked @ refinement
    predicted = constant_velocity_prediction(T1, T1_tracked, T0)
    torch.testing.assert_close(predicted, T1 @ T1_tracked)
    torch.testing.assert_close(se3_inverse(T1) @ predicted, se3_inverse(T0) @ T1_tracked)  # the tracked motion
    # unrefined, it is the plain constant-velocity model; with one frame, the previous pose
    torch.testing.assert_close(constant_velocity_prediction(T1_tracked, T1_tracked, T0), T1_tracked @ T1_tracked)
    torch.testing.assert_close(constant_velocity_prediction(T1, T1_tracked, None), T1)


def test_tracked_poses_survive_a_checkpoint_and_old_checkpoints_fall_back_to_the_poses(tiny_sequence, tmp_path):
    # every frame a keyframe and a large pose rate: mapping visibly moves the keyframes away from their tracked poses
    config = tiny_config(tiny_sequence, "mapping.lr_poses=1e-3", "keyframes.covisibility_threshold=1.0")
    run_slam(config, tmp_path / "run", evaluate=False)
    checkpoint = load_latest_checkpoint(tmp_path / "run" / "checkpoints")
    state = SLAMState.from_checkpoint(checkpoint.tensors, checkpoint.metadata, config.mapping, torch.device("cpu"))
    moved = [float((f.T_wc - f.T_wc_tracked).abs().max()) for f in state.frames if f.keyframe_id > 0]
    assert moved and max(moved) > 1e-4, moved
    torch.testing.assert_close(torch.stack([f.T_wc_tracked for f in state.frames]),
                               checkpoint.tensors["frames.T_wc_tracked"], rtol=0, atol=0)
    old = {k: v for k, v in checkpoint.tensors.items() if k != "frames.T_wc_tracked"}
    state = SLAMState.from_checkpoint(old, checkpoint.metadata, config.mapping, torch.device("cpu"))
    for frame in state.frames:
        torch.testing.assert_close(frame.T_wc_tracked, frame.T_wc, rtol=0, atol=0)
