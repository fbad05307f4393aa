"""Levenberg-Marquardt on SE(3) for the keyframe pose graph, with the SA-PGO extensions.

``optimize_pose_graph(graph, options) -> PGOResult`` minimises

    F(T) = sum_odometry  s_e  +  sum_loop  rho(s_e),      s_e = e_ij^T Omega'_ij e_ij,
    e_ij = Log(Z_ij^-1 T_i^-1 T_j),

over the free nodes (the gauge nodes, by default the first keyframe, stay exactly where they
are). ``Omega'`` is the edge information, optionally scaled by the spectral coherence weights
(:mod:`mipslam.loop.spectral`); ``rho`` is a robust kernel on loop edges. Each iteration
linearises with the analytic Jacobians (:func:`mipslam.loop.pose_graph.edge_jacobians`), builds
the sparse normal equations ``H = J^T W J``, ``b = J^T W e`` with IRLS weights
``W = rho'(s) Omega'`` (scipy.sparse), and solves ``(H + lambda diag(H)) delta = -b``. A step is
kept only if it lowers F (so F never increases); lambda follows Nielsen's rule.

With ``low_frequency_correction`` the update is ``delta = (U_K kron I6) c`` with U_K the K
smoothest modes of the grounded keyframe-graph Laplacian; LM runs on the 6K coefficients c
(dense 6K x 6K system ``B^T H B``), then ``full_iterations`` plain LM iterations follow.

After convergence (an unconverged subspace + few-full-iterations result is first run to
convergence), loop edges whose chi-square ``e^T Omega e`` (raw information) exceeds both
``prune_chi2`` and ``prune_median_factor`` x the median over the kept loops disagree with the
rest of the graph: they are pruned and the optimisation continues from the current poses without
them (at most ``max_prune_rounds`` times).
All arithmetic is float64 on the CPU (torch for the per-edge algebra, numpy/scipy for the
sparse linear algebra); the poses come back on the graph's device.
"""
from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from mipslam.loop.pose_graph import (
    PoseGraph,
    RobustKernel,
    edge_jacobians,
    edge_residuals,
    mahalanobis_sq,
    perturb_left,
    robust_cost,
    robust_weight,
)
from mipslam.loop.spectral import low_frequency_basis, scale_information, spectral_coherence_weights

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class PGOOptions:
    """Settings of :func:`optimize_pose_graph` (plain full LM with the defaults of the switches off).

    robust_kernel / kernel_scale: kernel on loop edges, scale in chi-square units (6 dof).
    prune_chi2 / prune_median_factor: after convergence a loop edge is pruned when its e^T Omega e
        exceeds both prune_chi2 and prune_median_factor x the median over the kept loop edges (the
        relative test keeps correct loops when the stated information is too optimistic overall);
        prune_chi2=None never prunes.
    spectral_*: see :func:`mipslam.loop.spectral.spectral_coherence_weights`.
    laplacian_edges: which edges define graph neighbours for the low-frequency basis: "odometry"
        (the keyframe chain; drift is smooth along it) or "all" (loops too).
    """

    max_iterations: int = 100
    subspace_iterations: int = 20  # cap of the low-frequency (subspace) stage
    subspace_relative_tolerance: float = 1e-4  # the coarse stage stops earlier (IRLS converges linearly there)
    relative_tolerance: float = 1e-6  # stop when an accepted step lowers F by less than this fraction
    step_tolerance: float = 1e-10  # stop when the update's largest entry is below this
    initial_lambda: float = 1e-5
    fixed_nodes: tuple[int, ...] = (0,)
    robust_kernel: RobustKernel = "cauchy"
    kernel_scale: float = 12.6  # chi-square(6) 95% quantile
    prune_chi2: float | None = 100.0
    prune_median_factor: float = 10.0  # ... and above this many times the median loop chi-square
    max_prune_rounds: int = 3
    spectral_edge_weighting: bool = False
    spectral_window: int = 16
    spectral_cutoff: float = 0.5
    spectral_min_weight: float = 0.05
    low_frequency_correction: bool = False
    num_eigenvectors: int = 16
    full_iterations: int = 3
    laplacian_edges: Literal["odometry", "all"] = "odometry"
    single_thread: bool = True  # run torch single-threaded during the call (see optimize_pose_graph)

    def __post_init__(self):
        if self.max_iterations < 0 or self.full_iterations < 0:
            raise ValueError("PGOOptions: iteration counts must be >= 0")
        if self.kernel_scale <= 0:
            raise ValueError(f"PGOOptions.kernel_scale must be positive, got {self.kernel_scale}")
        if self.num_eigenvectors < 1:
            raise ValueError(f"PGOOptions.num_eigenvectors must be >= 1, got {self.num_eigenvectors}")
        if self.laplacian_edges not in ("odometry", "all"):
            raise ValueError(f"PGOOptions.laplacian_edges must be 'odometry' or 'all', got {self.laplacian_edges!r}")
        if not self.fixed_nodes:
            raise ValueError("PGOOptions.fixed_nodes needs at least one gauge node")


@dataclass(frozen=True)
class PGOResult:
    """Outcome of :func:`optimize_pose_graph`.

    poses: optimised T_wc (the graph's device, float64)                         # [N, 4, 4]
    initial_cost / final_cost: F at the initial and the final poses, each on the edges kept in the
        end (pruned loops excluded), with the same weights and kernel, so the two compare.
    cost_history: F after every accepted step of the last round (first entry: initial poses)
    iterations: LM iterations of all rounds (subspace + full); subspace_iterations: of those, in the subspace
    pruned_edges: indices (into the input graph's edges) of the loop edges pruned, in pruning order
    loop_weights: final IRLS weight rho'(s) of every input edge (1 for odometry, 0 for pruned)  # [E]
    edge_chi2: final e^T Omega e of every input edge with its raw information                  # [E]
    spectral_weights: translation/rotation information scales (all 1 when switched off)       # [E, 2]
    converged: the full problem's LM stopped on a tolerance in the last round (False after a
        subspace-only stage or on the iteration cap)
    time_s: wall-clock seconds of the whole call
    """

    poses: torch.Tensor
    initial_cost: float
    final_cost: float
    cost_history: tuple[float, ...]
    iterations: int
    subspace_iterations: int
    pruned_edges: tuple[int, ...]
    loop_weights: torch.Tensor
    edge_chi2: torch.Tensor
    spectral_weights: torch.Tensor
    converged: bool
    time_s: float
    num_eigenvectors_used: int = 0
    notes: tuple[str, ...] = field(default_factory=tuple)
    problem_nodes: int = 0  # nodes in the solved problem (all of them, or a window and its fixed border)
    problem_edges: int = 0  # edges in the solved problem


@dataclass(frozen=True)
class _BlockPattern:
    """Sparsity pattern of H for a fixed edge set, built once per problem: every COO entry's slot
    in the CSC data array, so each iteration only sums values (no sorting, no duplicates)."""

    slot: np.ndarray  # [4 E 36 + fixed dofs] -> index into data
    indices: np.ndarray  # CSC row indices [nnz]
    indptr: np.ndarray  # CSC column pointers [6N + 1]
    i6: np.ndarray  # [E, 6] dof indices of node i
    j6: np.ndarray  # [E, 6] dof indices of node j
    num_fixed_dofs: int
    size: int  # 6N

    @staticmethod
    def build(edge_nodes: np.ndarray, num_nodes: int, fixed_mask: np.ndarray) -> "_BlockPattern":
        i6 = edge_nodes[:, 0][:, None] * 6 + np.arange(6)[None, :]  # [E, 6]
        j6 = edge_nodes[:, 1][:, None] * 6 + np.arange(6)[None, :]
        rows = np.stack([np.broadcast_to(r[:, :, None], r.shape + (6,)) for r in (i6, i6, j6, j6)])  # [4, E, 6, 6]
        cols = np.stack([np.broadcast_to(c[:, None, :], c.shape[:1] + (6, 6)) for c in (i6, j6, i6, j6)])
        fixed_dofs = np.flatnonzero(np.repeat(fixed_mask, 6))
        n6 = 6 * num_nodes
        key = np.concatenate([cols.ravel(), fixed_dofs]).astype(np.int64) * n6 + np.concatenate([rows.ravel(), fixed_dofs])
        unique, slot = np.unique(key, return_inverse=True)
        column = unique // n6
        return _BlockPattern(slot=slot.ravel(), indices=(unique % n6).astype(np.int32),
                             indptr=np.searchsorted(column, np.arange(n6 + 1)).astype(np.int32),
                             i6=i6, j6=j6, num_fixed_dofs=fixed_dofs.size, size=n6)


@dataclass(frozen=True)
class _Problem:
    """The fixed objective of one LM run (CPU float64)."""

    edge_nodes: torch.Tensor  # [E, 2]
    measurements: torch.Tensor  # [E, 4, 4]
    information: torch.Tensor  # [E, 6, 6] (spectrally scaled where asked)
    edge_is_loop: torch.Tensor  # [E]
    num_nodes: int
    fixed_mask: np.ndarray  # [N] bool
    kernel: RobustKernel
    kernel_scale: float
    pattern: _BlockPattern = field(init=False)
    free_i: torch.Tensor = field(init=False)  # [E, 1, 1] 0 where node i is a gauge node
    free_j: torch.Tensor = field(init=False)

    def __post_init__(self):
        nodes = self.edge_nodes.numpy()
        object.__setattr__(self, "pattern", _BlockPattern.build(nodes, self.num_nodes, self.fixed_mask))
        object.__setattr__(self, "free_i", torch.as_tensor(~self.fixed_mask[nodes[:, 0]], dtype=torch.float64)[:, None, None])
        object.__setattr__(self, "free_j", torch.as_tensor(~self.fixed_mask[nodes[:, 1]], dtype=torch.float64)[:, None, None])

    def evaluate(self, poses: torch.Tensor) -> tuple[float, torch.Tensor, torch.Tensor]:
        """(F, residuals [E, 6], s [E]) at ``poses`` [N, 4, 4]."""
        res = edge_residuals(poses, self.edge_nodes, self.measurements)
        s = mahalanobis_sq(res, self.information)
        rho = torch.where(self.edge_is_loop, robust_cost(s, self.kernel, self.kernel_scale), s)
        return float(rho.sum()), res, s

    def weights(self, s: torch.Tensor) -> torch.Tensor:
        return torch.where(self.edge_is_loop, robust_weight(s, self.kernel, self.kernel_scale), torch.ones_like(s))


def _normal_equations(problem: _Problem, poses: torch.Tensor, residuals: torch.Tensor, s: torch.Tensor):
    """Sparse H = J^T W J [6N, 6N] (CSC) and dense b = J^T W e [6N]; gauge nodes' columns are zero."""
    J_i, J_j = edge_jacobians(poses, problem.edge_nodes, residuals)  # [E, 6, 6] each
    W = problem.weights(s)[:, None, None] * problem.information  # [E, 6, 6]
    J_i, J_j = J_i * problem.free_i, J_j * problem.free_j
    WJ_i, WJ_j = W @ J_i, W @ J_j
    JiT, JjT = J_i.transpose(1, 2), J_j.transpose(1, 2)
    blocks = torch.stack([JiT @ WJ_i, JiT @ WJ_j, JjT @ WJ_i, JjT @ WJ_j]).numpy()  # [4, E, 6, 6]
    We = W @ residuals[:, :, None]  # [E, 6, 1]
    b_i, b_j = (JiT @ We)[..., 0].numpy(), (JjT @ We)[..., 0].numpy()
    pattern = problem.pattern
    values = np.concatenate([blocks.ravel(), np.ones(pattern.num_fixed_dofs)])
    data = np.bincount(pattern.slot, weights=values, minlength=pattern.indices.size)
    H = scipy.sparse.csc_matrix((data, pattern.indices, pattern.indptr), shape=(pattern.size, pattern.size))
    b = np.bincount(np.r_[pattern.i6.ravel(), pattern.j6.ravel()], weights=np.r_[b_i.ravel(), b_j.ravel()],
                    minlength=pattern.size)
    return H, b


def _levenberg_marquardt(
    problem: _Problem,
    poses: torch.Tensor,
    max_iterations: int,
    options: PGOOptions,
    basis: np.ndarray | None = None,
    relative_tolerance: float | None = None,
) -> tuple[torch.Tensor, list[float], int, bool]:
    """Run LM from ``poses`` [N, 4, 4]; ``basis`` [N, K] restricts the update to ``(U kron I6) c``.

    Returns (poses, accepted costs (first = start), iterations, converged).
    """
    tolerance = options.relative_tolerance if relative_tolerance is None else relative_tolerance
    cost, res, s = problem.evaluate(poses)
    history = [cost]
    lam, nu = options.initial_lambda, 2.0
    # B = U kron I6 [6N, 6K], kept sparse and dense: both projections run in scipy.sparse's
    # single-threaded kernels (multi-threaded BLAS stalls on a busy machine for these sizes)
    if basis is not None:
        B = scipy.sparse.kron(scipy.sparse.csr_matrix(basis), scipy.sparse.identity(6), format="csr")
        B_dense = B.toarray()
    else:
        B = B_dense = None
    converged = False
    iterations = 0
    need_linearisation = True
    for iterations in range(1, max_iterations + 1):
        if need_linearisation:
            H, b = _normal_equations(problem, poses, res, s)
            if B is not None:
                Hc, bc = B.T @ (H.tocsr() @ B_dense), B.T @ b
                diag = np.maximum(np.diag(Hc), 1e-12)
            else:
                diag = np.maximum(H.diagonal(), 1e-12)
            need_linearisation = False
        if B is not None:
            # small dense SPD system; torch's LAPACK follows torch's thread setting (scipy's BLAS would not)
            damped_c = torch.as_tensor(Hc + lam * np.diag(diag))
            chol, info = torch.linalg.cholesky_ex(damped_c)
            if int(info) != 0:
                lam *= nu
                nu *= 2.0
                continue
            c = torch.cholesky_solve(torch.as_tensor(-bc)[:, None], chol)[:, 0].numpy()
            step = B @ c
            predicted = -(c @ bc) * 2 - c @ (Hc @ c)
        else:
            damped = (H + scipy.sparse.diags(lam * diag)).tocsc()
            # symmetric positive definite: minimum-degree ordering on A + A^T, no pivoting
            factor = scipy.sparse.linalg.splu(damped, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                              options=dict(SymmetricMode=True))
            step = factor.solve(-b)
            predicted = -(step @ b) * 2 - step @ (H @ step)
        if not np.all(np.isfinite(step)):
            logger.warning("pose-graph LM: non-finite step (lambda=%.3g); stopping", lam)
            break
        step_t = torch.as_tensor(step.reshape(-1, 6))
        candidate = perturb_left(poses, step_t)
        new_cost, new_res, new_s = problem.evaluate(candidate)
        actual = cost - new_cost
        if np.isfinite(new_cost) and actual > 0:
            gain = actual / max(predicted, 1e-300)
            poses, res, s = candidate, new_res, new_s
            relative = actual / max(cost, 1e-300)
            cost = new_cost
            history.append(cost)
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
            nu = 2.0
            need_linearisation = True
            if relative < tolerance or np.abs(step).max() < options.step_tolerance:
                converged = True
                break
        else:
            if np.abs(step).max() < options.step_tolerance:
                converged = True
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e12:
                converged = True  # no descent direction left at machine precision
                break
    return poses, history, iterations, converged


def _solve_round(problem: _Problem, poses0: torch.Tensor, options: PGOOptions, basis: np.ndarray | None):
    """One optimisation: subspace LM then full LM (or full LM alone).

    Returns (poses, history, iterations, subspace iterations, converged); ``converged`` means the
    full (not the subspace) problem converged, so it is False after a subspace-only stage.
    """
    if basis is not None:
        poses, hist, it_sub, _ = _levenberg_marquardt(problem, poses0, options.subspace_iterations, options, basis,
                                                      options.subspace_relative_tolerance)
        it_full, conv = 0, False
        if options.full_iterations > 0:
            poses, hist_full, it_full, conv = _levenberg_marquardt(problem, poses, options.full_iterations, options)
            hist = hist + hist_full[1:]
        return poses, hist, it_sub + it_full, it_sub, conv
    poses, hist, it, conv = _levenberg_marquardt(problem, poses0, options.max_iterations, options)
    return poses, hist, it, 0, conv


@contextlib.contextmanager
def _torch_threads(count: int | None):
    """Temporarily set torch's intra-op thread count (restored on exit); None leaves it alone."""
    previous = torch.get_num_threads()
    if count is not None and count != previous:
        torch.set_num_threads(count)
    try:
        yield
    finally:
        if torch.get_num_threads() != previous:
            torch.set_num_threads(previous)


def optimize_pose_graph(graph: PoseGraph, options: PGOOptions = PGOOptions()) -> PGOResult:
    """Optimise the keyframe poses of ``graph`` (SA-PGO; plain LM with the switches off).

    Returns a :class:`PGOResult`; the input graph is not modified (use ``graph.with_poses``).
    With ``options.single_thread`` (default) torch runs on one intra-op thread during the call and
    the previous setting is restored afterwards: the per-edge algebra is many small tensors, which
    gain nothing from a second thread and, on a busy 2-core machine, stall at every op's thread
    barrier (1000 nodes: 5.2 s with 2 threads against 1.0 s with 1, measured under load).
    """
    with _torch_threads(1 if options.single_thread else None):
        return _optimize_pose_graph(graph, options)


def _optimize_pose_graph(graph: PoseGraph, options: PGOOptions) -> PGOResult:
    start = time.perf_counter()
    n, e = graph.num_nodes, graph.num_edges
    fixed = np.zeros(n, dtype=bool)
    for k in options.fixed_nodes:
        if not 0 <= k < n:
            raise ValueError(f"gauge node {k} is not in the graph (it has {n} nodes)")
        fixed[k] = True
    cpu = dict(dtype=torch.float64, device="cpu")
    poses0 = graph.poses.to(**cpu)
    edge_nodes = graph.edge_nodes.cpu()
    measurements = graph.measurements.to(**cpu)
    info_raw = graph.information.to(**cpu)
    is_loop = graph.edge_is_loop.cpu()

    if options.spectral_edge_weighting:
        spectral = spectral_coherence_weights(edge_nodes, measurements, is_loop, options.spectral_window,
                                              options.spectral_cutoff, options.spectral_min_weight)
    else:
        spectral = torch.ones(e, 2, **cpu)
    info = scale_information(info_raw, spectral)

    basis = None
    k_used = 0
    if options.low_frequency_correction and n > 1:
        lap_edges = edge_nodes if options.laplacian_edges == "all" else edge_nodes[~is_loop]
        basis, _ = low_frequency_basis(n, lap_edges.numpy(), options.num_eigenvectors, tuple(np.flatnonzero(fixed)))
        k_used = basis.shape[1]

    keep = torch.ones(e, dtype=torch.bool)
    pruned: list[int] = []
    total_it = total_sub = 0
    notes: list[str] = []
    poses = poses0
    for round_index in range(options.max_prune_rounds + 1):
        problem = _Problem(edge_nodes[keep], measurements[keep], info[keep], is_loop[keep], n, fixed,
                           options.robust_kernel, options.kernel_scale)
        # later rounds start from the previous solution: the kernel has already discounted the
        # pruned edges, so the poses are close to the new optimum
        poses, history, it, it_sub, converged = _solve_round(problem, poses, options, basis)
        total_it += it
        total_sub += it_sub
        if options.prune_chi2 is None or round_index == options.max_prune_rounds:
            break
        if not converged and basis is not None:
            # a loop is judged only against a converged full solution: the subspace stage and the few
            # full iterations after it may leave correct loops with large residuals
            poses, hist_more, it_more, converged = _levenberg_marquardt(problem, poses, options.max_iterations, options)
            history = history + hist_more[1:]
            total_it += it_more
        chi2 = mahalanobis_sq(edge_residuals(poses, edge_nodes, measurements), info_raw)
        kept_loops = keep & is_loop
        if not bool(kept_loops.any()):
            break
        threshold = max(options.prune_chi2, options.prune_median_factor * float(chi2[kept_loops].median()))
        bad = torch.nonzero(kept_loops & (chi2 > threshold)).ravel()
        if bad.numel() == 0:
            break
        order = bad[torch.argsort(chi2[bad], descending=True)].tolist()
        pruned.extend(order)
        keep[bad] = False
        notes.append(f"round {round_index}: pruned loop edges {order} (chi2 > {threshold:.4g})")
        logger.info("pose graph: pruned %d loop edge(s) %s (chi2 > %.4g); re-optimising", len(order), order, threshold)

    final_problem = _Problem(edge_nodes[keep], measurements[keep], info[keep], is_loop[keep], n, fixed,
                             options.robust_kernel, options.kernel_scale)
    initial_cost = final_problem.evaluate(poses0)[0]
    final_cost, _, s_kept = final_problem.evaluate(poses)
    weights = torch.zeros(e, **cpu)
    weights[keep] = final_problem.weights(s_kept)
    chi2 = mahalanobis_sq(edge_residuals(poses, edge_nodes, measurements), info_raw)
    return PGOResult(
        poses=poses.to(graph.device),
        initial_cost=initial_cost,
        final_cost=final_cost,
        cost_history=tuple(history),
        iterations=total_it,
        subspace_iterations=total_sub,
        pruned_edges=tuple(pruned),
        loop_weights=weights,
        edge_chi2=chi2,
        spectral_weights=spectral,
        converged=converged,
        time_s=time.perf_counter() - start,
        num_eigenvectors_used=k_used,
        notes=tuple(notes),
        problem_nodes=n,
        problem_edges=e,
    )


def optimize_pose_graph_window(graph: PoseGraph, options: PGOOptions, window: int) -> PGOResult:
    """:func:`optimize_pose_graph` over the ``window`` newest nodes only, so that its cost stops
    growing with the graph (the working-memory idea of RTAB-Map).

    Free: nodes ``N - window .. N - 1``. Fixed: every older node that shares an edge with a free
    one (the odometry predecessor of the window and the old ends of its loop edges), which anchor
    the window to the rest of the map and fix the gauge. Left out: every other node and every
    edge between two older nodes; their poses come back unchanged. A revisit then moves the new
    keyframes onto the old map instead of bending the whole history. ``window <= 0``, or a window
    that holds every node, is the plain whole-graph optimisation.

    The result is in the input graph's indices: ``pruned_edges``, ``loop_weights`` and
    ``spectral_weights`` of edges outside the problem are (none), 1 and 1; ``edge_chi2`` is
    evaluated on every edge; ``initial_cost``/``final_cost`` are those of the window's problem.
    """
    n = graph.num_nodes
    first_free = n - window
    if window <= 0 or first_free <= 0:
        return optimize_pose_graph(graph, options)
    start = time.perf_counter()
    edge_nodes = graph.edge_nodes.cpu()
    in_problem = (edge_nodes >= first_free).any(dim=1)  # [E] edges with a free end
    edge_index = torch.nonzero(in_problem).ravel()  # [E'] into the input graph
    nodes = torch.unique(torch.cat([torch.arange(first_free, n), edge_nodes[in_problem].ravel()]))  # sorted [N']
    local = torch.full((n,), -1, dtype=torch.int64)
    local[nodes] = torch.arange(nodes.numel())
    fixed = [int(local[k]) for k in nodes.tolist() if k < first_free]
    fixed += [int(local[k]) for k in options.fixed_nodes if first_free <= k < n]
    if not fixed:  # a window with no edge to older nodes: its oldest node fixes the gauge
        fixed = [int(local[first_free])]
    device = graph.device
    kept = graph.select_edges(in_problem.to(device))
    sub = PoseGraph(graph.poses[nodes.to(device)], local[edge_nodes[in_problem]].to(device), kept.measurements,
                    kept.information, kept.edge_is_loop)
    result = optimize_pose_graph(sub, replace(options, fixed_nodes=tuple(sorted(set(fixed)))))

    cpu = dict(dtype=torch.float64, device="cpu")
    poses = graph.poses.to(**cpu).clone()
    poses[nodes] = result.poses.to(**cpu)
    e = graph.num_edges
    loop_weights = torch.ones(e, **cpu)
    loop_weights[edge_index] = result.loop_weights.to(**cpu)
    spectral = torch.ones(e, 2, **cpu)
    spectral[edge_index] = result.spectral_weights.to(**cpu)
    chi2 = mahalanobis_sq(edge_residuals(poses, edge_nodes, graph.measurements.to(**cpu)), graph.information.to(**cpu))
    note = (f"window: {window} newest of {n} nodes free, {len(fixed)} older fixed; "
            f"{edge_index.numel()} of {e} edges")
    return replace(result, poses=poses.to(device), pruned_edges=tuple(int(edge_index[i]) for i in result.pruned_edges),
                   loop_weights=loop_weights, edge_chi2=chi2, spectral_weights=spectral,
                   time_s=time.perf_counter() - start, notes=(note, *result.notes))
