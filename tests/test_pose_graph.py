"""Pose graph: residuals, analytic Jacobians, LM guarantees, gauge, subspace = full, robustness."""
from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from mipslam.errors import CheckpointError
from mipslam.geometry import se3_exp, se3_inverse, se3_log
from mipslam.loop.pose_graph import (
    PoseGraph,
    edge_jacobians,
    edge_residuals,
    mahalanobis_sq,
    perturb_left,
    se3_right_jacobian_inverse,
)
from mipslam.loop.solver import PGOOptions, optimize_pose_graph, optimize_pose_graph_window
from synthetic_pose_graphs import circle_trajectory, make_synthetic_pose_graph, trajectory_errors

F64 = torch.float64
PLAIN = PGOOptions()
SUBSPACE = PGOOptions(low_frequency_correction=True)
SPECTRAL = PGOOptions(spectral_edge_weighting=True)
BOTH = PGOOptions(spectral_edge_weighting=True, low_frequency_correction=True)


def _random_graph(num_nodes: int, seed: int, residual_scale: float) -> PoseGraph:
    """Random poses, a chain plus a few long edges, measurements off the truth by ~residual_scale."""
    gen = torch.Generator().manual_seed(seed)
    poses = se3_exp(torch.randn(num_nodes, 6, generator=gen, dtype=F64) * torch.tensor([2, 2, 2, 1, 1, 1], dtype=F64))
    graph = PoseGraph.from_odometry(poses, torch.eye(6, dtype=F64))
    for i, j in [(0, num_nodes - 1), (1, num_nodes // 2)]:
        graph = graph.add_edge(i, j, se3_inverse(poses[i]) @ poses[j], torch.eye(6, dtype=F64), "loop")
    noise = se3_exp(torch.randn(graph.num_edges, 6, generator=gen, dtype=F64) * residual_scale)
    return PoseGraph(graph.poses, graph.edge_nodes, graph.measurements @ noise, graph.information, graph.edge_is_loop)


def test_residual_is_zero_at_the_truth():
    truth = circle_trajectory(40, laps=2)
    graph = PoseGraph.from_odometry(truth, torch.eye(6, dtype=F64))
    graph = graph.add_edge(3, 23, se3_inverse(truth[3]) @ truth[23], torch.eye(6, dtype=F64) * 100, "loop")
    res = edge_residuals(graph.poses, graph.edge_nodes, graph.measurements)
    assert res.shape == (40, 6)
    assert res.abs().max() < 1e-12
    result = optimize_pose_graph(graph)
    assert result.initial_cost < 1e-20
    assert (result.poses - truth).abs().max() < 1e-12  # nothing to correct


@pytest.mark.parametrize("residual_scale", [1e-2, 0.3, 1.0])
def test_analytic_jacobians_match_central_differences(residual_scale):
    graph = _random_graph(6, seed=3, residual_scale=residual_scale)
    poses, nodes, Z = graph.poses, graph.edge_nodes, graph.measurements
    res = edge_residuals(poses, nodes, Z)
    assert res.norm(dim=-1).max() > 0.5 * residual_scale  # the check runs away from the truth
    J_i, J_j = edge_jacobians(poses, nodes, res)
    h = 1e-6
    worst = 0.0
    for node in range(graph.num_nodes):
        for k in range(6):
            delta = torch.zeros(graph.num_nodes, 6, dtype=F64)
            delta[node, k] = h
            fd = (edge_residuals(perturb_left(poses, delta), nodes, Z) - edge_residuals(perturb_left(poses, -delta), nodes, Z)) / (2 * h)
            analytic = torch.zeros_like(fd)
            analytic += torch.where((nodes[:, 0] == node)[:, None], J_i[:, :, k], torch.zeros_like(fd))
            analytic += torch.where((nodes[:, 1] == node)[:, None], J_j[:, :, k], torch.zeros_like(fd))
            worst = max(worst, float((fd - analytic).abs().max()))
    assert worst < 1e-6


@pytest.mark.parametrize("angle", [1e-4, 0.0999, 0.1001, 1.0, 3.0])
def test_right_jacobian_inverse_linearises_the_logarithm(angle):
    """Log(Exp(xi) Exp(eta)) = xi + J_r^-1(xi) eta + O(|eta|^2), on both sides of the Taylor switch."""
    gen = torch.Generator().manual_seed(1)
    axis = torch.randn(3, generator=gen, dtype=F64)
    xi = torch.cat([torch.randn(3, generator=gen, dtype=F64), axis / axis.norm() * angle])
    J = se3_right_jacobian_inverse(xi)
    # h = 1e-3: geometry.se3_log carries a smooth ~1e-9 error near 1e-4 rad that a smaller step would amplify
    h = 1e-3
    for k in range(6):
        eta = torch.zeros(6, dtype=F64)
        eta[k] = h
        fd = (se3_log(se3_exp(xi) @ se3_exp(eta)) - se3_log(se3_exp(xi) @ se3_exp(-eta))) / (2 * h)
        assert (fd - J[:, k]).abs().max() < 1e-6


def test_lm_never_increases_the_cost():
    syn = make_synthetic_pose_graph(60, laps=2, num_outlier_loops=2, noisy_fraction=0.2, seed=4)
    for options in (PLAIN, SUBSPACE, BOTH):
        result = optimize_pose_graph(syn.graph, replace(options, prune_chi2=None))
        history = torch.tensor(result.cost_history, dtype=F64)
        assert len(history) >= 3
        assert bool((history[1:] <= history[:-1]).all())
        assert result.final_cost < 0.9 * result.initial_cost
        assert result.final_cost == pytest.approx(float(history[-1]))


def test_gauge_node_does_not_move():
    syn = make_synthetic_pose_graph(50, laps=2, seed=5)
    for options in (PLAIN, BOTH):
        result = optimize_pose_graph(syn.graph, options)
        assert torch.equal(result.poses[0], syn.graph.poses[0])
        assert (result.poses[1:] - syn.graph.poses[1:]).abs().max() > 1e-3  # the others did move
    moved_gauge = optimize_pose_graph(syn.graph, replace(PLAIN, fixed_nodes=(7,)))
    assert torch.equal(moved_gauge.poses[7], syn.graph.poses[7])


def test_subspace_with_every_mode_equals_the_full_solution():
    syn = make_synthetic_pose_graph(30, laps=2, loop_every=3, seed=6)
    tight = dict(robust_kernel="none", prune_chi2=None, relative_tolerance=1e-14, step_tolerance=1e-13)
    full = optimize_pose_graph(syn.graph, PGOOptions(max_iterations=100, **tight))
    sub = optimize_pose_graph(syn.graph, PGOOptions(low_frequency_correction=True, num_eigenvectors=30,
                                                    subspace_iterations=100, subspace_relative_tolerance=1e-14,
                                                    full_iterations=0, **tight))
    assert sub.num_eigenvectors_used == 29  # every free node
    assert sub.iterations == sub.subspace_iterations
    assert (sub.poses - full.poses).abs().max() < 1e-6
    assert sub.final_cost == pytest.approx(full.final_cost, rel=1e-9)
    # with few modes and no full iterations the solution is a genuinely different (coarser) one
    coarse = optimize_pose_graph(syn.graph, PGOOptions(low_frequency_correction=True, num_eigenvectors=3,
                                                       full_iterations=0, **tight))
    assert coarse.final_cost > full.final_cost * 1.01


@pytest.mark.parametrize("options", [PLAIN, SPECTRAL, SUBSPACE, BOTH], ids=["full", "spectral", "lowfreq", "both"])
def test_noisy_chain_with_loops_converges_near_the_truth(options):
    syn = make_synthetic_pose_graph(100, laps=2, seed=7)
    before = trajectory_errors(syn.graph.poses, syn.poses_true)
    result = optimize_pose_graph(syn.graph, options)
    after = trajectory_errors(result.poses, syn.poses_true)
    assert before.translation_rmse_m > 0.3  # the odometry really drifted
    assert after.translation_rmse_m < 0.3 * before.translation_rmse_m
    assert after.rotation_rmse_deg < 0.35 * before.rotation_rmse_deg
    assert result.pruned_edges == ()  # every loop here is correct


@pytest.mark.parametrize("options", [PLAIN, BOTH], ids=["full", "both"])
def test_a_wrong_loop_among_correct_ones_is_rejected(options):
    syn = make_synthetic_pose_graph(100, laps=2, seed=8, num_outlier_loops=1)
    (wrong,) = syn.outlier_edges
    result = optimize_pose_graph(syn.graph, options)
    assert wrong in result.pruned_edges or float(result.loop_weights[wrong]) < 0.05
    odometry_only = optimize_pose_graph(syn.graph.select_edges(~syn.graph.edge_is_loop), options)
    ate = trajectory_errors(result.poses, syn.poses_true).translation_rmse_m
    ate_without_loops = trajectory_errors(odometry_only.poses, syn.poses_true).translation_rmse_m
    assert ate <= ate_without_loops
    # and the correct loops still did their job
    assert ate < 0.5 * ate_without_loops


def test_without_a_robust_kernel_the_wrong_loop_does_damage():
    """The control experiment for the test above: the kernel and pruning are what protect the map."""
    syn = make_synthetic_pose_graph(100, laps=2, seed=8, num_outlier_loops=1)
    naive = optimize_pose_graph(syn.graph, PGOOptions(robust_kernel="none", prune_chi2=None))
    robust = optimize_pose_graph(syn.graph, PLAIN)
    naive_ate = trajectory_errors(naive.poses, syn.poses_true).translation_rmse_m
    robust_ate = trajectory_errors(robust.poses, syn.poses_true).translation_rmse_m
    assert naive_ate > 2 * robust_ate


def test_thousand_nodes_optimise_quickly():
    syn = make_synthetic_pose_graph(1000, laps=4, sigma_rotation=0.002, seed=9)
    result = optimize_pose_graph(syn.graph, PLAIN)
    assert result.converged and result.iterations <= 30
    # "well under a second" on an idle core; this bound only catches gross regressions on a busy CI box
    assert result.time_s < 8.0
    assert trajectory_errors(result.poses, syn.poses_true).translation_rmse_m < 0.25 * trajectory_errors(
        syn.graph.poses, syn.poses_true).translation_rmse_m


def test_graph_construction_validation_and_checkpoint_round_trip(tmp_path):
    truth = circle_trajectory(5)
    graph = PoseGraph.empty()
    for T in truth:
        graph = graph.add_node(T)
    for k in range(4):
        graph = graph.add_edge(k, k + 1, se3_inverse(truth[k]) @ truth[k + 1], torch.eye(6, dtype=F64), "odometry")
    graph = graph.add_edge(0, 4, se3_inverse(truth[0]) @ truth[4], 2 * torch.eye(6, dtype=F64), "loop")
    assert (graph.num_nodes, graph.num_edges) == (5, 5)
    assert graph.edge_is_loop.tolist() == [False, False, False, False, True]
    with pytest.raises(ValueError, match="outside"):
        graph.add_edge(0, 9, torch.eye(4, dtype=F64), torch.eye(6, dtype=F64), "loop")
    with pytest.raises(ValueError, match="kind"):
        graph.add_edge(0, 1, torch.eye(4, dtype=F64), torch.eye(6, dtype=F64), "imu")

    path = tmp_path / "graph.pt"
    torch.save(graph.state_dict(), path)
    loaded = PoseGraph.from_state_dict(torch.load(path, weights_only=True))
    for name in ("poses", "edge_nodes", "measurements", "information", "edge_is_loop"):
        assert torch.equal(getattr(loaded, name), getattr(graph, name))
    broken = graph.state_dict()
    del broken["information"]
    with pytest.raises(CheckpointError, match="information"):
        PoseGraph.from_state_dict(broken)
    broken = graph.state_dict()
    broken["edge_nodes"] = broken["edge_nodes"] + 10
    with pytest.raises(CheckpointError, match="malformed"):
        PoseGraph.from_state_dict(broken)
    assert not math.isnan(optimize_pose_graph(loaded.without_edges([4])).final_cost)


# ----------------------------------------------------------------------------- windowed optimisation


def test_window_covering_the_graph_is_the_whole_graph_optimisation():
    syn = make_synthetic_pose_graph(num_nodes=60, seed=2)
    full = optimize_pose_graph(syn.graph, BOTH)
    for window in (0, 60, 500):
        windowed = optimize_pose_graph_window(syn.graph, BOTH, window)
        assert torch.equal(windowed.poses, full.poses)
        assert windowed.problem_nodes == 60 and windowed.problem_edges == syn.graph.num_edges


def test_window_moves_only_its_nodes_and_anchors_them_to_the_older_ones():
    syn = make_synthetic_pose_graph(num_nodes=120, laps=3.0, num_outlier_loops=2, seed=4)
    graph, window = syn.graph, 40
    result = optimize_pose_graph_window(graph, BOTH, window)
    old = graph.num_nodes - window
    assert torch.equal(result.poses[:old], graph.poses[:old])  # the history stays where it was
    assert (result.poses[old:] - graph.poses[old:]).abs().max() > 1e-4  # the window was corrected
    # the problem: the window plus the older nodes its edges reach, and only edges with a free end
    touches = (graph.edge_nodes >= old).any(dim=1)
    anchors = {int(v) for v in graph.edge_nodes[touches].ravel() if int(v) < old}
    assert result.problem_nodes == window + len(anchors) < graph.num_nodes
    assert result.problem_edges == int(touches.sum())
    # results come back in the input graph's edge indices
    assert result.loop_weights.shape == (graph.num_edges,) and result.edge_chi2.shape == (graph.num_edges,)
    assert all(bool(touches[e]) and bool(graph.edge_is_loop[e]) for e in result.pruned_edges)
    assert bool(torch.isfinite(result.edge_chi2).all()) and result.notes[0].startswith("window: 40 newest")
    # the window's own cost went down; the chi2 of an edge the problem left out is its old value
    assert result.final_cost < result.initial_cost
    before = mahalanobis_sq(edge_residuals(graph.poses, graph.edge_nodes, graph.measurements), graph.information)
    assert torch.allclose(result.edge_chi2[~touches], before[~touches])


def test_window_without_older_edges_fixes_its_oldest_node():
    truth = circle_trajectory(10, laps=1)
    chain = PoseGraph.from_odometry(truth[:5], torch.eye(6, dtype=F64))
    island = PoseGraph.from_odometry(truth[5:], torch.eye(6, dtype=F64))
    graph = chain
    for k in range(5):
        graph = graph.add_node(island.poses[k])
    for e in range(island.num_edges):  # the island's own chain, offset by 5, and nothing joining the two
        i, j = island.edge_nodes[e].tolist()
        graph = graph.add_edge(i + 5, j + 5, island.measurements[e] @ se3_exp(torch.full((6,), 0.01, dtype=F64)),
                               island.information[e], "odometry")
    result = optimize_pose_graph_window(graph, PLAIN, 5)
    assert torch.equal(result.poses[:6], graph.poses[:6])  # node 5, the window's oldest, is the gauge
    assert result.problem_nodes == 5
