"""The keyframe pose graph: storage, residuals, analytic Jacobians and robust kernels.

Representation (all torch float64 on the caller's device; the solver works on CPU copies):

* node ``k``: a keyframe pose ``T_wc[k]`` (camera to world, 4x4);
* edge ``(i, j)``: a measured relative pose ``Z_ij ~ T_i^-1 T_j`` (maps camera-j points into
  camera i), a 6x6 information matrix in the twist order ``[rho, phi]`` (translation first,
  docs/design.md), and a kind (odometry or loop).

Residual (docs/design.md): ``e_ij = Log(Z_ij^-1 T_i^-1 T_j)``, a twist ``[rho, phi]`` expressed in
camera j's frame. Poses are updated on the left (world frame), ``T_k <- Exp(delta_k) T_k``, so
a correction is a world-frame twist per node. With ``E = Z_ij^-1 T_i^-1 T_j``:

    d e / d delta_j = J_r^-1(e) Ad(T_j^-1)          d e / d delta_i = -J_r^-1(e) Ad(T_j^-1)

(``J_r`` is the right Jacobian of SE(3), Barfoot 2017 eq. 7.83-7.86; ``Ad(T) = [[R, t^ R],
[0, R]]`` for the ``[rho, phi]`` order). Robust kernels act on the squared Mahalanobis norm
``s = e^T Omega e`` (a chi-square with 6 degrees of freedom for a correct edge).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Sequence

import torch

from mipslam.errors import CheckpointError
from mipslam.geometry import hat, se3_exp, se3_inverse, se3_log

EdgeKind = Literal["odometry", "loop"]
RobustKernel = Literal["none", "cauchy", "geman_mcclure"]

# Below this squared angle the SE(3) Jacobian coefficients use their Taylor series: the closed
# forms lose digits to cancellation (their numerators vanish like theta^4 and theta^5).
_JACOBIAN_TAYLOR_THETA_SQ = 1e-2


@dataclass(frozen=True)
class PoseGraph:
    """Keyframe poses and relative-pose constraints between them (immutable; ``with_*`` copy).

    poses:        camera-to-world keyframe poses T_wc, float64                 # [N, 4, 4]
    edge_nodes:   (i, j) node indices of every edge, int64                      # [E, 2]
    measurements: measured relative poses Z_ij ~ T_i^-1 T_j, float64           # [E, 4, 4]
    information:  information of e_ij in the order [rho, phi], float64         # [E, 6, 6]
    edge_is_loop: True for loop-closure edges, False for odometry               # [E]
    """

    poses: torch.Tensor
    edge_nodes: torch.Tensor
    measurements: torch.Tensor
    information: torch.Tensor
    edge_is_loop: torch.Tensor

    def __post_init__(self):
        n, e = self.poses.shape[0], self.edge_nodes.shape[0]
        if self.poses.shape != (n, 4, 4) or self.poses.dtype != torch.float64:
            raise ValueError(f"PoseGraph.poses must be float64 [N, 4, 4], got {self.poses.dtype} {tuple(self.poses.shape)}")
        if self.edge_nodes.shape != (e, 2) or self.edge_nodes.dtype != torch.int64:
            raise ValueError(f"PoseGraph.edge_nodes must be int64 [E, 2], got {self.edge_nodes.dtype} {tuple(self.edge_nodes.shape)}")
        if self.measurements.shape != (e, 4, 4) or self.measurements.dtype != torch.float64:
            raise ValueError(f"PoseGraph.measurements must be float64 [E, 4, 4], got {tuple(self.measurements.shape)}")
        if self.information.shape != (e, 6, 6) or self.information.dtype != torch.float64:
            raise ValueError(f"PoseGraph.information must be float64 [E, 6, 6], got {tuple(self.information.shape)}")
        if self.edge_is_loop.shape != (e,) or self.edge_is_loop.dtype != torch.bool:
            raise ValueError(f"PoseGraph.edge_is_loop must be bool [E], got {tuple(self.edge_is_loop.shape)}")
        if e and (int(self.edge_nodes.min()) < 0 or int(self.edge_nodes.max()) >= n):
            raise ValueError(f"PoseGraph edge refers to a node outside [0, {n}); nodes must be added before their edges")
        if e and bool((self.edge_nodes[:, 0] == self.edge_nodes[:, 1]).any()):
            raise ValueError("PoseGraph edge connects a node to itself; an edge needs two different keyframes")

    # ------------------------------------------------------------------ construction
    @staticmethod
    def empty(device: torch.device | str = "cpu") -> "PoseGraph":
        """A graph without nodes or edges (float64 on ``device``)."""
        f64 = dict(dtype=torch.float64, device=device)
        return PoseGraph(
            poses=torch.zeros(0, 4, 4, **f64),
            edge_nodes=torch.zeros(0, 2, dtype=torch.int64, device=device),
            measurements=torch.zeros(0, 4, 4, **f64),
            information=torch.zeros(0, 6, 6, **f64),
            edge_is_loop=torch.zeros(0, dtype=torch.bool, device=device),
        )

    @staticmethod
    def from_odometry(poses: torch.Tensor, information: torch.Tensor) -> "PoseGraph":
        """A chain whose edges are the relative poses between consecutive keyframes.

        poses: T_wc of the keyframes                                  # [N, 4, 4]
        information: per edge [N-1, 6, 6] or one shared [6, 6], order [rho, phi]
        """
        poses = poses.to(torch.float64)
        n = poses.shape[0]
        info = information.to(dtype=torch.float64, device=poses.device)
        if info.dim() == 2:
            info = info.expand(max(n - 1, 0), 6, 6).clone()
        idx = torch.arange(max(n - 1, 0), device=poses.device)
        return PoseGraph(
            poses=poses.clone(),
            edge_nodes=torch.stack([idx, idx + 1], -1),
            measurements=se3_inverse(poses[:-1]) @ poses[1:],
            information=info,
            edge_is_loop=torch.zeros(max(n - 1, 0), dtype=torch.bool, device=poses.device),
        )

    @property
    def num_nodes(self) -> int:
        return int(self.poses.shape[0])

    @property
    def num_edges(self) -> int:
        return int(self.edge_nodes.shape[0])

    @property
    def device(self) -> torch.device:
        return self.poses.device

    def add_node(self, T_wc: torch.Tensor) -> "PoseGraph":
        """A copy with one more node (its index is the old ``num_nodes``).  T_wc [4, 4]"""
        T = T_wc.to(dtype=torch.float64, device=self.device).reshape(1, 4, 4)
        return PoseGraph(torch.cat([self.poses, T]), self.edge_nodes, self.measurements, self.information, self.edge_is_loop)

    def add_edge(self, i: int, j: int, T_ij: torch.Tensor, information: torch.Tensor, kind: EdgeKind) -> "PoseGraph":
        """A copy with one more edge measuring ``T_i^-1 T_j``.

        T_ij: measured relative pose (camera j to camera i)       # [4, 4]
        information: inverse covariance of e_ij, order [rho, phi]  # [6, 6]
        kind: "odometry" (trusted) or "loop" (robust kernel, may be pruned)
        """
        if kind not in ("odometry", "loop"):
            raise ValueError(f"edge kind must be 'odometry' or 'loop', got {kind!r}")
        dev = self.device
        return PoseGraph(
            self.poses,
            torch.cat([self.edge_nodes, torch.tensor([[int(i), int(j)]], dtype=torch.int64, device=dev)]),
            torch.cat([self.measurements, T_ij.to(dtype=torch.float64, device=dev).reshape(1, 4, 4)]),
            torch.cat([self.information, information.to(dtype=torch.float64, device=dev).reshape(1, 6, 6)]),
            torch.cat([self.edge_is_loop, torch.tensor([kind == "loop"], device=dev)]),
        )

    def with_poses(self, poses: torch.Tensor) -> "PoseGraph":
        """The same edges on new node poses.  poses [N, 4, 4]"""
        return PoseGraph(poses.to(dtype=torch.float64, device=self.device), self.edge_nodes, self.measurements,
                         self.information, self.edge_is_loop)

    def without_edges(self, edge_indices: Sequence[int]) -> "PoseGraph":
        """A copy without the listed edges (e.g. pruned loop closures)."""
        keep = torch.ones(self.num_edges, dtype=torch.bool, device=self.device)
        if len(edge_indices):
            keep[torch.as_tensor(list(edge_indices), dtype=torch.int64, device=self.device)] = False
        return self.select_edges(keep)

    def select_edges(self, keep: torch.Tensor) -> "PoseGraph":
        """A copy with only the edges where ``keep`` is True.  keep [E] bool"""
        return PoseGraph(self.poses, self.edge_nodes[keep], self.measurements[keep], self.information[keep],
                         self.edge_is_loop[keep])

    # ------------------------------------------------------------------ checkpointing
    def state_dict(self) -> dict[str, torch.Tensor]:
        """Plain tensors only (loadable with ``torch.load(..., weights_only=True)``)."""
        return {
            "poses": self.poses.detach().cpu().clone(),
            "edge_nodes": self.edge_nodes.detach().cpu().clone(),
            "measurements": self.measurements.detach().cpu().clone(),
            "information": self.information.detach().cpu().clone(),
            "edge_is_loop": self.edge_is_loop.detach().cpu().clone(),
        }

    @staticmethod
    def from_state_dict(state: dict, device: torch.device | str = "cpu") -> "PoseGraph":
        """Inverse of :meth:`state_dict`; raises CheckpointError on a malformed entry."""
        keys = ("poses", "edge_nodes", "measurements", "information", "edge_is_loop")
        missing = [k for k in keys if k not in state]
        if missing:
            raise CheckpointError(f"pose graph in checkpoint lacks {missing}; the checkpoint is incomplete, start a new run")
        try:
            return PoseGraph(*(torch.as_tensor(state[k]).to(device) for k in keys))
        except ValueError as err:
            raise CheckpointError(f"pose graph in checkpoint is malformed ({err}); start a new run") from err


# ---------------------------------------------------------------------------- SE(3) Jacobians
def adjoint(T: torch.Tensor) -> torch.Tensor:
    """Adjoint of SE(3) for twists ``[rho, phi]``: ``T Exp(xi) T^-1 = Exp(Ad(T) xi)``.

    T [..., 4, 4] -> [..., 6, 6] = [[R, t^ R], [0, R]]
    """
    R, t = T[..., :3, :3], T[..., :3, 3]
    top = torch.cat([R, hat(t) @ R], -1)
    bottom = torch.cat([torch.zeros_like(R), R], -1)
    return torch.cat([top, bottom], -2)


def _so3_left_jacobian_inverse(phi: torch.Tensor) -> torch.Tensor:
    """J_l^-1(phi) = I - phi^/2 + D phi^2, D = 1/theta^2 - (1 + cos)/(2 theta sin).  [..., 3] -> [..., 3, 3]"""
    theta2 = (phi * phi).sum(-1)
    small = theta2 < _JACOBIAN_TAYLOR_THETA_SQ
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    # (1 - A / (2B)) / theta^2 with A = sin/t, B = (1-cos)/t^2: stable up to theta -> pi.
    closed = (1 - t * torch.sin(t) / (2 * (1 - torch.cos(t)))) / t2
    d = torch.where(small, 1.0 / 12 + theta2 / 720 + theta2**2 / 30240 + theta2**3 / 1209600, closed)
    k = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(k.shape)
    return eye - 0.5 * k + d[..., None, None] * (k @ k)


def _se3_q_matrix(rho: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Upper-right block Q(rho, phi) of the SE(3) left Jacobian (Barfoot 2017, eq. 7.86).  -> [..., 3, 3]"""
    theta2 = (phi * phi).sum(-1)
    small = theta2 < _JACOBIAN_TAYLOR_THETA_SQ
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    s, c = torch.sin(t), torch.cos(t)
    c1 = torch.where(small, 1.0 / 6 - theta2 / 120 + theta2**2 / 5040 - theta2**3 / 362880, (t - s) / (t2 * t))
    c2 = torch.where(small, 1.0 / 24 - theta2 / 720 + theta2**2 / 40320 - theta2**3 / 3628800,
                     (t2 + 2 * c - 2) / (2 * t2 * t2))
    c3 = torch.where(small, 1.0 / 120 - theta2 / 2520 + theta2**2 / 120960 - theta2**3 / 9979200,
                     (2 * t - 3 * s + t * c) / (2 * t2 * t2 * t))
    P, Rh = hat(phi), hat(rho)
    PR, RP = P @ Rh, Rh @ P
    PRP = PR @ P
    return (
        0.5 * Rh
        + c1[..., None, None] * (PR + RP + PRP)
        + c2[..., None, None] * (P @ PR + RP @ P - 3 * PRP)
        + c3[..., None, None] * (PRP @ P + P @ PRP)
    )


def se3_right_jacobian_inverse(xi: torch.Tensor) -> torch.Tensor:
    """Inverse right Jacobian of SE(3): ``Log(Exp(xi) Exp(eta)) ~ xi + J_r^-1(xi) eta``.

    xi [..., 6] = [rho, phi] -> [..., 6, 6]. Uses ``J_r(xi) = J_l(-xi)`` and the block inverse
    ``J_l^-1 = [[J^-1, -J^-1 Q J^-1], [0, J^-1]]`` (Barfoot 2017, eq. 7.95).
    """
    rho, phi = -xi[..., :3], -xi[..., 3:]
    j_inv = _so3_left_jacobian_inverse(phi)
    q = _se3_q_matrix(rho, phi)
    top = torch.cat([j_inv, -j_inv @ q @ j_inv], -1)
    bottom = torch.cat([torch.zeros_like(j_inv), j_inv], -1)
    return torch.cat([top, bottom], -2)


# ---------------------------------------------------------------------------- residuals
def edge_residuals(poses: torch.Tensor, edge_nodes: torch.Tensor, measurements: torch.Tensor) -> torch.Tensor:
    """e_ij = Log(Z_ij^-1 T_i^-1 T_j) for every edge.

    poses [N, 4, 4] T_wc, edge_nodes [E, 2], measurements [E, 4, 4] -> residuals [E, 6] ([rho, phi], frame j)
    """
    T_i, T_j = poses[edge_nodes[:, 0]], poses[edge_nodes[:, 1]]
    return se3_log(se3_inverse(measurements) @ se3_inverse(T_i) @ T_j)


def edge_jacobians(poses: torch.Tensor, edge_nodes: torch.Tensor, residuals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Analytic Jacobians of e_ij with respect to left (world-frame) updates of T_i and T_j.

    poses [N, 4, 4], edge_nodes [E, 2], residuals [E, 6] -> (J_i [E, 6, 6], J_j [E, 6, 6]),
    ``J_j = J_r^-1(e) Ad(T_j^-1)`` and ``J_i = -J_j``.
    """
    T_j = poses[edge_nodes[:, 1]]
    J_j = se3_right_jacobian_inverse(residuals) @ adjoint(se3_inverse(T_j))
    return -J_j, J_j


def mahalanobis_sq(residuals: torch.Tensor, information: torch.Tensor) -> torch.Tensor:
    """s = e^T Omega e per edge.  residuals [E, 6], information [E, 6, 6] -> [E]"""
    return torch.einsum("ea,eab,eb->e", residuals, information, residuals)


def robust_cost(s: torch.Tensor, kernel: RobustKernel, scale: float) -> torch.Tensor:
    """rho(s) per edge for a squared Mahalanobis norm s [E] (chi-square units) -> [E].

    none: s;  cauchy: c log(1 + s/c);  geman_mcclure: c s / (c + s)  (c = ``scale``, chi-square units;
    rho(s) ~ s for s << c, so inliers keep their information).
    """
    if kernel == "none":
        return s
    if kernel == "cauchy":
        return scale * torch.log1p(s / scale)
    if kernel == "geman_mcclure":
        return scale * s / (scale + s)
    raise ValueError(f"unknown robust kernel {kernel!r}; use 'none', 'cauchy' or 'geman_mcclure'")


def robust_weight(s: torch.Tensor, kernel: RobustKernel, scale: float) -> torch.Tensor:
    """d rho / d s, the iteratively-reweighted least-squares weight in (0, 1].  s [E] -> [E]"""
    if kernel == "none":
        return torch.ones_like(s)
    if kernel == "cauchy":
        return 1.0 / (1.0 + s / scale)
    if kernel == "geman_mcclure":
        return (scale / (scale + s)) ** 2
    raise ValueError(f"unknown robust kernel {kernel!r}; use 'none', 'cauchy' or 'geman_mcclure'")


def perturb_left(poses: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """T_k <- Exp(delta_k) T_k.  poses [N, 4, 4], delta [N, 6] world-frame twists -> [N, 4, 4]"""
    return se3_exp(delta) @ poses
