"""SA-PGO spectral parts: coherence weights of the odometry chain, Laplacian bases, config mapping."""
from __future__ import annotations

from dataclasses import replace

import math

import numpy as np
import pytest
import torch

from mipslam.config import LoopConfig
from mipslam.loop.closer import LoopOptions
from mipslam.loop.pose_graph import PoseGraph
from mipslam.loop.solver import PGOOptions, optimize_pose_graph
from mipslam.loop.spectral import (
    graph_laplacian,
    low_frequency_basis,
    scale_information,
    spectral_coherence_weights,
)
from synthetic_pose_graphs import make_synthetic_pose_graph, trajectory_errors

F64 = torch.float64


def test_noisy_segments_get_low_weight_and_clean_ones_keep_theirs():
    syn = make_synthetic_pose_graph(200, laps=2, noisy_fraction=0.2, segment_noise_factor=5.0,
                                    segment_length=20, seed=11)
    g = syn.graph
    w = spectral_coherence_weights(g.edge_nodes, g.measurements, g.edge_is_loop, window=16)
    assert w.shape == (g.num_edges, 2)
    assert float(w.min()) >= 0.05 and float(w.max()) <= 1.0
    assert bool((w[g.edge_is_loop] == 1).all())  # loops keep their registration information
    noisy = torch.zeros(g.num_edges, dtype=torch.bool)
    noisy[list(syn.noisy_edges)] = True
    # away from the segment borders (the window straddles them) the separation is clear
    core = noisy.clone()
    for k in syn.noisy_edges:
        if k - 8 not in syn.noisy_edges or k + 8 not in syn.noisy_edges:
            core[k] = False
    clean = ~noisy & ~g.edge_is_loop
    for col in (0, 1):
        assert float(w[core, col].mean()) < 0.15  # true variance ratio is 1/25
        assert float(w[clean, col].median()) > 0.7


def test_uniform_noise_gives_near_uniform_weights():
    syn = make_synthetic_pose_graph(200, laps=2, seed=12)
    g = syn.graph
    w = spectral_coherence_weights(g.edge_nodes, g.measurements, g.edge_is_loop)
    odo = w[~g.edge_is_loop]
    assert float(odo.median()) == pytest.approx(1.0)  # the median edge is the reference
    assert float((odo > 0.4).float().mean()) > 0.9


def test_short_chains_and_validation():
    syn = make_synthetic_pose_graph(4, laps=1, seed=1)
    g = syn.graph
    assert bool((spectral_coherence_weights(g.edge_nodes, g.measurements, g.edge_is_loop) == 1).all())
    with pytest.raises(ValueError, match="window"):
        spectral_coherence_weights(g.edge_nodes, g.measurements, g.edge_is_loop, window=2)
    with pytest.raises(ValueError, match="cutoff"):
        spectral_coherence_weights(g.edge_nodes, g.measurements, g.edge_is_loop, cutoff=1.5)


def test_information_scaling_is_block_wise():
    info = torch.arange(36, dtype=F64).reshape(1, 6, 6) + 1
    w = torch.tensor([[0.25, 0.04]], dtype=F64)
    scaled = scale_information(info, w)
    assert torch.allclose(scaled[0, :3, :3], info[0, :3, :3] * 0.25)
    assert torch.allclose(scaled[0, 3:, 3:], info[0, 3:, 3:] * 0.04)
    assert torch.allclose(scaled[0, :3, 3:], info[0, :3, 3:] * 0.1)  # sqrt(0.25 * 0.04)


@pytest.mark.parametrize("num_nodes", [40, 900])  # dense and sparse (shift-invert) eigen-solvers
def test_grounded_path_laplacian_modes_match_the_analytic_spectrum(num_nodes):
    edges = np.stack([np.arange(num_nodes - 1), np.arange(1, num_nodes)], 1)
    U, values = low_frequency_basis(num_nodes, edges, 5)
    k = np.arange(1, 6)
    # path grounded at node 0: lambda_k = 2 - 2 cos((2k - 1) pi / (2N - 1))
    assert np.allclose(values, 2 - 2 * np.cos((2 * k - 1) * np.pi / (2 * num_nodes - 1)), atol=1e-10)
    assert np.allclose(U.T @ U, np.eye(5), atol=1e-9)
    assert np.all(U[0] == 0)
    lap = graph_laplacian(num_nodes, edges).toarray()
    assert np.allclose((lap @ U)[1:], U[1:] * values, atol=1e-9)  # eigen-equation on the free nodes
    # the first mode is the smooth, monotone drift-like shape
    first = U[:, 0] * np.sign(U[-1, 0])
    assert np.all(np.diff(first) >= -1e-12)


def test_basis_clips_to_the_free_nodes_and_handles_isolated_nodes():
    edges = np.array([[0, 1], [1, 2]])  # node 3 has no edge
    U, values = low_frequency_basis(4, edges, 10)
    assert U.shape == (4, 3)
    assert np.allclose(U.T @ U, np.eye(3), atol=1e-12)
    assert values[0] == pytest.approx(0.0, abs=1e-12)  # the isolated node is its own free mode


def test_spectral_weighting_helps_when_tracking_quality_varies():
    """Noisy segments (5x noise) with nominal information: the situation edge weighting is made for.

    The weighted solution must beat the plain one clearly and come close to the oracle that knows
    which edges are noisy (their information divided by 25)."""
    ate = {"plain": [], "weighted": [], "oracle": []}
    for seed in range(4):
        syn = make_synthetic_pose_graph(150, laps=2, noisy_fraction=0.25, segment_noise_factor=5.0, loop_every=25,
                                        seed=seed)
        g = syn.graph
        info = g.information.clone()
        info[list(syn.noisy_edges)] /= 25.0
        oracle = PoseGraph(g.poses, g.edge_nodes, g.measurements, info, g.edge_is_loop)
        for name, graph, options in (("plain", g, PGOOptions()), ("weighted", g, PGOOptions(spectral_edge_weighting=True)),
                                     ("oracle", oracle, PGOOptions())):
            poses = optimize_pose_graph(graph, options).poses
            ate[name].append(trajectory_errors(poses, syn.poses_true).translation_rmse_m)
    mean = {k: sum(v) / len(v) for k, v in ate.items()}
    assert mean["weighted"] < 0.6 * mean["plain"]
    assert mean["weighted"] < 1.25 * mean["oracle"]


def test_loop_options_map_onto_the_components_options():
    config = replace(LoopOptions.from_config(LoopConfig(fitness_threshold=0.4), depth_noise_power=2.0),
                     min_keyframe_gap=7, icp_rmse_threshold=0.03, spectral_edge_weighting=False,
                     low_frequency_correction=True, num_eigenvectors=5, full_iterations=2)
    pgo = config.pgo_options()
    assert (pgo.spectral_edge_weighting, pgo.low_frequency_correction, pgo.num_eigenvectors, pgo.full_iterations) == (
        False, True, 5, 2)
    assert config.candidate_options().min_gap == 7
    reg = config.registration_options()
    assert (reg.fitness_threshold, reg.rmse_threshold, reg.direct_depth_noise_power) == (0.4, 0.03, 2.0)
    assert not math.isnan(pgo.kernel_scale)
