"""Local bundle adjustment (mipslam/local_ba.py): the analytic Jacobian against autodiff, recovery of a
perturbed window, the fixed gauge, the edge filter and the stage on a rendered sequence."""
import math

import numpy as np
import pytest
import torch

from mipslam.frontend import FrameFeatures
from mipslam.geometry import se3_exp
from mipslam.local_ba import (KeyframeObservations, LocalBAOptions, adjust_poses, reprojection_jacobians,
                              reprojection_residuals, smooth_depth_points)
from mipslam.types import Intrinsics

INTRINSICS = Intrinsics(fx=250.0, fy=250.0, cx=159.5, cy=119.5, width=320, height=240)
# the features alone decide (the prior on the current poses as good as absent)
WEAK_PRIOR = LocalBAOptions(enabled=True, iterations=8, prior_translation_m=1e3, prior_rotation_deg=1e5)


def _window(num_keyframes: int = 4, points: int = 200, seed: int = 0):
    """Keyframes stepping sideways before a cloud of points 1.5-3 m away; every ordered pair observes every
    point that projects into both images. -> (true poses [K, 4, 4], observations)"""
    g = torch.Generator().manual_seed(seed)
    world = torch.cat([(torch.rand(points, 2, generator=g, dtype=torch.float64) - 0.5) * 2.0,
                       1.5 + 1.5 * torch.rand(points, 1, generator=g, dtype=torch.float64)], 1)  # [P, 3]
    poses = torch.stack([se3_exp(torch.tensor([0.05 * k, 0.01 * k, 0.0, 0.0, 0.02 * k, 0.0], dtype=torch.float64))
                         for k in range(num_keyframes)])
    source, target, pts, pixels = [], [], [], []
    for a in range(num_keyframes):
        p_a = (world - poses[a, :3, 3]) @ poses[a, :3, :3]  # [P, 3] in keyframe a
        for b in range(num_keyframes):
            if a == b:
                continue
            p_b = (world - poses[b, :3, 3]) @ poses[b, :3, :3]
            uv = torch.stack([INTRINSICS.fx * p_b[:, 0] / p_b[:, 2] + INTRINSICS.cx,
                              INTRINSICS.fy * p_b[:, 1] / p_b[:, 2] + INTRINSICS.cy], 1)
            seen = (uv[:, 0] >= 0) & (uv[:, 0] < 320) & (uv[:, 1] >= 0) & (uv[:, 1] < 240)
            source.append(torch.full((int(seen.sum()),), a))
            target.append(torch.full((int(seen.sum()),), b))
            pts.append(p_a[seen])
            pixels.append(uv[seen])
    observations = KeyframeObservations(torch.cat(source), torch.cat(target), torch.cat(pts), torch.cat(pixels),
                                        num_keyframes * (num_keyframes - 1))
    return poses, observations


def test_jacobian_matches_autodiff():
    poses, observations = _window()
    poses = poses.clone()
    poses[2] = se3_exp(torch.tensor([0.01, -0.02, 0.005, 0.003, -0.002, 0.004], dtype=torch.float64)) @ poses[2]
    analytic = reprojection_jacobians(poses, observations, INTRINSICS)  # [N, 2, 6] w.r.t. the source

    def residual_of_source(xi):  # every pose moved by the same source perturbation, only where it is the source
        moved = se3_exp(xi)
        T_s = moved @ poses[observations.source]
        stacked = torch.cat([poses, T_s])
        shifted = KeyframeObservations(torch.arange(len(observations)) + poses.shape[0], observations.target,
                                       observations.points, observations.pixels, observations.pairs)
        return reprojection_residuals(stacked, shifted, INTRINSICS)

    numeric = torch.func.jacfwd(residual_of_source)(torch.zeros(6, dtype=torch.float64))  # [N, 2, 6]
    torch.testing.assert_close(analytic, numeric, rtol=1e-7, atol=1e-7)


def test_recovers_perturbed_window_and_keeps_the_gauge():
    truth, observations = _window()
    perturbed = truth.clone()
    for k, xi in ((1, [0.01, -0.008, 0.004, 0.004, -0.006, 0.003]), (2, [-0.012, 0.006, 0.01, -0.005, 0.004, 0.002]),
                  (3, [0.008, 0.01, -0.006, 0.003, 0.005, -0.006])):
        perturbed[k] = se3_exp(torch.tensor(xi, dtype=torch.float64)) @ truth[k]
    result = adjust_poses(perturbed, observations, INTRINSICS, WEAK_PRIOR)
    assert torch.equal(result.T_wc[0], perturbed[0])  # the oldest keyframe is the gauge
    assert result.error_before > 1.0 and result.error_after < 1e-6
    torch.testing.assert_close(result.T_wc, truth, rtol=0, atol=1e-8)
    assert result.matches == len(observations)


def test_the_prior_holds_the_current_poses():
    """With the default prior a keyframe moves only part of the way the features ask, and less the stronger
    the prior (a pose only the features dispute keeps what the render gave it)."""
    truth, observations = _window()
    perturbed = truth.clone()
    perturbed[3] = se3_exp(torch.tensor([0.01, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)) @ truth[3]
    moved = []
    for sigma_m in (1e3, 0.002, 0.0005):
        options = LocalBAOptions(enabled=True, iterations=8, prior_translation_m=sigma_m)
        result = adjust_poses(perturbed, observations, INTRINSICS, options)
        moved.append(float((result.T_wc[3, :3, 3] - perturbed[3, :3, 3]).norm()))
    assert moved[0] == pytest.approx(0.01, rel=1e-6)  # all the way to the truth
    assert 0.0 < moved[2] < moved[1] < moved[0]


def test_outliers_are_left_out_and_too_few_matches_change_nothing():
    truth, observations = _window()
    wrong = observations.pixels.clone()
    wrong[::10] += 40.0  # a tenth of the matches 40 px off: outside outlier_sigmas, never in the fit
    noisy = KeyframeObservations(observations.source, observations.target, observations.points, wrong,
                                 observations.pairs)
    perturbed = truth.clone()
    perturbed[3] = se3_exp(torch.tensor([0.004, 0.0, 0.0, 0.0, 0.002, 0.0], dtype=torch.float64)) @ truth[3]
    result = adjust_poses(perturbed, noisy, INTRINSICS, WEAK_PRIOR)
    torch.testing.assert_close(result.T_wc, truth, rtol=0, atol=1e-8)
    assert result.matches == len(observations) - len(range(0, len(observations), 10))
    few = adjust_poses(perturbed, noisy, INTRINSICS, LocalBAOptions(enabled=True, min_matches=10**6))
    assert torch.equal(few.T_wc, perturbed)


def test_edge_points_are_dropped():
    depth = torch.full((20, 20), 2.0)
    depth[:, 10:] = 1.0  # a step at column 10
    depth[0, 0] = 0.0  # a hole
    features = FrameFeatures(np.array([[5.0, 5.0], [10.0, 5.0], [15.0, 5.0], [1.0, 1.0]], np.float32),
                             np.zeros((4, 32), np.uint8),
                             np.array([[0, 0, 2.0], [0, 0, 1.0], [0, 0, 1.0], [0, 0, 2.0]], dtype=np.float64))
    kept = smooth_depth_points(features, depth, 0.03)
    assert np.isfinite(kept.points_c[0]).all() and np.isfinite(kept.points_c[2]).all()
    assert np.isnan(kept.points_c[1]).all()  # on the step
    assert np.isnan(kept.points_c[3]).all()  # beside the hole
    assert smooth_depth_points(features, depth, 0.0) is features


def test_the_stage_in_a_run(tmp_path, monkeypatch):
    """A run with ``local_ba.enabled``: each keyframe after the first adjusts the window from real matches, the
    state stays finite and on the lap, and the stage's time is recorded."""
    import json

    import data_synth
    from mipslam.config import load_config
    from mipslam.datasets import make_sequence
    from mipslam.io.tum import read_tum_trajectory
    from mipslam.local_ba import LocalBundleAdjuster
    from mipslam.pipeline import run_slam

    seq = tmp_path / "seq"
    data_synth.generate(seq, layout="replica", trajectory="loop", width=160, height=120, frames=60, seed=0,
                        supersample=1)
    results = []
    adjust = LocalBundleAdjuster.adjust_window

    def recorded(self, state, frames):
        result = adjust(self, state, frames)
        results.append(result)
        return result

    monkeypatch.setattr(LocalBundleAdjuster, "adjust_window", recorded)
    config = load_config("synthetic", overrides=[
        f"dataset.path={seq}", "dataset.max_frames=8", "local_ba.enabled=true", "keyframes.covisibility_threshold=0.99",
        "mapping.first_frame_iterations=30", "mapping.iterations=4", "tracking.iterations=4", "run.threads=1",
        "loop.enabled=false", "run.evaluate_at_end=false"])
    summary = run_slam(config, tmp_path / "run", evaluate=False)
    adjusted = [r for r in results if r is not None]
    assert summary.keyframes >= 3 and len(adjusted) == summary.keyframes - 1  # every keyframe after the first
    assert all(r.matches >= 30 and r.pairs >= 2 and r.error_after <= r.error_before for r in adjusted)
    poses = read_tum_trajectory(tmp_path / "run" / "traj_est.txt").T_wc
    gt = make_sequence(config.dataset).gt_T_wc.numpy()
    assert np.isfinite(poses).all() and np.abs(poses[:, :3, 3] - gt[:, :3, 3]).max() < 0.05  # metres
    timings = json.loads((tmp_path / "run" / "timings.json").read_text())
    assert timings["stages"]["local_ba"]["total_s"] > 0
