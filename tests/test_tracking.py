"""Tracking (mipslam/tracking.py): pose recovery, the optimisers, the frustum subset, the motion model."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from types import SimpleNamespace

import pytest
import torch

from mipslam.mapping import MappingOptions
from mipslam.tracking import TrackingOptions
from mipslam.config import RenderConfig, load_config
from mipslam.gaussians import ActivatedGaussians
from mipslam.geometry import se3_exp, se3_inverse, se3_log
from mipslam.geometry.direct import DirectResult
from mipslam.pipeline import run_slam
from mipslam.render import RenderOptions, cpu as cpu_backend
from mipslam.rendering import FRUSTUM_MARGIN, frustum_subset, render_view
import mipslam.rendering as rendering_module
import mipslam.tracking as tracking
from mipslam.state import FrameRecord, SLAMState
from mipslam.tracking import Tracker, TrackingResult, constant_velocity_prediction, relocalise
from mipslam.types import Frame, Intrinsics
from mipslam.datasets import make_sequence
from tiny_runs import map_of_first_frame, tiny_config, tiny_tracking


# rprop is tracking's optimiser (TrackingOptions); adam, which no shipped config uses, as the base config had it.
_OPTIMIZERS = {"adam": ["tracking.optimizer=adam", "tracking.lr_translation=2e-3", "tracking.lr_rotation=4e-3",
                        "tracking.convergence_threshold=1e-5"], "rprop": []}


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
    settings = tiny_tracking(seq, "tracking.iterations=80", f"tracking.use_exposure={str(exposure).lower()}",
                             *_OPTIMIZERS[optimizer])
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
        settings = tiny_tracking(seq, "tracking.iterations=80", *extra)
        result = Tracker(settings, config.render).track(gaussians, sequence[0], T_wc_true, running_loss=None)
        assert result.ok
        ends[name] = (result.iterations, se3_log(se3_inverse(T_wc_true) @ result.T_wc))
    assert ends["rprop"][0] < 40 and ends["adam"][0] == 80, ends
    # Adam still steps by about its rate (2 mm, 4 mrad) at the end, so its best iterate places the optimum
    # only to about a millimetre: float round-off in the map moves it by that much.
    assert (ends["rprop"][1] - ends["adam"][1]).norm() < 2e-3, ends


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
    settings = tiny_tracking(seq, "tracking.iterations=30")
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
    assert FRUSTUM_MARGIN == 0.25
    subset = frustum_subset(gaussians, T_cw, intrinsics, config)
    assert 0 < len(subset) < 0.5 * n  # the view sees well under half of a sphere around it
    nearby = se3_exp(torch.tensor([0.01, -0.01, 0.01, 0.02, -0.015, 0.01], dtype=torch.float64)).float()  # ~1.5 deg
    for pose in (T_cw, nearby @ T_cw):
        whole = render_view(gaussians, pose, intrinsics, config)
        part = render_view(subset, pose, intrinsics, config)
        assert whole.n_visible == part.n_visible
        for name in ("color", "depth", "alpha"):
            assert torch.allclose(getattr(whole, name), getattr(part, name), atol=1e-6), name


def test_compiled_frustum_rows_are_the_torch_references():
    """The compiled frustum test (float64) keeps the rows the torch reference keeps (float32), for poses and
    cameras of every kind, except a Gaussian within 1e-3 px or 1e-6 m of a limit; render.backend torch takes
    the reference."""
    if not cpu_backend.is_available():
        pytest.skip(f"the compiled CPU library is not available: {cpu_backend.unavailable_reason()}")
    generator = torch.Generator().manual_seed(1)
    n = 20000
    means = 3.0 * torch.randn(n, 3, generator=generator)
    means[:50, 2] = 0.5 * RenderOptions.near_plane  # on the near limit
    scales = 0.1 * torch.rand(n, 3, generator=generator) ** 3
    cameras = (Intrinsics(fx=40.0, fy=40.0, cx=31.5, cy=23.5, width=64, height=48),
               Intrinsics(fx=517.3, fy=516.5, cx=318.6, cy=255.3, width=640, height=480))
    poses = [torch.eye(4)] + [se3_exp(0.8 * torch.randn(6, generator=generator, dtype=torch.float64)).float()
                              for _ in range(6)]
    for intrinsics in cameras:
        for T_cw in poses:
            compiled = rendering_module.frustum_indices(means, scales, T_cw, intrinsics, RenderConfig())
            reference = rendering_module.frustum_indices_reference(means, scales, T_cw, intrinsics)
            assert torch.all(compiled[1:] > compiled[:-1])
            assert T_cw is not poses[0] or len(reference) > 1000  # the camera at the origin sees many
            differing = torch.tensor(sorted(set(compiled.tolist()) ^ set(reference.tolist())), dtype=torch.int64)
            if len(differing):  # only where the float64 test sits on a limit
                points = means[differing].double() @ T_cw[:3, :3].double().T + T_cw[:3, 3].double()
                z = points[:, 2]
                near = 0.5 * RenderOptions.near_plane
                reach = (RenderOptions.k_sigma * scales[differing].double().amax(-1) * max(intrinsics.fx, intrinsics.fy)
                         / z.clamp_min(near) + FRUSTUM_MARGIN * max(intrinsics.width, intrinsics.height) + 1.0)
                u = intrinsics.fx * points[:, 0] / z.clamp_min(near) + intrinsics.cx
                v = intrinsics.fy * points[:, 1] / z.clamp_min(near) + intrinsics.cy
                slack = torch.stack([u + reach + 0.5, intrinsics.width - 0.5 - u + reach,
                                     v + reach + 0.5, intrinsics.height - 0.5 - v + reach], -1).abs().amin(-1)
                assert bool(((slack < 1e-3) | ((z - near).abs() < 1e-6)).all()), differing
            assert len(differing) <= 1e-3 * n
    torch_only = rendering_module.frustum_indices(means, scales, poses[1], cameras[1], RenderConfig(backend="torch"))
    assert torch.equal(torch_only, rendering_module.frustum_indices_reference(means, scales, poses[1], cameras[1]))


def test_tracking_renders_the_map_with_its_own_filter_rates(tiny_sequence, tmp_path, monkeypatch):
    """With ``render.filter_3d`` the frozen map that tracking sees keeps its per-Gaussian sampling rates, so
    tracking renders the same filtered map that mapping fitted (it once fell back to the
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


def test_the_coarse_levels_get_the_configured_share_of_the_iterations(one_frame_map):
    _, config, sequence, _ = one_frame_map
    for share, expected in ((0.5, [20, 20]), (0.25, [10, 30]), (0.0, [40])):
        settings = replace(TrackingOptions.from_config(config.tracking), iterations=40, coarse_to_fine=(0.5,), coarse_share=share)
        levels = Tracker(settings, config.render)._levels(sequence[0])
        assert [level.iterations for level in levels] == expected, share
        assert levels[-1].intrinsics == sequence[0].intrinsics  # full resolution last


def test_coarse_levels_render_in_the_coarse_mode_and_the_finest_in_the_tracking_mode(one_frame_map, monkeypatch):
    _, config, sequence, gaussians = one_frame_map
    settings = replace(TrackingOptions.from_config(config.tracking), iterations=6, coarse_to_fine=(0.5,), render_mode="eaa",
                       coarse_render_mode="mip", convergence_threshold=0.0)
    tracker = Tracker(settings, config.render)
    assert [level.render_mode for level in tracker._levels(sequence[0])] == ["mip", "eaa"]
    rendered = []

    def recording(real_render):
        def render(gaussians, T_cw, intrinsics, render_config, **kwargs):
            out = real_render(gaussians, T_cw, intrinsics, render_config, **kwargs)
            if out is not None:  # render_view_pose_only declines where only autograd renders
                rendered.append((intrinsics.width, kwargs["mode"]))
            return out
        return render

    # the gradient steps render through render_view_pose_only on the compiled backend, else render_view
    monkeypatch.setattr(tracking, "render_view", recording(tracking.render_view))
    monkeypatch.setattr(tracking, "render_view_pose_only", recording(tracking.render_view_pose_only))
    tracker.track(gaussians, sequence[0], sequence.gt_T_wc[0], running_loss=None)
    width = sequence[0].intrinsics.width
    assert rendered == [(width // 2, "mip")] * 3 + [(width, "eaa")] * 3
    # unset, every level renders in the tracking mode
    plain = Tracker(replace(settings, coarse_render_mode=None), config.render)
    assert [level.render_mode for level in plain._levels(sequence[0])] == ["eaa", "eaa"]


def test_the_first_steps_of_the_finest_level_render_in_the_coarse_mode(one_frame_map, monkeypatch):
    _, config, sequence, gaussians = one_frame_map
    settings = replace(TrackingOptions.from_config(config.tracking), iterations=6, coarse_to_fine=(), render_mode="eaa", coarse_render_mode="mip",
                       coarse_mode_iterations=2, direct_iterations=0, convergence_threshold=0.0)
    tracker = Tracker(settings, config.render)
    levels = tracker._levels(sequence[0])
    assert [(level.render_mode, level.iterations) for level in levels] == [("mip", 2), ("eaa", 4)]
    assert levels[0].color is levels[1].color and levels[0].intrinsics == levels[1].intrinsics  # the same images
    judged = []
    real_coverage = Tracker._coverage

    def coverage(self, depth, alpha, level):  # called for each new best pose: the coarse-mode steps never judge
        judged.append(level.render_mode)
        return real_coverage(self, depth, alpha, level)

    monkeypatch.setattr(Tracker, "_coverage", coverage)
    result = tracker.track(gaussians, sequence[0], sequence.gt_T_wc[0], running_loss=None)
    assert result.ok and result.iterations == 6 and judged and set(judged) == {"eaa"}
    # never all of the finest level's steps; nothing split without a different coarse mode
    for kwargs, expected in [(dict(coarse_mode_iterations=9), [("mip", 5), ("eaa", 1)]),
                             (dict(coarse_render_mode=None), [("eaa", 6)]),
                             (dict(coarse_render_mode="eaa"), [("eaa", 6)]),
                             (dict(coarse_mode_iterations=0), [("eaa", 6)])]:
        split = Tracker(replace(settings, **kwargs), config.render)._levels(sequence[0])
        assert [(level.render_mode, level.iterations) for level in split] == expected, kwargs


def test_relocalisation_runs_above_the_loss_ratio_and_accepts_the_configured_jump(one_frame_map, monkeypatch):
    _, config, sequence, gaussians = one_frame_map
    frame = sequence[0]
    state = SLAMState.initial(MappingOptions.from_config(config.mapping), 0, torch.device("cpu"))
    state.frames.append(FrameRecord(0, 0.0, sequence.gt_T_wc[0], torch.zeros(2), "ok", 0.01, 1, 0, -1,
                                    sequence.gt_T_wc[0]))
    state.running_loss = 0.01
    asked = []

    def alignment(*args):
        asked.append(args[-1])  # the registration options
        return SimpleNamespace(accepted=False)

    monkeypatch.setattr(tracking, "register_rgbd_odometry", alignment)
    settings = replace(TrackingOptions.from_config(config.tracking), relocalise_loss_ratio=2.0, relocalise_max_m=0.3, relocalise_max_deg=20.0)
    tracker = Tracker(settings, config.render)
    usual = TrackingResult(sequence.gt_T_wc[0], torch.zeros(2), 0.015, 5, 1.0, True, "ok")
    assert relocalise(tracker, state, frame, {0: frame}, gaussians, usual) is usual and not asked
    high = replace(usual, loss=0.05)  # 5x the running level, above the ratio 2
    assert relocalise(tracker, state, frame, {0: frame}, gaussians, high) is high  # the alignment was refused
    assert [(o.max_correction_m, o.max_correction_deg) for o in asked] == [(0.3, 20.0)]


def test_map_coverage_is_the_share_of_valid_depth_the_map_renders(one_frame_map):
    # The map built from frame 0 covers frame 0; with the Gaussians of the image's left half removed it
    # covers only about the right half, which is what keyframes.min_map_coverage reads.
    seq, config, sequence, gaussians = one_frame_map
    frame, T_wc_true = sequence[0], sequence.gt_T_wc[0]
    settings = tiny_tracking(seq, "tracking.iterations=4")
    whole = Tracker(settings, config.render).track(gaussians, frame, T_wc_true, running_loss=None)
    assert whole.ok and whole.map_coverage > 0.95
    u = (gaussians.means - T_wc_true[:3, 3].float()) @ T_wc_true[:3, :3].float()  # camera frame, OpenCV axes
    right = u[:, 0] / u[:, 2] > 0.0  # right of the optical axis (the principal point is near the centre)
    half = type(gaussians)(*(t[right] for t in (gaussians.means, gaussians.quats, gaussians.scales,
                                                gaussians.opacities, gaussians.colors)))
    result = Tracker(settings, config.render).track(half, frame, T_wc_true, running_loss=None)
    assert 0.3 < result.map_coverage < 0.7, result.map_coverage


def test_dense_start_joins_the_candidates_where_the_features_give_none(one_frame_map, monkeypatch):
    # No front-end, and the motion model predicts a pose 8 cm / 6 degrees off: beyond what a few refinement
    # steps recover. With tracking.dense_start the RGB-D alignment's pose (here the truth) joins the candidates
    # and the render loss picks it.
    seq, config, sequence, _ = one_frame_map
    _, _, gmap, _, _ = map_of_first_frame(seq, 60)
    frame, T_wc_true = sequence[0], sequence.gt_T_wc[0]
    T_wc_off = T_wc_true @ se3_exp(torch.tensor([0.06, -0.04, 0.03, 0.06, -0.07, 0.05], dtype=torch.float64))
    asked = []

    def alignment(color_i, depth_i, color_j, depth_j, intrinsics, T_ij_init, options):
        asked.append(T_ij_init)
        return SimpleNamespace(accepted=True, T_ij=se3_inverse(T_wc_off) @ T_wc_true)

    monkeypatch.setattr(tracking, "register_rgbd_odometry", alignment)
    errors = {}
    for dense in (False, True):
        state = SLAMState.initial(MappingOptions.from_config(config.mapping), 0, torch.device("cpu"))
        state.gaussian_map = gmap
        state.frames.append(FrameRecord(1, 0.0, T_wc_off, torch.zeros(2), "ok", 0.01, 4, -1, 0, T_wc_off))
        # the pose check off: its wider search would align to the previous frame again (test_verify_pose_*)
        settings = replace(TrackingOptions.from_config(config.tracking), iterations=4, dense_start=dense,
                           motion_check_m=math.inf, motion_check_deg=math.inf)
        result = tracking.track_frame(Tracker(settings, config.render), state, frame, {1: frame}, T_wc_true)
        errors[dense] = float(se3_log(se3_inverse(T_wc_true) @ result.T_wc)[:3].norm())
    assert len(asked) == 1  # only with dense_start, from the motion model's prediction (the reference's pose)
    torch.testing.assert_close(asked[0], torch.eye(4, dtype=torch.float64))
    assert errors[True] < 0.01 < 0.05 < errors[False], errors


def test_dense_alignment_to_the_previous_frame_recovers_a_large_motion(tmp_path):
    # 8 cm and 5.8 degrees between two frames of a 160x120 data_synth loop: Open3D's RGB-D odometry, started
    # at the reference's pose, lands within about a centimetre of the truth.
    import data_synth

    data_synth.generate(tmp_path / "seq", layout="replica", trajectory="loop", width=160, height=120, frames=60,
                        seed=0, supersample=1)
    config = tiny_config(tmp_path / "seq")
    sequence = make_sequence(config.dataset)
    T_wc_reference, T_wc_true = sequence.gt_T_wc[0], sequence.gt_T_wc[4]
    aligned = tracking.align_to_frame(TrackingOptions.from_config(config.tracking), sequence[0], T_wc_reference, sequence[4], T_wc_reference)
    assert aligned is not None
    before = se3_log(se3_inverse(T_wc_true) @ T_wc_reference)
    after = se3_log(se3_inverse(T_wc_true) @ aligned)
    assert before[:3].norm() > 0.07 and after[:3].norm() < 0.02, (before, after)
    assert math.degrees(float(after[3:].norm())) < 1.0, after


def test_direct_alignment_starts_the_gradient_steps_close_to_the_pose(one_frame_map_128):
    # tracking.direct_*: Gauss-Newton against the map's render takes a 2 cm / 1 degree error out before four
    # gradient steps, which alone leave most of it; its renders' losses join the best-pose bookkeeping.
    seq, config, sequence, gaussians = one_frame_map_128
    frame = sequence[0]
    T_wc_true = sequence.gt_T_wc[0]
    perturbation = se3_exp(torch.tensor([0.015, -0.01, 0.01, 0.01, -0.015, 0.005], dtype=torch.float64))
    T_wc_init = T_wc_true @ perturbation
    settings = tiny_tracking(seq, "tracking.iterations=4", *_OPTIMIZERS["rprop"])
    errors = {}
    for name, direct_iterations in (("gradient steps", 0), ("direct + gradient steps", 8)):
        tracker = Tracker(replace(settings, direct_iterations=direct_iterations, direct_renders=2), config.render)
        result = tracker.track(gaussians, frame, T_wc_init, running_loss=None)
        assert result.ok
        errors[name] = se3_log(se3_inverse(T_wc_true) @ result.T_wc)
        if direct_iterations:
            assert result.iterations > settings.iterations  # Gauss-Newton steps are counted
    before = se3_log(se3_inverse(T_wc_true) @ T_wc_init)
    direct, plain = errors["direct + gradient steps"], errors["gradient steps"]
    assert direct[:3].norm() < 0.3 * before[:3].norm() and direct[3:].norm() < 0.3 * before[3:].norm(), errors
    assert direct[:3].norm() < 0.5 * plain[:3].norm(), errors


def test_a_direct_alignment_that_renders_worse_ends_at_the_best_render(one_frame_map, monkeypatch):
    seq, config, sequence, gaussians = one_frame_map
    frame = sequence[0]
    T_wc_true = sequence.gt_T_wc[0]
    settings = tiny_tracking(seq, "tracking.iterations=1", *_OPTIMIZERS["rprop"])
    tracker = Tracker(replace(settings, direct_iterations=8, direct_renders=3), config.render)
    away = se3_exp(torch.tensor([0.05, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64))

    def misaligned(references, targets, T_init, **kwargs):  # an alignment that walks 5 cm off every time
        return DirectResult(T=away, iterations=3, points=100, ok=True)

    monkeypatch.setattr(tracking, "direct_aligner", lambda backend, device: misaligned)
    T_cw_true = se3_inverse(T_wc_true)
    T_cw, seen, steps = tracker._direct_alignment(gaussians, frame, T_cw_true)
    # the second render (5 cm off) explains the frame worse than the first: the alignment stops at the first
    assert torch.equal(T_cw, T_cw_true) and torch.equal(seen.T_cw, T_cw_true) and steps == 3
    result = tracker.track(gaussians, frame, T_wc_true, running_loss=None)
    assert se3_log(se3_inverse(T_wc_true) @ result.T_wc)[:3].norm() < 0.01


@pytest.mark.parametrize("power", [0.0, 2.0])
def test_the_alignment_reads_depth_residuals_in_the_configured_units_of_sensor_noise(one_frame_map, monkeypatch,
                                                                                      power):
    seq, config, sequence, gaussians = one_frame_map
    settings = tiny_tracking(seq, "tracking.iterations=1", *_OPTIMIZERS["rprop"])
    tracker = Tracker(replace(settings, direct_iterations=4, direct_depth_noise_power=power), config.render)
    seen_options = []

    def recording(references, targets, T_init, **kwargs):
        seen_options.append(kwargs)
        return DirectResult(T=T_init, iterations=1, points=100, ok=True)

    monkeypatch.setattr(tracking, "direct_aligner", lambda backend, device: recording)
    tracker._direct_alignment(gaussians, sequence[0], se3_inverse(sequence.gt_T_wc[0]))
    assert seen_options and all(options["depth_noise_power"] == power for options in seen_options)


def test_the_direct_alignment_runs_compiled_where_the_render_backend_does():
    from mipslam.geometry.direct import align_direct as reference
    from mipslam.render import cpu as cpu_backend
    from mipslam.render import direct_aligner

    cpu = torch.device("cpu")
    assert direct_aligner("torch", cpu) is reference
    assert direct_aligner("auto", torch.device("meta")) is reference  # not a CPU tensor: torch
    expected = cpu_backend.align_direct if cpu_backend.is_available() else reference
    assert direct_aligner("auto", cpu) is expected
    assert direct_aligner("cpu", cpu) is expected


@dataclass
class _JudgedStarts:
    """A tracker that judged two starts of frame 0 (2 cm / 0.6 deg and 0.5 cm off), with render_view counted."""

    settings: TrackingOptions
    render_config: RenderConfig
    gaussians: ActivatedGaussians
    sequence: object  # the run's frames (frame 0 is ``frame``)
    frame: Frame
    candidates: list[torch.Tensor]  # [4, 4] float64 camera-to-world each
    tracker: Tracker
    chosen: int
    renders: list  # one entry per render_view call


def _judge_two_starts(one_frame_map_128, monkeypatch) -> _JudgedStarts:
    seq, config, sequence, gaussians = one_frame_map_128
    frame = sequence[0]
    T_wc_true = sequence.gt_T_wc[0]
    candidates = [T_wc_true @ se3_exp(torch.tensor([0.02, 0.0, 0.0, 0.0, 0.01, 0.0], dtype=torch.float64)),
                  T_wc_true @ se3_exp(torch.tensor([0.005, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64))]
    settings = replace(tiny_tracking(seq, "tracking.iterations=4", *_OPTIMIZERS["rprop"]),
                       direct_iterations=8, start_margin=0.0)
    renders = []
    real_render = tracking.render_view
    monkeypatch.setattr(tracking, "render_view", lambda *a, **k: renders.append(1) or real_render(*a, **k))
    judged = Tracker(settings, config.render)
    chosen = judged.best_start(gaussians, frame, candidates)
    return _JudgedStarts(settings, config.render, gaussians, sequence, frame, candidates, judged, chosen, renders)


def test_the_direct_alignment_reuses_the_start_judges_render_of_the_chosen_start(one_frame_map_128, monkeypatch):
    j = _judge_two_starts(one_frame_map_128, monkeypatch)
    assert j.chosen == 1 and len(j.renders) == 2
    start = j.candidates[j.chosen]
    reused = j.tracker.track(j.gaussians, j.frame, start, running_loss=None)
    after_judge = len(j.renders)
    fresh = Tracker(j.settings, j.render_config).track(j.gaussians, j.frame, start, running_loss=None)
    # the same pose, bit for bit, with one render fewer
    assert torch.equal(reused.T_wc, fresh.T_wc) and reused.loss == fresh.loss
    assert after_judge - 2 == len(j.renders) - after_judge - 1


def test_a_retimed_frame_keeps_the_start_judges_renders_and_is_tracked_on_its_own_images(one_frame_map_128,
                                                                                          monkeypatch):
    j = _judge_two_starts(one_frame_map_128, monkeypatch)
    moved = replace(j.frame, color=torch.roll(j.frame.color, 1, dims=1))  # the frame's images, moved
    start = j.candidates[j.chosen]
    j.tracker.retimed(j.frame, moved)
    reused = j.tracker.track(j.gaussians, moved, start, running_loss=None)
    after_judge = len(j.renders)
    fresh = Tracker(j.settings, j.render_config).track(j.gaussians, moved, start, running_loss=None)
    # the moved images' pose, bit for bit, with the judge's render of the start reused
    assert torch.equal(reused.T_wc, fresh.T_wc) and reused.loss == fresh.loss
    assert after_judge - 2 == len(j.renders) - after_judge - 1
    original = Tracker(j.settings, j.render_config).track(j.gaussians, j.frame, start, running_loss=None)
    assert original.loss != reused.loss
    j.tracker.best_start(j.gaussians, j.frame, j.candidates)
    with pytest.raises(ValueError, match="not a re-timed copy"):
        j.tracker.retimed(j.frame, j.sequence[1])  # another frame's images


@pytest.mark.parametrize("exposure,optimizer", [(True, "rprop"), (False, "adam")])
def test_compiled_steps_track_as_autograd(one_frame_map, monkeypatch, exposure, optimizer):
    """The compiled backend's gradient steps carry the chain rule by hand (Tracker._step_render); autograd
    through render_view and rgbd_l1_loss is the reference: the same pose, exposure and steps, bit for bit (the
    gradient images are autograd's), the loss to rounding (the library sums in float64)."""
    if rendering_module.render_view_pose_only(one_frame_map[3], torch.eye(4), one_frame_map[2][0].intrinsics,
                                              one_frame_map[1].render) is None:
        pytest.skip("the compiled CPU backend is not built here")
    seq, config, sequence, gaussians = one_frame_map
    frame = sequence[0]
    perturbation = se3_exp(torch.tensor([0.01, -0.008, 0.006, 0.008, -0.01, 0.004], dtype=torch.float64))
    T_wc_init = sequence.gt_T_wc[0] @ perturbation
    settings = tiny_tracking(seq, "tracking.iterations=12", f"tracking.use_exposure={str(exposure).lower()}",
                             *_OPTIMIZERS[optimizer])
    compiled = Tracker(settings, config.render).track(gaussians, frame, T_wc_init, running_loss=None)
    monkeypatch.setattr(tracking, "render_view_pose_only", lambda *args, **kwargs: None)
    reference = Tracker(settings, config.render).track(gaussians, frame, T_wc_init, running_loss=None)
    assert compiled.ok and reference.ok and compiled.iterations == reference.iterations
    assert torch.equal(compiled.T_wc, reference.T_wc) and compiled.loss == pytest.approx(reference.loss, rel=1e-6)
    assert torch.equal(compiled.exposure, reference.exposure)
    assert not torch.equal(compiled.T_wc, T_wc_init)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_pose_rprop_is_bit_equal_to_torch_rprop(dtype):
    # gradients that keep, flip and lose their sign, zeros, and steps that reach the cap
    generator = torch.Generator().manual_seed(7)
    start = [torch.randn(3, generator=generator, dtype=dtype) for _ in range(3)]
    ours = [p.clone().requires_grad_(True) for p in start]
    theirs = [p.clone().requires_grad_(True) for p in start]
    lrs = (5e-4, 1e-3, 2e-3)
    optimizer = tracking.PoseRprop([{"params": [p], "lr": lr} for p, lr in zip(ours, lrs)], max_step_ratio=4.0)
    reference = torch.optim.Rprop([{"params": [p], "lr": lr, "step_sizes": (0.0, lr * 4.0)} for p, lr in zip(theirs, lrs)],
                                  etas=(0.5, 1.2))
    for step in range(60):
        grads = [torch.randn(3, generator=generator, dtype=dtype) for _ in range(3)]
        if step % 5 == 0:
            grads[0] = grads[0].abs()  # runs of one sign: the step grows to the cap
        grads[1][torch.rand(3, generator=generator) < 0.2] = 0.0
        for p, q, g in zip(ours, theirs, grads):
            p.grad, q.grad = g.clone(), g.clone()
        optimizer.step()
        reference.step()
        for p, q in zip(ours, theirs):
            assert torch.equal(p.detach(), q.detach())
            assert torch.equal(torch.from_numpy(optimizer.step_sizes[p]), reference.state[q]["step_size"])
        optimizer.zero_grad(set_to_none=True)
        assert all(p.grad is None for p in ours)
    assert tracking._converged(optimizer, ours[:2], 1.0, 1e9) and not tracking._converged(optimizer, ours[:2], 0.0, 0.0)


@pytest.fixture(scope="module")
def spin_start(tmp_path_factory):
    """A 160x120 data_synth spin (9 degrees a frame from frame 0 over repeated texture) and its frame 0's map."""
    import data_synth

    root = tmp_path_factory.mktemp("spin") / "seq"
    data_synth.generate(root, layout="replica", trajectory="spin", width=160, height=120, frames=20, seed=2,
                        supersample=1)
    config, sequence, gmap, _, _ = map_of_first_frame(root, 60)
    return config, sequence, gmap


SYNTHETIC_DISAGREEMENT = 0.001  # the running depth disagreement of a data_synth room (exact depth)


def _track_spin_frame(spin_start, **constants):
    config, sequence, gmap = spin_start
    state = SLAMState.initial(MappingOptions.from_config(config.mapping), 0, torch.device("cpu"))
    state.gaussian_map = gmap
    state.running_disagreement = SYNTHETIC_DISAGREEMENT
    T_wc_0 = sequence.gt_T_wc[0].to(torch.float64)
    state.frames.append(FrameRecord(0, 0.0, T_wc_0, torch.zeros(2), "initial", 0.0, 0, 0, -1, T_wc_0))
    state.keyframe_frames.append(0)
    settings = replace(TrackingOptions.from_config(config.tracking), dense_start=False, **constants)
    frames = {0: sequence[0]}
    result = tracking.track_frame(Tracker(settings, config.render), state, sequence[1], frames, T_wc_0)
    error = se3_inverse(sequence.gt_T_wc[1].to(torch.float64)) @ result.T_wc
    return result, float(error[:3, 3].norm())


def test_verify_pose_searches_again_where_the_maps_depth_disputes_the_pose(spin_start):
    # Frame 1 is 9 degrees from frame 0; the motion model (no motion yet) starts at frame 0's pose. With one
    # pyramid level of direct alignment and 4 steps tracking stops where part of the map's depth disagrees with
    # the frame; the pose check searches again (two more levels) and lands where the depth agrees, nearer the truth.
    weak = dict(direct_levels=1, iterations=4)
    off = dict(disagreement_floor=math.inf, motion_check_m=math.inf, motion_check_deg=math.inf)
    limit = tracking.disagreement_limit(TrackingOptions(), SYNTHETIC_DISAGREEMENT)
    unchecked, unchecked_error = _track_spin_frame(spin_start, **weak, **off)
    checked, checked_error = _track_spin_frame(spin_start, **weak)
    assert unchecked.ok and unchecked.depth_disagreement > limit  # silently ok without the check
    assert checked.ok and checked.depth_disagreement <= limit
    assert checked_error < 0.7 * unchecked_error, (checked_error, unchecked_error)


def test_verify_pose_flags_a_pose_it_cannot_resolve(spin_start):
    # A limit no pose can meet (every covered pixel disagrees at a tolerance of 1e-6 of the depth): the frame
    # keeps its best pose and is flagged, never silently ok.
    result, _ = _track_spin_frame(spin_start, disagreement_tolerance=1e-6, disagreement_floor=0.05,
                                  disagreement_ratio=0.0)
    assert not result.ok and result.status == "depth_disagreement"
    assert torch.isfinite(result.T_wc).all()


def test_no_disagreement_check_before_the_camera_has_a_level():
    # What share of the pixels disagrees on a good pose differs from camera to camera (5 % on fr3_teddy, 0.1 % in
    # a synthetic room): without a running level no frame is disputed; after, the floor and the ratio apply.
    options = TrackingOptions()
    assert tracking.disagreement_limit(options, None) == math.inf
    assert tracking.disagreement_limit(options, 0.001) == options.disagreement_floor
    assert tracking.disagreement_limit(options, 0.05) == pytest.approx(options.disagreement_ratio * 0.05)
