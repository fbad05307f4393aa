"""Trajectory evaluation (association, alignment, ATE, RPE) and TUM trajectory files.

The real-data tests check against evo (a test-only dependency) computed here through its Python
API, and against the reference number of ../shared/data/README.md.
"""
from __future__ import annotations

import copy
import json
import math
from functools import lru_cache

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from mipslam.errors import DatasetError, EvaluationError
from mipslam.evaluation import (
    associate_by_index,
    associate_by_timestamp,
    evaluate_trajectory,
    umeyama_alignment,
)
from mipslam.io import Trajectory, read_tum_trajectory, write_tum_trajectory

GT_FR1 = "freiburg1_xyz-groundtruth.txt"
GT_FR2 = "fr2_desk_groundtruth.txt"


# ----------------------------------------------------------------------------- helpers


def make_trajectory(n: int, seed: int, t0: float = 1000.0, dt: float = 1 / 30) -> Trajectory:
    """A smooth random camera path (metres, ~1 m extent) with varied orientations."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 1, n)
    positions = np.stack([np.sin(2 * s + rng.uniform(0, 3)), np.cos(3 * s), 0.5 * s**2 + rng.uniform(-1, 1)], 1)
    rotvecs = np.stack([0.5 * np.sin(4 * s), 0.3 * s, rng.uniform(-2, 2) + s], 1)
    T_wc = np.tile(np.eye(4), (n, 1, 1))
    T_wc[:, :3, :3] = Rotation.from_rotvec(rotvecs).as_matrix()
    T_wc[:, :3, 3] = positions
    return Trajectory(t0 + dt * np.arange(n), T_wc)


def similarity(rotvec, translation, scale: float = 1.0) -> np.ndarray:
    S = np.eye(4)
    S[:3, :3] = scale * Rotation.from_rotvec(rotvec).as_matrix()
    S[:3, 3] = translation
    return S


def apply_similarity(S: np.ndarray, trajectory: Trajectory) -> Trajectory:
    """Left-apply ``x -> s R x + t`` to positions and ``R`` to orientations."""
    scale = np.cbrt(np.linalg.det(S[:3, :3]))
    R = S[:3, :3] / scale
    T_wc = trajectory.T_wc.copy()
    T_wc[:, :3, 3] = trajectory.positions @ (scale * R).T + S[:3, 3]
    T_wc[:, :3, :3] = R @ T_wc[:, :3, :3]
    return Trajectory(trajectory.timestamps, T_wc)


def with_position_noise(trajectory: Trajectory, sigma: float, seed: int) -> Trajectory:
    T_wc = trajectory.T_wc.copy()
    T_wc[:, :3, 3] += np.random.default_rng(seed).normal(0, sigma, (len(trajectory), 3))
    return Trajectory(trajectory.timestamps, T_wc)


@lru_cache(maxsize=None)
def load(path: str) -> Trajectory:
    return read_tum_trajectory(path, allow_duplicate_timestamps=True)


# ----------------------------------------------------------------------------- real data: reference and evo


@pytest.mark.real_data
def test_reference_number_fr1_xyz_rgbdslam(tum_trajectories_path):
    gt = load(str(tum_trajectories_path / GT_FR1))
    est = load(str(tum_trajectories_path / "freiburg1_xyz-rgbdslam.txt"))
    metrics = evaluate_trajectory(gt, est)  # defaults: se3, timestamp, 0.02 s
    assert metrics.num_matched == 786
    assert metrics.ate.rmse == pytest.approx(0.013473, abs=5e-7)  # README: evo 1.38.1, evo_ape -a --t_max_diff 0.02
    assert metrics.num_est_poses == 788 and metrics.num_gt_poses == 3000


EVO_CASES = [
    (GT_FR1, "freiburg1_xyz-rgbdslam.txt", "se3", 1),
    (GT_FR1, "freiburg1_xyz-rgbdslam.txt", "sim3", 1),
    (GT_FR1, "freiburg1_xyz-rgbdslam.txt", "none", 1),
    (GT_FR1, "freiburg1_xyz-rgbdslam.txt", "se3", 3),
    (GT_FR1, "freiburg1_xyz-ORB_kf_mono.txt", "sim3", 1),
    (GT_FR2, "fr2_desk_ORB.txt", "se3", 1),
    (GT_FR2, "fr2_desk_ORB.txt", "sim3", 1),
    (GT_FR2, "fr2_desk_ORB_kf_mono.txt", "sim3", 1),
]


@lru_cache(maxsize=None)
def _evo_associated(gt_path: str, est_path: str):
    from evo.core import sync
    from evo.tools import file_interface

    return sync.associate_trajectories(
        file_interface.read_tum_trajectory_file(gt_path), file_interface.read_tum_trajectory_file(est_path), max_diff=0.02
    )


def evo_associated(gt_path: str, est_path: str):
    """evo's own reading and association (as evo_ape/evo_rpe with --t_max_diff 0.02); fresh copies."""
    return copy.deepcopy(_evo_associated(gt_path, est_path))


@pytest.mark.real_data
@pytest.mark.parametrize("gt_name, est_name, alignment, delta", EVO_CASES)
def test_equals_evo(tum_trajectories_path, gt_name, est_name, alignment, delta):
    pytest.importorskip("evo", reason="evo (test extra) is needed to cross-check ATE/RPE")
    from evo.core import metrics as evo_metrics
    from evo.main_ape import ape
    from evo.main_rpe import rpe

    gt_path, est_path = tum_trajectories_path / gt_name, tum_trajectories_path / est_name
    ours = evaluate_trajectory(load(str(gt_path)), load(str(est_path)), alignment=alignment, rpe_delta=delta)

    ref, est = evo_associated(str(gt_path), str(est_path))
    align, scale = alignment != "none", alignment == "sim3"
    assert ours.num_matched == ref.num_poses
    np.testing.assert_array_equal(ours.matched_gt_timestamps, ref.timestamps)
    np.testing.assert_array_equal(ours.matched_est_timestamps, est.timestamps)

    evo_ape = ape(copy.deepcopy(ref), copy.deepcopy(est), evo_metrics.PoseRelation.translation_part, align=align, correct_scale=scale)
    for key in ("rmse", "mean", "median", "std", "min", "max"):
        assert getattr(ours.ate, key) == pytest.approx(evo_ape.stats[key], abs=1e-9), key
    if align:
        evo_sim3 = evo_ape.np_arrays["alignment_transformation_sim3"]
        np.testing.assert_allclose(ours.alignment.matrix(), evo_sim3, atol=1e-9)

    for relation, ours_stats in (
        (evo_metrics.PoseRelation.translation_part, ours.rpe_translation),
        (evo_metrics.PoseRelation.rotation_angle_deg, ours.rpe_rotation),
    ):
        evo_rpe = rpe(
            copy.deepcopy(ref), copy.deepcopy(est), relation, delta=delta, delta_unit=evo_metrics.Unit.frames,
            align=align, correct_scale=scale,
        )
        assert ours_stats.count == evo_rpe.np_arrays["error_array"].size
        for key in ("rmse", "mean", "median", "std", "min", "max"):
            assert getattr(ours_stats, key) == pytest.approx(evo_rpe.stats[key], abs=1e-9), (relation, key)


@pytest.mark.real_data
def test_tum_reader_agrees_with_evo_reader(tum_trajectories_path):
    pytest.importorskip("evo", reason="evo (test extra) is needed for the cross-check")
    from evo.tools import file_interface

    for name in ("freiburg1_xyz-rgbdslam.txt", "fr2_desk_ORB_kf_mono.txt", GT_FR1):
        ours = load(str(tum_trajectories_path / name))
        theirs = file_interface.read_tum_trajectory_file(tum_trajectories_path / name)
        np.testing.assert_array_equal(ours.timestamps, theirs.timestamps)
        np.testing.assert_allclose(ours.T_wc, np.stack(theirs.poses_se3), atol=1e-12)


@pytest.mark.real_data
def test_real_ground_truth_with_duplicate_timestamp(tum_trajectories_path):
    path = tum_trajectories_path / GT_FR2
    with pytest.raises(DatasetError) as info:
        read_tum_trajectory(path)
    assert info.value.line == 10863 and str(path) in str(info.value)
    kept = load(str(path))
    assert len(kept) == 20957  # 20960 lines - 3 comments, both poses of the duplicate kept (like evo)


# ----------------------------------------------------------------------------- ATE / alignment properties


def test_identical_trajectories_have_zero_error():
    gt = make_trajectory(60, seed=1)
    for alignment in ("se3", "sim3", "none"):
        metrics = evaluate_trajectory(gt, gt, alignment=alignment)
        assert metrics.num_matched == 60
        assert metrics.ate.rmse < 1e-12 and metrics.ate.max < 1e-12
        assert metrics.rpe_translation.max < 1e-12 and metrics.rpe_rotation.max < 1e-5  # degrees
        assert metrics.alignment.scale == pytest.approx(1.0, abs=1e-12)


def test_path_length_of_estimate_and_ground_truth():
    gt = make_trajectory(90, seed=4)
    steps = np.linalg.norm(np.diff(gt.T_wc[:, :3, 3], axis=0), axis=1)
    same = evaluate_trajectory(gt, gt)
    assert same.path_length_gt_m == pytest.approx(steps.sum(), rel=1e-12)
    assert same.path_length_est_m == pytest.approx(same.path_length_gt_m, rel=1e-9)
    assert same.to_dict()["path_length"]["ratio"] == pytest.approx(1.0, rel=1e-9)
    # Jitter of 1 cm per pose lengthens the estimate's path, and a rigid motion of it changes nothing.
    noisy = with_position_noise(gt, 0.01, seed=5)
    jittery = evaluate_trajectory(gt, noisy)
    moved = evaluate_trajectory(gt, apply_similarity(similarity([0.3, -1.2, 2.0], [4.0, -2.0, 0.5]), noisy))
    assert jittery.path_length_est_m > 1.2 * jittery.path_length_gt_m
    assert moved.path_length_est_m == pytest.approx(jittery.path_length_est_m, rel=1e-9)
    # Only matched poses count: a ground truth at twice the rate is walked at the estimate's poses.
    assert evaluate_trajectory(gt, Trajectory(gt.timestamps[::2], gt.T_wc[::2])).path_length_gt_m < steps.sum()


def test_ate_invariant_to_rigid_transform_of_estimate():
    gt = make_trajectory(80, seed=2)
    noisy = with_position_noise(gt, 0.01, seed=3)
    S = similarity([0.3, -1.2, 2.0], [4.0, -2.0, 0.5])
    moved = apply_similarity(S, noisy)
    reference = evaluate_trajectory(gt, noisy)
    metrics = evaluate_trajectory(gt, moved)
    assert 0.005 < reference.ate.rmse < 0.02
    assert metrics.ate.rmse == pytest.approx(reference.ate.rmse, abs=1e-12)
    np.testing.assert_allclose(metrics.ate_errors, reference.ate_errors, atol=1e-12)
    # the fitted alignment undoes the motion: alignment(moved) = alignment(noisy) o S^-1
    np.testing.assert_allclose(metrics.alignment.matrix() @ S, reference.alignment.matrix(), atol=1e-10)
    # RPE does not see a rigid motion at all (even without alignment)
    unaligned = evaluate_trajectory(gt, moved, alignment="none")
    assert unaligned.rpe_translation.rmse == pytest.approx(reference.rpe_translation.rmse, abs=1e-12)
    assert unaligned.rpe_rotation.rmse == pytest.approx(reference.rpe_rotation.rmse, abs=1e-9)
    assert unaligned.ate.rmse > 1.0  # but the unaligned ATE does


@pytest.mark.parametrize("scale", [0.37, 2.5])
def test_sim3_recovers_known_scale(scale):
    gt = make_trajectory(50, seed=4)
    # est = S^-1 gt, so aligning est to gt must find S (scale included)
    S = similarity([-0.4, 0.2, 0.9], [1.0, 2.0, -3.0], scale)
    est = apply_similarity(np.linalg.inv(S), gt)
    metrics = evaluate_trajectory(gt, est, alignment="sim3")
    assert metrics.alignment.scale == pytest.approx(scale, rel=1e-12)
    np.testing.assert_allclose(metrics.alignment.matrix(), S, atol=1e-10)
    assert metrics.ate.rmse < 1e-10 and metrics.rpe_translation.rmse < 1e-10
    # SE(3) cannot explain the scale: its error is large, and its rotation is still proper
    rigid = evaluate_trajectory(gt, est, alignment="se3")
    assert rigid.ate.rmse > 0.05
    assert rigid.alignment.scale == 1.0
    assert np.linalg.det(rigid.alignment.rotation) == pytest.approx(1.0, abs=1e-12)


def test_sim3_scale_with_noise_matches_least_squares_optimum():
    gt = make_trajectory(100, seed=5)
    est = with_position_noise(apply_similarity(np.linalg.inv(similarity([0.1, 0.2, 0.3], [0, 1, 0], 1.7)), gt), 0.01, 6)
    fitted = evaluate_trajectory(gt, est, alignment="sim3")
    assert fitted.alignment.scale == pytest.approx(1.7, rel=0.02)
    # any perturbed scale gives a larger ATE RMSE (the closed form is the optimum)
    for factor in (0.99, 1.01):
        perturbed = fitted.alignment.scale * factor
        positions = perturbed * est.positions[fitted.association.est_indices] @ fitted.alignment.rotation.T
        t = gt.positions.mean(0) - positions.mean(0)
        rmse = np.sqrt(np.mean(np.sum((gt.positions - positions - t) ** 2, axis=1)))
        assert rmse > fitted.ate.rmse


def test_umeyama_reflection_fix_against_scipy_kabsch():
    rng = np.random.default_rng(7)
    source = rng.normal(size=(30, 3))
    # a mirrored copy: the unconstrained least-squares "rotation" would be a reflection
    target = source * np.array([1.0, 1.0, -1.0]) + rng.normal(0, 0.01, (30, 3)) + [1, 2, 3]
    fitted = umeyama_alignment(source, target, with_scale=False)
    assert np.linalg.det(fitted.rotation) == pytest.approx(1.0, abs=1e-12)
    expected, _ = Rotation.align_vectors(target - target.mean(0), source - source.mean(0))
    np.testing.assert_allclose(fitted.rotation, expected.as_matrix(), atol=1e-9)
    np.testing.assert_allclose(fitted.translation, target.mean(0) - fitted.rotation @ source.mean(0), atol=1e-12)


def test_degenerate_positions_cannot_be_aligned():
    gt = make_trajectory(20, seed=8)
    T_wc = gt.T_wc.copy()
    T_wc[:, :3, 3] = [0.5, 0.5, 0.5]  # a camera that only turns
    still = Trajectory(gt.timestamps, T_wc)
    with pytest.raises(EvaluationError, match="alignment='none'"):
        evaluate_trajectory(gt, still)
    metrics = evaluate_trajectory(gt, still, alignment="none")
    np.testing.assert_allclose(metrics.ate_errors, np.linalg.norm(gt.positions - 0.5, axis=1), atol=1e-12)


# ----------------------------------------------------------------------------- RPE with known answers


def straight_line(n: int, step: float, yaw_step_deg: float = 0.0) -> Trajectory:
    """Camera moving along its own x axis by ``step`` metres per frame while yawing."""
    T_wc = np.tile(np.eye(4), (n, 1, 1))
    for i in range(1, n):
        increment = similarity([0, 0, math.radians(yaw_step_deg)], [step, 0, 0])
        T_wc[i] = T_wc[i - 1] @ increment
    return Trajectory(np.arange(n) * 0.1, T_wc)


def test_rpe_known_translation_and_rotation_drift():
    gt = straight_line(20, 0.10)
    too_long = straight_line(20, 0.11)
    metrics = evaluate_trajectory(gt, too_long, alignment="none")
    assert metrics.rpe_translation.count == 19
    assert metrics.rpe_translation.min == pytest.approx(0.01, abs=1e-12)
    assert metrics.rpe_translation.max == pytest.approx(0.01, abs=1e-12)
    assert metrics.rpe_rotation.max < 1e-6
    turning = straight_line(20, 0.10, yaw_step_deg=1.5)
    metrics = evaluate_trajectory(gt, turning, alignment="none", rpe_delta=2)
    assert metrics.rpe_rotation.count == len(range(0, 20, 2)) - 1  # evo's consecutive pairs (0,2), (2,4), ...
    np.testing.assert_allclose(metrics.rpe_rotation.mean, 3.0, atol=1e-9)
    assert metrics.rpe_rotation.std < 1e-9
    # two steps of (1.5 deg yaw, 0.1 m forward) end 0.1 * |1 - exp(i 1.5 deg)| = 0.002618 m from where gt ends
    assert metrics.rpe_translation.mean == pytest.approx(0.1 * 2 * math.sin(math.radians(0.75)), abs=1e-12)


def test_rpe_delta_must_leave_pairs():
    gt = make_trajectory(5, seed=9)
    with pytest.raises(EvaluationError, match="rpe_delta=5"):
        evaluate_trajectory(gt, gt, rpe_delta=5)
    with pytest.raises(EvaluationError, match="rpe_delta"):
        evaluate_trajectory(gt, gt, rpe_delta=0)


# ----------------------------------------------------------------------------- association


def test_association_tie_goes_to_earlier_stamp_and_window_is_inclusive():
    gt = np.array([0.0, 0.25, 0.5, 0.75])
    match = associate_by_timestamp(gt, np.array([0.125, 0.375, 1.0]), max_diff=0.25)
    assert match.gt_indices.tolist() == [0, 1, 3] and match.est_indices.tolist() == [0, 1, 2]
    assert associate_by_timestamp(gt, np.array([1.0]), max_diff=0.2).gt_indices.size == 0


def test_association_walks_the_shorter_trajectory():
    # estimate shorter (or equal): every estimated pose gets its nearest gt pose, gt poses may repeat
    match = associate_by_timestamp(np.arange(6.0), np.array([1.0, 1.01, 3.4]), max_diff=0.02)
    assert match.est_indices.tolist() == [0, 1] and match.gt_indices.tolist() == [1, 1]
    # estimate longer: every gt pose gets its nearest estimated pose
    match = associate_by_timestamp(np.array([0.0, 1.0, 2.0]), np.array([0.0, 0.01, 0.99, 1.0, 2.0, 2.01]), 0.02)
    assert match.gt_indices.tolist() == [0, 1, 2] and match.est_indices.tolist() == [0, 3, 4]


stamp_grid = st.lists(st.integers(0, 60), min_size=1, max_size=25, unique=True).map(lambda v: np.sort(np.array(v) * 0.125))


@settings(max_examples=60, deadline=None)
@given(gt=stamp_grid, est=stamp_grid, max_diff=st.sampled_from([0.0, 0.125, 0.2, 0.25, 0.5]))
def test_association_equals_evo_on_random_stamps_with_ties(gt, est, max_diff):
    pytest.importorskip("evo", reason="evo (test extra) is needed for the cross-check")
    from evo.core import sync
    from evo.core.trajectory import PoseTrajectory3D

    def evo_trajectory(stamps):
        n = stamps.size
        return PoseTrajectory3D(np.arange(3 * n, dtype=float).reshape(n, 3), np.tile([1.0, 0, 0, 0], (n, 1)), stamps)

    ours = associate_by_timestamp(gt, est, max_diff)
    try:
        ref, est_synced = sync.associate_trajectories(evo_trajectory(gt), evo_trajectory(est), max_diff=max_diff)
    except sync.SyncException:
        assert len(ours) == 0
        return
    # positions encode the original index (3 i), so evo's kept poses tell which indices it matched
    assert ours.gt_indices.tolist() == (ref.positions_xyz[:, 0] / 3).astype(int).tolist()
    assert ours.est_indices.tolist() == (est_synced.positions_xyz[:, 0] / 3).astype(int).tolist()


def test_association_of_unsorted_stamps_uses_nearest_like_evo():
    # evo falls back to a linear search (first minimum) when the longer trajectory is unsorted
    match = associate_by_timestamp(np.array([2.0, 0.0, 1.0, 1.0]), np.array([1.0, 0.0]), max_diff=0.01)
    assert match.est_indices.tolist() == [0, 1] and match.gt_indices.tolist() == [2, 1]


def test_index_association():
    match = associate_by_index(4, 4)
    assert match.gt_indices.tolist() == match.est_indices.tolist() == [0, 1, 2, 3]
    assert match.max_diff_s is None
    with pytest.raises(EvaluationError, match="3 estimated and 4 ground truth"):
        associate_by_index(4, 3)
    gt = make_trajectory(10, seed=10)
    est = Trajectory(np.arange(10.0), gt.T_wc)  # frame numbers as timestamps (Replica)
    assert evaluate_trajectory(gt, est, association="index").ate.rmse < 1e-12


def test_too_few_matches_reports_counts_and_time_ranges():
    gt = make_trajectory(30, seed=11, t0=100.0)
    est = make_trajectory(30, seed=11, t0=160.0)  # a one-minute clock offset
    with pytest.raises(EvaluationError) as info:
        evaluate_trajectory(gt, est)
    message = str(info.value)
    assert "only 0 pose(s) matched" in message and "0.02 s" in message
    assert "[100.000000, 100.966667]" in message and "[160.000000, 160.966667]" in message
    two = Trajectory(gt.timestamps[:2], gt.T_wc[:2])
    with pytest.raises(EvaluationError, match="only 2 pose"):
        evaluate_trajectory(gt, two)


def test_bad_arguments_and_non_finite_poses():
    gt = make_trajectory(10, seed=12)
    with pytest.raises(EvaluationError, match="unknown alignment 'sim2'"):
        evaluate_trajectory(gt, gt, alignment="sim2")
    with pytest.raises(EvaluationError, match="unknown association"):
        evaluate_trajectory(gt, gt, association="nearest")
    T_wc = gt.T_wc.copy()
    T_wc[4, 0, 3] = np.nan
    with pytest.raises(EvaluationError, match="estimated pose 4"):
        evaluate_trajectory(gt, Trajectory(gt.timestamps, T_wc))


def test_to_dict_spells_out_the_protocol():
    gt = make_trajectory(40, seed=13)
    est = with_position_noise(apply_similarity(similarity([0, 0, 1], [1, 0, 0], 0.5), gt), 0.01, 14)
    est = est.subset(np.arange(0, 40, 2))
    metrics = evaluate_trajectory(gt, est, alignment="sim3", max_diff=0.01)
    report = json.loads(json.dumps(metrics.to_dict()))  # plain JSON types only
    protocol = report["protocol"]
    assert protocol["alignment"]["method"] == "sim3"
    assert protocol["alignment"]["scale"] == pytest.approx(2.0, rel=0.05)
    np.testing.assert_allclose(protocol["alignment"]["rotation"], metrics.alignment.rotation)
    assert protocol["association"] == {
        "method": "timestamp", "max_diff_s": 0.01, "rule": protocol["association"]["rule"],
    }
    assert (protocol["num_est_poses"], protocol["num_gt_poses"], protocol["num_matched"]) == (20, 40, 20)
    assert protocol["frames"]["matched_gt_indices"] == list(range(0, 40, 2))
    assert protocol["frames"]["matched_est_indices"] == list(range(20))
    assert "-as --t_max_diff 0.01" in protocol["equivalent_evo"]
    assert report["ate"]["unit"] == "m" and report["rpe_rotation"]["unit"] == "deg"
    assert report["ate"]["rmse"] == metrics.ate.rmse and report["ate"]["count"] == 20
    assert report["rpe_translation"]["count"] == 19


# ----------------------------------------------------------------------------- TUM files


def test_write_read_round_trip_exact_to_printed_precision(tmp_path):
    gt = make_trajectory(200, seed=15, t0=1305031102.160407)
    path = write_tum_trajectory(tmp_path / "traj.txt", gt.timestamps, gt.T_wc)
    back = read_tum_trajectory(path)
    assert len(back) == 200
    ulp = np.spacing(gt.timestamps.max())
    assert np.abs(back.timestamps - gt.timestamps).max() <= 0.5e-6 + ulp
    assert np.abs(back.positions - gt.positions).max() <= 0.5e-9 + 1e-15
    # each quaternion component is off by <= 0.5e-9, so each rotation entry by a few 1e-9
    assert np.abs(back.T_wc[:, :3, :3] - gt.T_wc[:, :3, :3]).max() < 5e-9
    # writing what was read reproduces the text of timestamps and positions exactly; the quaternion
    # (normalised on reading, recomputed from the matrix) moves by at most one unit of the last digit
    again = write_tum_trajectory(tmp_path / "again.txt", back.timestamps, back.T_wc)
    first_rows = [line.split() for line in path.read_text().splitlines()[1:]]
    second_rows = [line.split() for line in again.read_text().splitlines()[1:]]
    assert [row[:4] for row in first_rows] == [row[:4] for row in second_rows]
    quats_first = np.array([row[4:] for row in first_rows], dtype=float)
    quats_second = np.array([row[4:] for row in second_rows], dtype=float)
    assert np.abs(quats_first - quats_second).max() <= 1.01e-9
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.txt", "traj.txt"]  # no temporary files left


def test_write_accepts_torch_float32_and_creates_folders(tmp_path):
    gt = make_trajectory(5, seed=16)
    path = write_tum_trajectory(
        tmp_path / "run" / "traj_est.txt", torch.tensor(gt.timestamps), torch.tensor(gt.T_wc).float()
    )
    back = read_tum_trajectory(path)
    np.testing.assert_allclose(back.T_wc, gt.T_wc, atol=1e-6)
    data_lines = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    assert len(data_lines) == 5 and all(len(line.split()) == 8 for line in data_lines)
    assert all(float(line.split()[7]) >= 0 for line in data_lines)  # qw >= 0


def _scaled_rotation(T_wc, stamps):
    T_wc[:, :3, :3] *= 1.1
    return T_wc, stamps


def _nan_translation(T_wc, stamps):
    T_wc[3, 1, 3] = np.nan
    return T_wc, stamps


def _reversed_stamps(T_wc, stamps):
    return T_wc, stamps[::-1].copy()


def _sub_microsecond_stamps(T_wc, stamps):
    return T_wc, 5.0 + np.arange(len(stamps)) * 1e-7


def _missing_pose(T_wc, stamps):
    return T_wc[:-1], stamps


def _infinite_stamp(T_wc, stamps):
    stamps[2] = np.inf
    return T_wc, stamps


@pytest.mark.parametrize(
    "breaker, expected",
    [
        (_scaled_rotation, "pose 0 .* not a finite rigid transform"),
        (_nan_translation, "pose 3 .* not a finite rigid transform"),
        (_reversed_stamps, "not larger than"),
        (_sub_microsecond_stamps, "microsecond precision"),
        (_missing_pose, "need timestamps"),
        (_infinite_stamp, "timestamp of pose 2 is not finite"),
    ],
)
def test_write_refuses_bad_poses_and_leaves_existing_file(tmp_path, breaker, expected):
    gt = make_trajectory(6, seed=17)
    path = tmp_path / "traj.txt"
    path.write_text("previous content\n")
    T_wc, stamps = breaker(gt.T_wc.copy(), gt.timestamps.copy())
    with pytest.raises(DatasetError, match=expected) as info:
        write_tum_trajectory(path, stamps, T_wc)
    assert str(path) in str(info.value)
    assert path.read_text() == "previous content\n"
    assert [p.name for p in tmp_path.iterdir()] == ["traj.txt"]  # no temporary file left behind


def test_reader_accepts_commas_comments_and_rounded_quaternions(tmp_path):
    spaced = tmp_path / "spaced.txt"
    spaced.write_text(
        "# timestamp tx ty tz qx qy qz qw\n\n"
        "1.0 0.1 0.2 0.3 0 0 0 1\n"
        "   \n"
        "2.0\t0.4 0.5 0.6 0.0 0.0 0.6 0.8\n"
        "3.0 0 0 0 0 0.7071 0 0.7071\n"  # norm 0.99999: rounded, normalised
    )
    commas = tmp_path / "commas.txt"
    commas.write_text("1.0,0.1,0.2,0.3,0,0,0,1\n2.0, 0.4, 0.5, 0.6, 0.0, 0.0, 0.6, 0.8\n3.0,0,0,0,0,0.7071,0,0.7071\n")
    a, b = read_tum_trajectory(spaced), read_tum_trajectory(commas)
    np.testing.assert_array_equal(a.timestamps, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(a.T_wc, b.T_wc)
    np.testing.assert_allclose(a.T_wc[1, :3, :3], Rotation.from_quat([0, 0, 0.6, 0.8]).as_matrix(), atol=1e-15)
    np.testing.assert_allclose(a.T_wc[2, :3, :3], Rotation.from_rotvec([0, math.pi / 2, 0]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(a.positions[1], [0.4, 0.5, 0.6])
    off = tmp_path / "off.txt"
    off.write_text("1.0 0 0 0 0 0 0.6 0.85\n")  # norm 1.04: accepted and normalised
    R = read_tum_trajectory(off).T_wc[0, :3, :3]
    np.testing.assert_allclose(R, Rotation.from_quat([0, 0, 0.6, 0.85]).as_matrix(), atol=1e-15)


GOOD = "1.0 0 0 0 0 0 0 1\n"
BAD_FILES = [
    ("short line", "# header\n" + GOOD + "2.0 0 0 0 0 0 1\n", 3, "expected 8 numbers"),
    ("long line", GOOD + "2.0 0 0 0 0 0 0 1 5\n", 2, "found 9"),
    ("not a number", GOOD + "2.0 0 abc 0 0 0 0 1\n", 2, "'ty' is not a number"),
    ("nan", "1.0 nan 0 0 0 0 0 1\n", 1, "'tx' is not finite"),
    ("inf", GOOD + "2.0 0 0 0 0 0 0 inf\n", 2, "'qw' is not finite"),
    ("zero quaternion", GOOD + "2.0 0 0 0 0 0 0 0\n", 2, "quaternion qx qy qz qw is zero"),
    ("long quaternion", GOOD + "2.0 0 0 0 0 0 0 2\n", 2, "norm 2"),
    ("short quaternion", "\n\n1.0 0 0 0 0.5 0 0 0.5\n", 3, "far from 1"),
    ("unsorted", GOOD + "3.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n", 3, "timestamps must increase"),
    ("duplicate", GOOD + "# c\n1.0 0 0 0 0 0 0 1\n", 3, "duplicate timestamp 1.0 .also on line 1"),
    ("empty", "", None, "contains no poses"),
    ("only comments", "# a\n\n# b\n", None, "contains no poses"),
]


@pytest.mark.parametrize("case, content, line, message", BAD_FILES, ids=[c[0] for c in BAD_FILES])
def test_bad_files_raise_dataset_error_naming_file_and_line(tmp_path, case, content, line, message):
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(DatasetError, match=message) as info:
        read_tum_trajectory(path)
    assert info.value.path == path and info.value.line == line
    assert str(info.value).startswith(f"{path}:{line}: " if line is not None else f"{path}: ")


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(DatasetError, match="not found") as info:
        read_tum_trajectory(tmp_path / "nope.txt")
    assert info.value.path == tmp_path / "nope.txt"
    binary = tmp_path / "binary.txt"
    binary.write_bytes(b"\xff\xfe\x00\x01garbage")
    with pytest.raises(DatasetError, match="UTF-8") as info:
        read_tum_trajectory(binary)
    assert info.value.path == binary


def test_duplicate_timestamps_can_be_kept_like_evo(tmp_path):
    path = tmp_path / "dup.txt"
    path.write_text(GOOD + "1.0 1 0 0 0 0 0 1\n2.0 2 0 0 0 0 0 1\n")
    kept = read_tum_trajectory(path, allow_duplicate_timestamps=True)
    assert kept.timestamps.tolist() == [1.0, 1.0, 2.0] and kept.positions[:, 0].tolist() == [0.0, 1.0, 2.0]
    # evo's binary search (side="right") pairs a stamp with the last of several equal stamps
    match = associate_by_timestamp(kept.timestamps, np.array([1.0]), max_diff=0.01)
    assert match.gt_indices.tolist() == [1]


def test_trajectory_checks_shapes_and_is_read_only():
    with pytest.raises(ValueError, match=r"\[N, 4, 4\]"):
        Trajectory(np.zeros(3), np.zeros((3, 3, 3)))
    with pytest.raises(ValueError, match="3 timestamps but 2 poses"):
        Trajectory(np.zeros(3), np.tile(np.eye(4), (2, 1, 1)))
    trajectory = make_trajectory(4, seed=18)
    with pytest.raises(ValueError):
        trajectory.T_wc[0, 0, 0] = 5.0
    assert trajectory.subset(np.array([3, 1])).timestamps.tolist() == [trajectory.timestamps[3], trajectory.timestamps[1]]
