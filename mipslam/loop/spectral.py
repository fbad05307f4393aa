"""Spectral awareness for the pose graph (SA-PGO): edge coherence weights and low-frequency bases.

Two independent ingredients (docs/pgo.md gives the definitions and the reasoning):

1. :func:`spectral_coherence_weights` - the odometry chain's se(3) increments ``xi_k = Log(Z_k,k+1)``
   are a signal over the keyframe index. Camera motion is smooth, so its energy sits at low
   frequencies; odometry noise is close to white and spreads over the whole band. In a Hann
   window of W increments around edge k the power above a cut-off frequency estimates the local
   noise level, separately for translation and rotation. The coherence of edge k is the
   graph-wide median of that high-band power divided by the local one, clipped to
   ``[min_weight, 1]``; the edge information is scaled by it (noisy segments weigh less).

2. :func:`low_frequency_basis` - the K eigenvectors of the grounded graph Laplacian (gauge nodes
   removed, i.e. Dirichlet condition there) with the smallest eigenvalues. They are the smoothest
   functions on the keyframe graph that vanish at the gauge; accumulated drift is such a function,
   so the pose correction is sought as ``delta = U_K c`` (per-node 6-dof twists).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from mipslam.geometry import se3_log

# The dense eigen-solver is faster and exact below this many free nodes; above, shift-invert Lanczos.
_DENSE_EIGEN_MAX_NODES = 600


def _hann_high_band_power(signal: np.ndarray, window: int, cutoff: float) -> np.ndarray:
    """Mean power above ``cutoff`` (fraction of Nyquist) in a Hann window centred on every sample.

    signal [M, C] (reflect-padded at the ends) -> power [M] summed over the C channels, in the
    signal's squared units per sample (Parseval-normalised by the window energy).
    """
    m = signal.shape[0]
    half = window // 2
    padded = np.pad(signal, ((half, window - half), (0, 0)), mode="reflect") if m > 1 else np.repeat(signal, window + 1, 0)
    # windows[k] covers padded[k : k + window], centred on sample k
    idx = np.arange(m)[:, None] + np.arange(window)[None, :]
    segments = padded[idx]  # [M, W, C]
    segments = segments - segments.mean(axis=1, keepdims=True)
    hann = np.hanning(window + 2)[1:-1]  # strictly positive taps
    spectrum = np.fft.rfft(segments * hann[None, :, None], axis=1)  # [M, W/2+1, C]
    freqs = np.fft.rfftfreq(window)  # cycles per keyframe, Nyquist = 0.5
    high = freqs >= cutoff * 0.5
    if not high.any():
        high[-1] = True
    # Parseval: sum |X|^2 over the full band = W * sum (h x)^2; one-sided bins count twice (except DC/Nyquist)
    two_sided = np.where((freqs > 0) & (freqs < 0.5), 2.0, 1.0)
    power = (np.abs(spectrum[:, high, :]) ** 2 * two_sided[high][None, :, None]).sum(axis=(1, 2))
    return power / (window * (hann**2).sum())


def odometry_chain(edge_nodes: torch.Tensor, edge_is_loop: torch.Tensor) -> np.ndarray:
    """Indices of the odometry edges (i, i+1), sorted by i.  edge_nodes [E, 2], edge_is_loop [E] -> [M] int"""
    nodes = edge_nodes.cpu().numpy()
    is_loop = edge_is_loop.cpu().numpy()
    chain = np.flatnonzero(~is_loop & (nodes[:, 1] == nodes[:, 0] + 1))
    return chain[np.argsort(nodes[chain, 0], kind="stable")]


def spectral_coherence_weights(
    edge_nodes: torch.Tensor,
    measurements: torch.Tensor,
    edge_is_loop: torch.Tensor,
    window: int = 16,
    cutoff: float = 0.5,
    min_weight: float = 0.05,
) -> torch.Tensor:
    """Per-edge translation and rotation weights from the spectral coherence of the odometry chain.

    edge_nodes [E, 2], measurements [E, 4, 4] (Z_ij), edge_is_loop [E] -> weights [E, 2] float64
    (column 0 scales the translation block of the information, column 1 the rotation block, via
    ``Omega' = S Omega S`` with ``S = diag(sqrt(w_t) I3, sqrt(w_r) I3)``).

    For the consecutive odometry edges, split into runs of consecutive node indices, the
    increments ``xi_k = Log(Z_k)`` [M, 6] give the local high-band power ``P_t[k]`` (translation
    components) and ``P_r[k]`` (rotation) in a Hann window of ``window`` increments centred on k
    (frequencies >= ``cutoff`` x Nyquist). The weight is ``clip(median(P) / P[k], min_weight, 1)``.
    Loop edges and non-consecutive odometry edges keep weight 1 (their reliability is judged by
    registration and the robust kernel, not by the chain's smoothness). Runs shorter than 4 edges
    carry too little spectrum to judge and keep weight 1.
    """
    if window < 4:
        raise ValueError(f"spectral window must be >= 4 increments, got {window}")
    if not 0.0 < cutoff < 1.0:
        raise ValueError(f"spectral cutoff must lie in (0, 1) (fraction of Nyquist), got {cutoff}")
    num_edges = edge_nodes.shape[0]
    weights = np.ones((num_edges, 2))
    chain = odometry_chain(edge_nodes, edge_is_loop)
    if chain.size < 4:
        return torch.as_tensor(weights, dtype=torch.float64, device=measurements.device)
    increments = se3_log(measurements[torch.as_tensor(chain, device=measurements.device)]).cpu().numpy()  # [M, 6]
    first = edge_nodes[torch.as_tensor(chain, device=edge_nodes.device), 0].cpu().numpy()
    breaks = np.flatnonzero(np.diff(first) != 1) + 1
    power_t = np.full(chain.size, np.nan)
    power_r = np.full(chain.size, np.nan)
    for run in np.split(np.arange(chain.size), breaks):
        if run.size < 4:
            continue
        w = min(window, 2 * (run.size // 2))
        power_t[run] = _hann_high_band_power(increments[run, :3], w, cutoff)
        power_r[run] = _hann_high_band_power(increments[run, 3:], w, cutoff)
    for col, power in ((0, power_t), (1, power_r)):
        valid = np.isfinite(power)
        if not valid.any():
            continue
        reference = np.median(power[valid])
        tiny = np.finfo(np.float64).tiny
        ratio = np.where(valid, reference / np.maximum(power, tiny), 1.0)
        weights[chain, col] = np.clip(ratio, min_weight, 1.0) if reference > tiny else 1.0
    return torch.as_tensor(weights, dtype=torch.float64, device=measurements.device)


def scale_information(information: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Omega' = S Omega S, S = diag(sqrt(w_t) I3, sqrt(w_r) I3).  information [E, 6, 6], weights [E, 2] -> [E, 6, 6]"""
    s = torch.sqrt(weights).repeat_interleave(3, dim=1)  # [E, 6]
    return information * s[:, :, None] * s[:, None, :]


def graph_laplacian(num_nodes: int, edge_nodes: np.ndarray, edge_weights: np.ndarray | None = None) -> scipy.sparse.csr_matrix:
    """Combinatorial Laplacian L = D - A of an undirected graph (parallel edges add up).

    edge_nodes [E, 2] int, edge_weights [E] (default 1) -> sparse [N, N]
    """
    e = edge_nodes.shape[0]
    w = np.ones(e) if edge_weights is None else np.asarray(edge_weights, dtype=np.float64)
    i, j = edge_nodes[:, 0], edge_nodes[:, 1]
    adj = scipy.sparse.coo_matrix((np.r_[w, w], (np.r_[i, j], np.r_[j, i])), shape=(num_nodes, num_nodes)).tocsr()
    degree = np.asarray(adj.sum(axis=1)).ravel()
    return (scipy.sparse.diags(degree) - adj).tocsr()


def low_frequency_basis(
    num_nodes: int,
    edge_nodes: np.ndarray,
    num_eigenvectors: int,
    fixed_nodes: tuple[int, ...] = (0,),
) -> tuple[np.ndarray, np.ndarray]:
    """The ``num_eigenvectors`` smoothest modes of the grounded Laplacian.

    edge_nodes [E, 2] (the edges that define "neighbouring" keyframes) ->
    (basis U [N, K] with orthonormal columns and zero rows at ``fixed_nodes``, eigenvalues [K]).
    K is clipped to the number of free nodes; with K = free nodes U spans every correction, so the
    subspace problem equals the full one. Nodes without edges get their own (zero-eigenvalue) mode.
    """
    free = np.setdiff1d(np.arange(num_nodes), np.asarray(fixed_nodes, dtype=np.int64))
    k = int(min(max(num_eigenvectors, 1), free.size))
    basis = np.zeros((num_nodes, k))
    if k == 0:
        return basis, np.zeros(0)
    lap = graph_laplacian(num_nodes, edge_nodes)[free][:, free]
    if free.size <= _DENSE_EIGEN_MAX_NODES or k >= free.size // 2:
        # torch's LAPACK follows torch's thread setting (scipy's multi-threaded BLAS stalls on a busy machine)
        values_t, vectors_t = torch.linalg.eigh(torch.as_tensor(lap.toarray()))
        values, vectors = values_t[:k].numpy(), vectors_t[:, :k].numpy()
    else:
        # shift-invert around a point just below 0: the grounded Laplacian is positive semi-definite
        values, vectors = scipy.sparse.linalg.eigsh(lap.tocsc(), k=k, sigma=-1e-6, which="LM", tol=1e-10)
        order = np.argsort(values)
        values, vectors = values[order], vectors[:, order]
    basis[free] = vectors
    return basis, values
