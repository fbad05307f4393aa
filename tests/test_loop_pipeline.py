"""Loop closure and SA-PGO inside the SLAM loop, on tiny data_synth loop sequences.

Drift is injected with a biased odometer (fault_injection.BiasedOdometer (tests/fault_injection.py)): every frame's pose is
the previous estimate times the ground-truth motion times Exp(bias), so the run drifts by about
0.6 deg and 4 mm per frame; mapping, keyframes and loop closure run as usual on those poses. The
sequence is a 48-frame `loop` trajectory (a small circle that returns to its start) at 40x30.
"""
from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

import data_synth
from mipslam.checkpoint import load_latest_checkpoint, select_prefix
from mipslam.config import load_config
from mipslam.datasets import make_sequence
from mipslam.evaluation.image_metrics import psnr
from mipslam.evaluation.trajectory import evaluate_trajectory
from mipslam.gaussians import GaussianMap, GaussianParameters
from mipslam.geometry import se3_exp, se3_inverse, se3_log
from mipslam.io.ply import read_map_ply
from mipslam.io.tum import read_tum_trajectory
from mipslam.loop.closer import LoopOptions
from fault_injection import BiasedOdometer, WrongLoop
from tiny_runs import split_settings
from mipslam.observer import Observer
from mipslam.pipeline import PipelineHooks, run_slam
from mipslam.rendering import render_view
from mipslam.state import FrameRecord, LoopState, SLAMState

F64 = torch.float64

# One torch thread: on the shared 2-core machine two threads stall at every operator's barrier.
TINY = [
    "mapping.first_frame_iterations=30", "mapping.iterations=8", "mapping.densify_pixel_stride=2",
    "keyframes.window_size=3", "keyframes.random_past=1", "run.threads=1", "run.checkpoint_every=0",
]
# The odometer replaces the tracker's pose, so one tracking iteration is enough. 40x30 frames need
# every pixel and a 5 cm voxel for the fitness check; the odometer drifts by ~40% of the rotation it
# measures, so the odometry edges declare a drift ratio of 0.3 (an honest chain, docs/pgo.md).
DRIFT = ["tracking.iterations=1", "loop.min_keyframe_gap=6", "loop.icp_pixel_stride=1", "loop.icp_voxel_m=0.05",
         "loop.odometry_drift_ratio=0.3"]
BIAS = torch.tensor([0.004, 0.0, 0.0, 0.0, 0.01, 0.0], dtype=F64)  # per frame: [rho (m), phi (rad)], camera frame
FRAMES = 48


@pytest.fixture(scope="module")
def drift_sequence(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("loopseq") / "seq"
    data_synth.generate(out, layout="replica", trajectory="loop", width=40, height=30, frames=FRAMES, seed=0,
                        supersample=2)
    return out


def drift_setup(sequence: Path, *extra: str):
    """The drift runs' config and the stage constants they replace (PipelineHooks.constants)."""
    overrides, constants = split_settings([*TINY, *DRIFT, *extra])
    return load_config("synthetic", overrides=[f"dataset.path={sequence}", *overrides]), constants


def drift_config(sequence: Path, *extra: str):
    return drift_setup(sequence, *extra)[0]


def drift_loop_options(config, constants: dict) -> LoopOptions:
    """The loop stage's options of a drift run, as the pipeline builds them (PipelineHooks.options)."""
    return PipelineHooks(constants=constants).options(
        "loop", LoopOptions.from_config(config.loop, depth_noise_power=config.dataset.depth_noise_power))


def drift_run(sequence: Path, run_dir: Path, *extra: str, wrong: WrongLoop | None = None, resume: bool = False,
              diagnostics: bool = False):
    config, constants = drift_setup(sequence, *extra)
    odometer = BiasedOdometer(make_sequence(config.dataset).gt_T_wc, BIAS)
    return run_slam(config, run_dir, resume=resume, evaluate=False, observer=Observer(diagnostics=diagnostics),
                    hooks=PipelineHooks(after_tracking=odometer, loop_verification=wrong, constants=constants))


def ate_rmse(run_dir: Path) -> float:
    metrics = evaluate_trajectory(read_tum_trajectory(run_dir / "traj_gt.txt"),
                                  read_tum_trajectory(run_dir / "traj_est.txt"), alignment="se3")
    return float(metrics.ate.rmse)


def loops(run_dir: Path) -> dict:
    return json.loads((run_dir / "loops.json").read_text())


@pytest.fixture(scope="module")
def drift_runs(drift_sequence, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("loopruns")
    drift_run(drift_sequence, root / "off", "loop.enabled=false")
    drift_run(drift_sequence, root / "on", diagnostics=True)  # the map's PSNR around each correction in loops.json
    return {"off": root / "off", "on": root / "on", "root": root}


# ----------------------------------------------------------------------------- switch


def test_disabled_stage_is_absent_and_an_idle_stage_changes_nothing(drift_sequence, tmp_path):
    # Real tracking on the first 14 frames. Enabled, the stage finds no keyframe 10 keyframes older
    # than another, so it only stores descriptors and odometry edges: nothing else may change.
    common = [f"dataset.path={drift_sequence}", *TINY, "tracking.iterations=6", "dataset.max_frames=14"]
    run_slam(load_config("synthetic", overrides=[*common, "loop.enabled=false"]),
             tmp_path / "off", evaluate=False)
    run_slam(load_config("synthetic", overrides=common), tmp_path / "on", evaluate=False)
    off, on = read_tum_trajectory(tmp_path / "off" / "traj_est.txt"), read_tum_trajectory(tmp_path / "on" / "traj_est.txt")
    np.testing.assert_array_equal(off.T_wc, on.T_wc)
    map_off, map_on = read_map_ply(tmp_path / "off" / "map.ply"), read_map_ply(tmp_path / "on" / "map.ply")
    assert torch.equal(map_off.means, map_on.means) and torch.equal(map_off.colors_raw, map_on.colors_raw)

    timings_off = json.loads((tmp_path / "off" / "timings.json").read_text())["stages"]
    timings_on = json.loads((tmp_path / "on" / "timings.json").read_text())["stages"]
    assert "loop" not in timings_off and "pgo" not in timings_off
    assert len(timings_on["loop"]["per_frame_s"]) == len(timings_on["pgo"]["per_frame_s"]) == 14
    assert loops(tmp_path / "off")["enabled"] is False and loops(tmp_path / "off")["candidates"] == []

    # The enabled run's checkpoint holds the pose graph: one node per keyframe, a chain of odometry edges.
    checkpoint = load_latest_checkpoint(tmp_path / "on" / "checkpoints")
    state = LoopState.from_state_dict(select_prefix("loop", checkpoint.tensors))
    keyframes = int(checkpoint.tensors["keyframe_frames"].numel())
    assert keyframes >= 2
    assert state.graph.num_nodes == state.descriptors.shape[0] == keyframes
    assert state.graph.edge_nodes.tolist() == [[k, k + 1] for k in range(keyframes - 1)]
    assert not bool(state.graph.edge_is_loop.any())


# ----------------------------------------------------------------------------- drift is removed


def test_sa_pgo_halves_the_drift_of_a_biased_odometer(drift_runs):
    ate_off, ate_on = ate_rmse(drift_runs["off"]), ate_rmse(drift_runs["on"])
    assert ate_off > 0.03, f"the injected bias should drift by several cm, ATE {ate_off:.4f} m"
    assert ate_on <= 0.5 * ate_off, (ate_on, ate_off)

    report = loops(drift_runs["on"])
    assert report["enabled"] is True
    applied = [o for o in report["optimisations"] if o["applied"]]
    assert applied, report["optimisations"]
    for candidate in report["candidates"]:
        assert candidate["query_keyframe"] - candidate["candidate_keyframe"] >= 6  # min_keyframe_gap
        assert 0 <= candidate["fitness"] <= 1 and candidate["similarity"] > 0.5
        if candidate["accepted"]:
            assert candidate["inlier_rmse_m"] <= 0.05 and candidate["fitness"] >= 0.3
    for optimisation in applied:
        assert optimisation["final_cost"] <= optimisation["initial_cost"]
        assert optimisation["iterations"] >= 1 and optimisation["time_s"] > 0
    assert any(entry["accepted"] for entry in report["loops"])
    # every verified registration records the relative pose it measured; `mipslam eval` compares it with the truth
    assert all(len(c["measured_T_ij"]) == 16 == len(c["estimate_T_ij"]) for c in report["candidates"] if c["accepted"])
    from mipslam.evaluation.run_eval import evaluate_run

    edges = evaluate_run(drift_runs["on"], render=False, report=False)["loop_edges"]
    assert edges["edges"] == sum(c["measured_T_ij"] is not None for c in report["candidates"]) > 0
    assert edges["used"] == sum(bool(c["accepted"]) for c in report["candidates"])
    # at 40x30 pixels and a 5 cm voxel the edges err by centimetres, still less than the biased odometer drifted
    assert edges["error_t_cm_median"] < 100 * ate_off and edges["error_r_deg_median"] < 2.0, edges
    # ... and less than the drifted estimate they corrected
    assert edges["used_error_t_cm_median"] < edges["used_estimate_then_error_t_cm_median"], edges
    assert sum(row["edges"] for row in edges["by_fitness"]) == edges["edges"]
    # SA-PGO as configured by default: both spectral switches on.
    assert all(o["spectral_edge_weighting"] and o["low_frequency_correction"] for o in report["optimisations"])
    timings = json.loads((drift_runs["on"] / "timings.json").read_text())["stages"]
    assert len(timings["pgo"]["per_frame_s"]) == FRAMES and timings["pgo"]["total_s"] > 0


@torch.no_grad()
def final_map_psnr_at_ground_truth(run_dir: Path, sequence_dir: Path) -> float:
    """Mean PSNR of the run's final map rendered at the ground-truth poses of its keyframes (dB)."""
    config = drift_config(sequence_dir)
    sequence = make_sequence(config.dataset)
    frames = json.loads((run_dir / "frames.json").read_text())["frames"]
    gaussians = read_map_ply(run_dir / "map.ply").activated()
    values = []
    for index in [f["index"] for f in frames if f["keyframe_id"] >= 0]:
        out = render_view(gaussians, se3_inverse(sequence.gt_T_wc[index]).float(), sequence.intrinsics, config.render)
        values.append(float(psnr(out.color.clamp(0, 1), sequence[index].color)))
    return float(np.mean(values))


def test_map_correction_moves_gaussians_with_their_anchors(drift_sequence, drift_runs):
    report = loops(drift_runs["on"])
    first = next(o for o in report["optimisations"] if o["applied"])  # the keyframe that closes the lap
    assert first["gaussians_moved"] > 0 and first["max_correction_deg"] > 2.0
    # Re-rendered at the loop's keyframes (the first keyframe after the lap and the keyframe it
    # closes with), the corrected map is no worse than the drifted one was before the correction.
    before, after = np.mean(first["psnr_before_db"]), np.mean(first["psnr_after_db"])
    assert after >= before, (first["psnr_keyframes"], first["psnr_before_db"], first["psnr_after_db"])
    # The final map in the world frame: rendered at the true keyframe poses it is clearly better.
    psnr_on = final_map_psnr_at_ground_truth(drift_runs["on"], drift_sequence)
    psnr_off = final_map_psnr_at_ground_truth(drift_runs["off"], drift_sequence)
    assert psnr_on > psnr_off + 0.3, (psnr_on, psnr_off)


def test_correction_keeps_frames_relative_to_their_reference_keyframe():
    # Three frames: keyframe 0 (identity), keyframe 1, and a non-keyframe tracked after keyframe 1.
    def pose(*xi):
        return se3_exp(torch.tensor(xi, dtype=F64))

    T = [torch.eye(4, dtype=F64), pose(0.5, 0, 0, 0, 0.1, 0), pose(0.7, 0.1, 0, 0, 0.15, 0)]
    frames = [FrameRecord(0, 0.0, T[0], torch.zeros(2), "initial", 0.0, 0, 0, -1, T[0]),
              FrameRecord(1, 1.0, T[1], torch.zeros(2), "ok", 0.1, 5, 1, 0, T[1]),
              FrameRecord(2, 2.0, T[2], torch.zeros(2), "ok", 0.1, 5, -1, 1, T[2])]
    gmap = GaussianMap.empty(dtype=torch.float32)
    points = torch.tensor([[0.0, 0.0, 2.0], [0.5, 0.0, 2.0]])
    gmap.add(GaussianParameters.from_activated(points, torch.tensor([[1.0, 0, 0, 0]] * 2), torch.full((2, 3), 0.05),
                                               torch.full((2,), 0.5), torch.full((2, 3), 0.5),
                                               anchor_keyframe=torch.tensor([0, 1])))
    state = SLAMState(gmap, None, torch.Generator(), frames=frames, keyframe_frames=[0, 1])
    T1_new = pose(0.45, 0.02, 0, 0, 0.05, 0.01)
    moved = state.correct_keyframe_poses(torch.stack([T[0], T1_new]))
    assert moved == 2
    torch.testing.assert_close(state.frames[1].T_wc, T1_new)
    torch.testing.assert_close(se3_inverse(state.frames[1].T_wc) @ state.frames[2].T_wc, se3_inverse(T[1]) @ T[2])
    torch.testing.assert_close(state.frames[0].T_wc, T[0])
    # The Gaussian of keyframe 0 stays; the one of keyframe 1 keeps its position in keyframe 1's camera.
    torch.testing.assert_close(gmap.means[0], points[0])
    local_before = (se3_inverse(T[1]) @ torch.cat([points[1].double(), torch.ones(1, dtype=F64)]))[:3]
    local_after = (se3_inverse(T1_new) @ torch.cat([gmap.means[1].double(), torch.ones(1, dtype=F64)]))[:3]
    torch.testing.assert_close(local_after, local_before, atol=1e-6, rtol=0)


def test_frames_between_two_keyframes_blend_their_corrections_and_an_undo_is_exact():
    # keyframe 0, two frames tracked after it, keyframe 1, one frame after it; only keyframe 1 is corrected.
    from mipslam.geometry import interpolate_pose

    T = [se3_exp(torch.tensor([0.1 * k, 0.02 * k, 0, 0, 0.05 * k, 0], dtype=F64)) for k in range(5)]
    roles = [(0, -1), (-1, 0), (-1, 0), (1, 0), (-1, 1)]  # (keyframe id, reference keyframe)
    frames = [FrameRecord(k, float(k), T[k], torch.zeros(2), "ok", 0.1, 5, kf, ref, T[k])
              for k, (kf, ref) in enumerate(roles)]
    state = SLAMState(GaussianMap.empty(dtype=torch.float32), None, torch.Generator(), frames=frames,
                      keyframe_frames=[0, 3])
    before = state.poses()
    C1 = se3_exp(torch.tensor([0.03, -0.02, 0.01, 0.01, -0.02, 0.005], dtype=F64))
    state.correct_keyframe_poses(torch.stack([T[0], C1 @ T[3]]))
    after = state.poses()
    torch.testing.assert_close(after[0], T[0])
    torch.testing.assert_close(after[3], C1 @ T[3])
    torch.testing.assert_close(after[4], C1 @ T[4])  # after the newest keyframe: its correction alone
    for k, s in ((1, 1 / 3), (2, 2 / 3)):  # a third and two thirds of the way from keyframe 0 to keyframe 1
        torch.testing.assert_close(after[k], interpolate_pose(T[k], C1 @ T[k], s))
    # No step at keyframe 1: the frame before it has moved most of the way with it.
    step_before = (after[2][:3, 3] - T[2][:3, 3]).norm()
    assert (C1 @ T[2])[:3, 3].sub(T[2][:3, 3]).norm() * 0.6 < step_before
    state.set_poses(before)
    torch.testing.assert_close(state.poses(), before)
    with pytest.raises(ValueError, match="poses for 5 frames"):
        state.set_poses(before[:4])


def _corrected_one_frame_at_a_time(T_wc, roles, keyframe_frames, T_new):
    """The correction of :meth:`SLAMState.correct_keyframe_poses` written out frame by frame (its docstring)."""
    from mipslam.geometry import interpolate_pose

    T_old = torch.stack([T_wc[p] for p in keyframe_frames])
    changed = [not torch.equal(a, b) for a, b in zip(T_new, T_old)]
    C = [n @ se3_inverse(o) if c else torch.eye(4, dtype=F64) for n, o, c in zip(T_new, T_old, changed)]
    out = T_wc.clone()
    for position, (keyframe_id, r) in enumerate(roles):
        if keyframe_id >= 0:
            out[position] = T_new[keyframe_id] if changed[keyframe_id] else T_wc[position]
            continue
        following = r + 1 if 0 <= r and r + 1 < len(changed) else None
        if r < 0 or not (changed[r] or (following is not None and changed[following])):
            continue
        T = C[r] @ T_wc[position]
        if following is not None:
            start, end = keyframe_frames[r], keyframe_frames[following]
            T = interpolate_pose(T, C[following] @ T_wc[position], (position - start) / (end - start))
        out[position] = T
    return out


def test_the_correction_of_many_frames_matches_the_frame_by_frame_rule():
    generator = torch.Generator().manual_seed(5)
    keyframe_frames = [2, 5, 6, 11, 17]  # frames 0-1 come before any keyframe (no reference: they stay)
    roles, keyframe_id = [], -1
    for position in range(22):
        if position in keyframe_frames:
            keyframe_id += 1
            roles.append((keyframe_id, keyframe_id - 1))
        else:
            roles.append((-1, keyframe_id))
    T = se3_exp(0.3 * torch.randn(22, 6, generator=generator, dtype=F64))
    frames = [FrameRecord(k, float(k), T[k], torch.zeros(2), "ok", 0.1, 5, kf, ref, T[k])
              for k, (kf, ref) in enumerate(roles)]
    state = SLAMState(GaussianMap.empty(dtype=torch.float32), None, torch.Generator(), frames=frames,
                      keyframe_frames=keyframe_frames)
    C = se3_exp(0.05 * torch.randn(5, 6, generator=generator, dtype=F64))
    T_new = torch.stack([C[k] @ T[p] for k, p in enumerate(keyframe_frames)])
    T_new[2] = T[keyframe_frames[2]]  # keyframe 2 stays: its frames move only towards keyframe 3
    expected = _corrected_one_frame_at_a_time(T, roles, keyframe_frames, T_new)
    state.correct_keyframe_poses(T_new)
    torch.testing.assert_close(state.poses(), expected, rtol=0, atol=1e-12)  # batched products: rounding
    torch.testing.assert_close(state.poses()[:2], T[:2], rtol=0, atol=0)


# ----------------------------------------------------------------------------- robustness


def test_a_wrong_loop_edge_is_pruned_or_down_weighted(drift_sequence, drift_runs):
    # The second verified loop is moved by 45 cm and 8.6 deg but keeps its information and verdict.
    wrong = WrongLoop(torch.tensor([0.4, 0.0, 0.2, 0.0, 0.15, 0.0], dtype=F64), nth=1)
    run_dir = drift_runs["root"] / "wrong"
    drift_run(drift_sequence, run_dir, wrong=wrong)
    assert len(wrong.corrupted) == 1, "the sequence should verify at least two loops"
    pair = list(wrong.corrupted[0])
    assert ate_rmse(run_dir) <= ate_rmse(drift_runs["off"])
    report = loops(run_dir)
    status = next(entry for entry in report["loops"] if [entry["keyframe_i"], entry["keyframe_j"]] == pair)
    assert status["accepted"] is False
    seen = [o for o in report["optimisations"] if any(w["edge"] == pair for w in o["loop_edge_weights"])]
    if seen:  # it reached the pose graph: the robust kernel must have pruned or down-weighted it
        for optimisation in seen:
            weight = next(w["weight"] for w in optimisation["loop_edge_weights"] if w["edge"] == pair)
            assert pair in optimisation["pruned_edges"] or weight < 0.1, optimisation
        assert "pruned" in status["status"]
    else:  # no other loop edge implied its correction: it never entered the graph (loop.confirm_keyframes)
        assert "not confirmed by another loop edge" in status["status"], status
    assert any(entry["accepted"] for entry in report["loops"])  # the correct loops stay
    # With the confirmation off, the pose graph's robust kernel is the defence, and it holds as well.
    unconfirmed = WrongLoop(torch.tensor([0.4, 0.0, 0.2, 0.0, 0.15, 0.0], dtype=F64), nth=1)
    drift_run(drift_sequence, drift_runs["root"] / "wrong_unconfirmed", "loop.confirm_keyframes=0", wrong=unconfirmed)
    pair = list(unconfirmed.corrupted[0])
    report = loops(drift_runs["root"] / "wrong_unconfirmed")
    seen = [o for o in report["optimisations"] if any(w["edge"] == pair for w in o["loop_edge_weights"])]
    assert seen
    for optimisation in seen:
        weight = next(w["weight"] for w in optimisation["loop_edge_weights"] if w["edge"] == pair)
        assert pair in optimisation["pruned_edges"] or weight < 0.1, optimisation
    assert ate_rmse(drift_runs["root"] / "wrong_unconfirmed") <= ate_rmse(drift_runs["off"])


def closer_steps(sequence: Path, drift_per_keyframe: torch.Tensor, *overrides: str, hook=None) -> list:
    """LoopCloser over every 2nd frame of ``sequence`` as keyframes, at ground-truth poses times a growing drift;
    verification returns the exact ground-truth relative pose (a perfect loop edge)."""
    from mipslam.loop.closer import KeyframeView, LoopCloser

    config, constants = drift_setup(sequence, *overrides)
    frames = make_sequence(config.dataset)
    gt = frames.gt_T_wc.to(F64)[::2]
    drifted = torch.stack([gt[k] @ se3_exp(k * drift_per_keyframe) for k in range(len(gt))])

    def exact_edge(i, k, result):
        return replace(result, T_ij=se3_inverse(gt[i]) @ gt[k], accepted=True, reason="")

    def verification(i, k, result):
        return exact_edge(i, k, result) if hook is None else hook(i, k, exact_edge(i, k, result))

    closer, state, steps = LoopCloser(drift_loop_options(config, constants), verification_hook=verification), \
        LoopState.empty(), []

    def view(k: int) -> KeyframeView:
        frame = frames[2 * k]
        return KeyframeView(k, 2 * k, frame.color, frame.depth, frame.intrinsics)

    for k in range(len(gt)):
        step = closer.process_keyframe(state, view(k), drifted[: k + 1], (0.05, 0.05, 1.0), view)
        state, steps = step.state, steps + [step]
    return steps


def test_loop_edges_that_agree_with_the_poses_join_the_graph_without_an_optimisation(drift_sequence):
    def verified(steps) -> list[bool]:
        return [any(c.accepted for c in s.candidates) for s in steps]

    def optimised(steps) -> list[bool]:
        return [s.optimisation is not None for s in steps]

    no_drift = torch.zeros(6, dtype=F64)
    always = ("loop.consistent_chi2=0", "loop.min_correction_m=0", "loop.min_correction_deg=0")
    gated = closer_steps(drift_sequence, no_drift)
    assert any(verified(gated)), "the sequence should verify loops"
    # Edges that the poses already satisfy join the graph, and nothing is optimised.
    assert not any(optimised(gated)) and all(s.pgo_seconds == 0.0 for s in gated)
    assert int(gated[-1].state.graph.edge_is_loop.sum()) == sum(sum(c.accepted for c in s.candidates) for s in gated)
    # With both gates off, every keyframe that verified a loop optimises.
    ungated = closer_steps(drift_sequence, no_drift, *always)
    assert optimised(ungated) == verified(ungated)
    # 0.3 mm / 0.01 deg of drift per keyframe: chi-square far above 12.6 (the registration claims about a
    # millimetre), but the residuals stay under the 2 cm / 1 deg floor, so the floor alone skips them.
    creeping = torch.tensor([0.0003, 0, 0, 0, 0.0002, 0], dtype=F64)
    no_correction_floor = ("loop.min_correction_m=0", "loop.min_correction_deg=0")
    assert not any(optimised(closer_steps(drift_sequence, creeping)))
    assert any(optimised(closer_steps(drift_sequence, creeping, *no_correction_floor)))
    # With a 1 cm / 0.5 deg error floor on the loop edges (loop.loop_sigma_*) that drift is within the
    # chi-square gate as well.
    edge_floor = ("loop.loop_sigma_m=0.01", "loop.loop_sigma_deg=0.5")
    assert not any(optimised(closer_steps(drift_sequence, creeping, *no_correction_floor, *edge_floor)))
    # Poses that drifted centimetres away from the loop measurements are optimised.
    assert any(optimised(closer_steps(drift_sequence, torch.tensor([0.004, 0, 0, 0, 0.01, 0], dtype=F64))))


def test_a_disagreeing_loop_edge_needs_a_second_edge_that_implies_the_same_correction(drift_sequence):
    from mipslam.loop.closer import corrections_agree, implied_corrections

    def pose(*xi):
        return se3_exp(torch.tensor(xi, dtype=F64))

    truth = [pose(0.0, 0, 0, 0, 0, 0), pose(0.3, 0.1, 0, 0, 0.4, 0), pose(0.35, 0.1, 0.02, 0.05, 0.45, 0)]
    drift = pose(0.03, -0.02, 0.01, 0.01, 0.03, -0.02)  # world-frame drift shared by keyframes 1 and 2
    poses = torch.stack([truth[0], drift @ truth[1], drift @ truth[2]])
    exact = [se3_inverse(truth[0]) @ truth[k] for k in (1, 2)]
    C1, C2 = implied_corrections(poses, 1, [0], exact[:1])[0], implied_corrections(poses, 2, [0], exact[1:])[0]
    torch.testing.assert_close(C1, se3_inverse(drift))  # the correction undoes the drift exactly
    tolerances = (0.01, math.radians(0.5), 0.5)
    assert corrections_agree(C1, C2, poses[2], *tolerances)
    # The same test in another world frame (the verdict may not depend on where the origin lies).
    W = pose(5.0, -3.0, 2.0, 0.3, -0.2, 0.9)
    moved = W @ poses
    C1w = implied_corrections(moved, 1, [0], exact[:1])[0]
    C2w = implied_corrections(moved, 2, [0], exact[1:])[0]
    assert corrections_agree(C1w, C2w, moved[2], *tolerances)
    # Registration noise: each edge off by its own 3 cm / 1.5 deg, in different directions.
    noisy = [exact[0] @ pose(0.03, 0, 0, 0, 0.026, 0), exact[1] @ pose(-0.01, 0.03, 0, 0.026, 0, 0)]
    N1, N2 = implied_corrections(truth_stack := torch.stack(truth), 1, [0], noisy[:1])[0], \
        implied_corrections(truth_stack, 2, [0], noisy[1:])[0]
    assert not corrections_agree(N1, N2, truth_stack[2], *tolerances)

    # In the stage: perfect loop edges on drifting poses confirm each other and are optimised; edges each
    # corrupted in its own direction are never used, with the reason in the candidate report.
    drifting = torch.tensor([0.004, 0, 0, 0, 0.01, 0], dtype=F64)
    steps = closer_steps(drift_sequence, drifting)
    assert any(s.optimisation is not None for s in steps)

    calls = []

    def scattered(i, k, result):
        # 5 cm along one of 6 axes and 2 deg about one of 4: no two of any 12 consecutive edges alike
        n = len(calls)
        calls.append((i, k))
        error = torch.zeros(6, dtype=F64)
        error[n % 3] = 0.05 * (1 if n % 6 < 3 else -1)
        error[3 + n % 2] = math.radians(2.0) * (1 if n % 4 < 2 else -1)
        return replace(result, T_ij=se3_exp(error) @ result.T_ij, accepted=True, reason="")

    noisy_steps = closer_steps(drift_sequence, torch.zeros(6, dtype=F64), hook=scattered)
    reports = [c for s in noisy_steps for c in s.candidates]
    assert reports and not any(s.optimisation is not None for s in noisy_steps)
    assert all(not c.accepted and "not confirmed" in c.reason for c in reports)
    assert int(noisy_steps[-1].state.graph.edge_is_loop.sum()) == 0
    # With the confirmation off the same edges reach the pose graph.
    calls.clear()
    unchecked = closer_steps(drift_sequence, torch.zeros(6, dtype=F64), "loop.confirm_keyframes=0", hook=scattered)
    assert any(s.optimisation is not None for s in unchecked)


def test_verification_rejects_a_correction_larger_than_the_odometry_can_have_drifted():
    from mipslam.loop.closer import LoopCloser
    from mipslam.loop.registration import RegistrationResult

    config = load_config("base")  # odometry sigma 1 cm + 5 % of the path, 3 sigma
    closer = LoopCloser(LoopOptions.from_config(config.loop))
    # 20 keyframes 2 cm apart along x, no rotation: 0.38 m of path, 3 x (0.01 + 0.05 x 0.38) = 8.7 cm allowed.
    chain = torch.eye(4, dtype=F64).repeat(20, 1, 1)
    chain[:, 0, 3] = 0.02 * torch.arange(20, dtype=F64)

    def verified(correction_m: float, correction_deg: float) -> RegistrationResult:
        return RegistrationResult(torch.eye(4, dtype=F64), torch.eye(6, dtype=F64), 0.5, 0.01, 400, correction_m,
                                  correction_deg, True, "", 0.0)

    assert closer._within_expected_drift(verified(0.05, 1.0), chain).accepted
    too_far = closer._within_expected_drift(verified(0.19, 1.0), chain)
    assert not too_far.accepted and "0.087 m" in too_far.reason and "0.38 m" in too_far.reason
    assert not closer._within_expected_drift(verified(0.05, 11.6), chain).accepted  # 1.5 deg allowed
    off = LoopCloser(replace(LoopOptions.from_config(config.loop), max_drift_sigmas=0.0))
    assert off._within_expected_drift(verified(0.19, 11.6), chain).accepted


def test_a_loop_edge_is_never_more_certain_than_its_error_floor():
    from mipslam.loop.closer import loop_information

    # Open3D-like information: 1 mm and 0.05 deg standard deviations, with a translation-rotation coupling.
    rng = torch.Generator().manual_seed(0)
    basis = torch.linalg.qr(torch.randn(6, 6, generator=rng, dtype=F64))[0]
    sigmas = torch.tensor([1e-3] * 3 + [math.radians(0.05)] * 3, dtype=F64)
    covariance = basis @ torch.diag(sigmas**2) @ basis.T
    information = torch.linalg.inv(covariance)
    floored = loop_information(information, 0.01, 0.5)
    floor = torch.diag(torch.tensor([0.01**2] * 3 + [math.radians(0.5) ** 2] * 3, dtype=F64))
    torch.testing.assert_close(floored, torch.linalg.inv(covariance + floor))  # covariances add
    assert torch.allclose(floored, floored.T)
    assert float(torch.linalg.eigvalsh(floored).min()) > 0
    # a singular registration information (a wall: one direction unobserved) stays singular there and finite
    wall = torch.diag(torch.tensor([1e6, 1e6, 0.0, 1e5, 1e5, 1e5], dtype=F64))
    floored_wall = loop_information(wall, 0.01, 0.5)
    assert torch.isfinite(floored_wall).all() and abs(float(floored_wall[2, 2])) < 1e-9
    assert float(floored_wall[0, 0]) < 1e4 < 1e6  # at most 1 / (1 cm)^2
    assert loop_information(information, 0.0, 0.0) is information  # no floor: unchanged


# ----------------------------------------------------------------------------- resume


def test_resume_across_a_loop_closure_equals_the_uninterrupted_run(drift_sequence, drift_runs):
    full = drift_runs["on"]
    first_closure = next(o for o in loops(full)["optimisations"] if o["applied"])["query_frame"]
    stop = first_closure + 3
    assert stop < FRAMES - 6, "the split should leave loop closures for the resumed part"
    split = drift_runs["root"] / "split"
    drift_run(drift_sequence, split, f"dataset.max_frames={stop}")
    drift_run(drift_sequence, split, resume=True)
    np.testing.assert_allclose(read_tum_trajectory(split / "traj_est.txt").T_wc,
                               read_tum_trajectory(full / "traj_est.txt").T_wc, atol=1e-6)
    map_full, map_split = read_map_ply(full / "map.ply"), read_map_ply(split / "map.ply")
    assert len(map_full) == len(map_split)
    torch.testing.assert_close(map_split.means, map_full.means, atol=1e-5, rtol=0)

    def decisions(report: dict) -> list:
        return [(o["query_keyframe"], o["new_loop_edges"], o["pruned_edges"], o["applied"]) for o in report["optimisations"]]

    def verdicts(report: dict) -> list:
        return [(c["query_keyframe"], c["candidate_keyframe"], c["accepted"], c["reason"]) for c in report["candidates"]]

    assert decisions(loops(split)) == decisions(loops(full))
    assert verdicts(loops(split)) == verdicts(loops(full))
    # the resumed part verified loops of its own (their confirmation reads the restored recent corrections)
    assert any(c["query_frame"] >= stop and c["fitness"] >= 0.3 for c in loops(full)["candidates"])
    # The full run measured the map's PSNR around each correction (diagnostics), the split run did not (the
    # default): the results above are the same, so the diagnostics changed nothing.
    applied = [o for o in loops(split)["optimisations"] if o["applied"]]
    assert applied and all("psnr_after_db" not in o and o["gaussians_moved"] > 0 for o in applied)
    assert all("psnr_after_db" in o for o in loops(full)["optimisations"] if o["applied"])


def test_resume_is_bit_identical_where_small_splats_amplify_round_off(drift_sequence, tmp_path):
    # With 0.7-cell splats at 40x30 a last-bit difference at the first loop closure grew to 3.6 mm in
    # the map: Open3D's multi-threaded reductions made registration differ between runs. Open3D now
    # runs on one thread, and a resumed run equals the uninterrupted one exactly. The race showed in
    # 2 of 2 runs with a checkpoint every frame but does not show every time, so the setting is pinned too.
    from mipslam.loop.registration import load_open3d

    assert load_open3d().utility.get_max_threads() == 1
    small = "mapping.initial_scale_factor=0.7"
    drift_run(drift_sequence, tmp_path / "full", small)
    # split between the keyframes whose loop edges wait for confirmation and the one that confirms them: the
    # resumed run must restore the recent corrections to close the same loop
    drift_run(drift_sequence, tmp_path / "split", small, "dataset.max_frames=25")
    drift_run(drift_sequence, tmp_path / "split", small, resume=True)
    report = loops(tmp_path / "full")
    assert any(not c["accepted"] and "not confirmed" in c["reason"] for c in report["candidates"] if c["query_frame"] < 25)
    assert any(o["applied"] for o in report["optimisations"] if o["query_frame"] > 25)
    np.testing.assert_array_equal(read_tum_trajectory(tmp_path / "split" / "traj_est.txt").T_wc,
                                  read_tum_trajectory(tmp_path / "full" / "traj_est.txt").T_wc)
    assert torch.equal(read_map_ply(tmp_path / "split" / "map.ply").means,
                       read_map_ply(tmp_path / "full" / "map.ply").means)


# ----------------------------------------------------------------------------- verification


@pytest.mark.parametrize("method", ["direct", "rgbd_odometry"])
def test_dense_rgbd_alignment_recovers_loop_poses_on_a_textured_wall(drift_sequence, method):
    from mipslam.loop.registration import register_rgbd_pair

    config, constants = drift_setup(drift_sequence)
    registration = drift_loop_options(config, constants).registration_options()
    assert registration.method == "direct"  # the default
    options = replace(registration, method=method)
    sequence = make_sequence(config.dataset)
    gt = sequence.gt_T_wc
    # Start 7 cm / 2.4 deg off. Point-to-plane ICP slides along the wall here (errors of decimetres to
    # metres, docs/pgo.md); the dense alignment must end within a pixel: one pixel is 2 deg at 40x30.
    offset = torch.tensor([0.05, -0.03, 0.04, 0.02, 0.03, -0.02], dtype=F64)
    pixel_rad = math.atan(1.0 / sequence.intrinsics.fx)
    for i, j in [(0, 40), (2, 44), (5, 38), (3, 41), (6, 45)]:
        T_true = se3_inverse(gt[i]) @ gt[j]
        a, b = sequence[i], sequence[j]
        result = register_rgbd_pair(a.color, a.depth, b.color, b.depth, a.intrinsics, T_true @ se3_exp(offset), options)
        error = se3_log(se3_inverse(T_true) @ result.T_ij)
        assert result.accepted, result.reason
        assert float(error[:3].norm()) < 0.03 and float(error[3:].norm()) < pixel_rad, (i, j, error)
        assert torch.linalg.eigvalsh(result.information).min() > 0
