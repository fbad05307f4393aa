"""The loop-closure stage of the frame loop: pose graph, loop detection, verification and SA-PGO.

:class:`LoopCloser` is built from its :class:`LoopOptions` (the ``loop:`` config section and its constants). The pipeline calls
:meth:`LoopCloser.process_keyframe` after mapping on every keyframe k (docs/pgo.md, "Loop closure
in the SLAM loop"):

1. the keyframe becomes node k of the pose graph, with an odometry edge (k-1, k) whose
   measurement is the current relative pose ``T_{k-1}^-1 T_k`` and whose information comes from
   the distance and rotation travelled since keyframe k-1 and the tracking quality
   (:func:`odometry_information`);
2. its global descriptor (:func:`mipslam.loop.descriptors.global_descriptor`) is stored;
3. loop candidates: older keyframes (at least ``min_keyframe_gap`` back) that look alike and lie
   near in the current estimate (:func:`mipslam.loop.descriptors.select_loop_candidates`);
4. each candidate i is verified by registering the two keyframes' RGB-D data
   (:func:`mipslam.loop.registration.register_rgbd_pair`, keyframe i the target); an accepted
   registration becomes a loop edge (i, k) if it agrees with the current poses (step 5) or if another
   verified edge of this keyframe or of the ``confirm_keyframes`` before it implies the same correction
   of the query (:func:`implied_corrections`, :func:`corrections_agree`); an unconfirmed edge is reported
   and left out;
5. when this keyframe added loop edges that disagree with the current poses (some ``e^T Omega e``
   above ``consistent_chi2`` and a residual above ``min_correction_m`` or ``min_correction_deg``;
   edges that agree join the graph without an optimisation, which keeps a
   revisited route from re-optimising the whole graph on every keyframe), the graph is optimised
   (:func:`optimize_pose_graph_window` with :meth:`LoopOptions.pgo_options`: the newest
   ``pgo_window_keyframes`` keyframes are free, the older ones they connect to are fixed anchors,
   so the cost per optimisation is bounded). The odometry measurements are refreshed from the
   current keyframe poses first, so the optimisation only distributes the loop error along the
   chain and keeps the local structure that tracking and mapping estimated (as ORB-SLAM's
   essential-graph optimisation does). Pruned loop edges leave the graph for good.
6. The correction is *applied* when at least one of this keyframe's loop edges is still an inlier
   at the solution (kept, and chi-square ``e^T Omega e`` at most the solver's ``prune_chi2``): a
   loop that the robust kernel had to down-weight moves nothing. The pipeline then moves the
   keyframes, the other frames and the map (:meth:`mipslam.state.SLAMState.correct_keyframe_poses`).

The stage never reaches back into the pipeline: it receives the keyframe, the current keyframe
poses and a function that loads an older keyframe's RGB-D data, and returns a :class:`LoopStep`.
:func:`close_loops` is its step in the frame loop: it feeds the stage from the SLAM state and applies
an accepted correction (:func:`correct_map`).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any, Callable, Literal, NamedTuple

import torch

from mipslam.config import LoopConfig, RenderConfig, section_options
from mipslam.errors import MipslamError
from mipslam.geometry import rotation_angle, se3_inverse
from mipslam.losses.metrics import psnr
from mipslam.losses.photometric import apply_affine_exposure
from mipslam.loop.descriptors import CandidateOptions, DescriptorOptions, global_descriptor, select_loop_candidates
from mipslam.loop.pose_graph import PoseGraph, edge_residuals, mahalanobis_sq
from mipslam.loop.registration import RegistrationOptions, RegistrationResult, register_rgbd_pair
from mipslam.loop.solver import PGOOptions, PGOResult, optimize_pose_graph_window
from mipslam.observer import Observer
from mipslam.rendering import render_view
from mipslam.state import LoopState
from mipslam.types import Intrinsics

if TYPE_CHECKING:
    from mipslam.datasets import FrameCache
    from mipslam.state import SLAMState

logger = logging.getLogger(__name__)

# Tracking quality q = running loss / keyframe loss is clamped to [MIN_QUALITY, 1]: a keyframe
# tracked at 10x the usual loss keeps a tenth of the nominal information, never less.
MIN_QUALITY = 0.1

VerificationHook = Callable[[int, int, RegistrationResult], RegistrationResult]
"""(candidate keyframe i, query keyframe k, verification result) -> result: fault injection for
tests and benchmarks (e.g. a deliberately wrong loop); a normal run has none."""

MapRefit = Callable[[list[int], int], int]
"""(keyframe ids, steps) -> steps taken: the mapping stage's refit of the map at the keyframes' corrected poses
after a correction moved them (:func:`mipslam.mapping.refine_after_correction`), which the pipeline passes in:
the stages talk through the pipeline, not through each other's modules (docs/design.md "Import layers")."""


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


# ----------------------------------------------------------------------------- the stage's input


@dataclass(frozen=True)
class KeyframeView:
    """One keyframe's data as the stage reads it.  color [H, W, 3] in [0, 1], depth [H, W] metres."""

    keyframe_id: int
    frame_index: int
    color: torch.Tensor
    depth: torch.Tensor
    intrinsics: Intrinsics


# ----------------------------------------------------------------------------- reports


@dataclass(frozen=True)
class CandidateReport:
    """One loop candidate and its verification (a row of loops.json)."""

    query_keyframe: int
    query_frame: int
    candidate_keyframe: int
    candidate_frame: int
    similarity: float
    distance_m: float
    view_angle_deg: float
    fitness: float
    inlier_rmse_m: float | None
    correspondences: int
    registration_correction_m: float | None
    registration_correction_deg: float | None
    accepted: bool
    reason: str
    time_s: float
    # where the registration passed verification's checks, the relative pose T_i^-1 T_k it measured and the one the
    # estimate held when it was verified (its start), row-major 4x4, else None: what `mipslam eval` compares with
    # the ground truth (mipslam.evaluation.loop_edges)
    measured_T_ij: list[float] | None = None
    estimate_T_ij: list[float] | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class OptimisationReport:
    """One pose-graph optimisation (a row of loops.json); the pipeline adds the map correction."""

    query_keyframe: int
    query_frame: int
    nodes: int
    odometry_edges: int
    loop_edges: int
    new_loop_edges: list[list[int]]
    initial_cost: float | None
    final_cost: float | None
    iterations: int
    subspace_iterations: int
    converged: bool
    pruned_edges: list[list[int]]
    loop_edge_weights: list[dict[str, Any]]
    applied: bool
    reason: str
    max_correction_m: float
    max_correction_deg: float
    spectral_edge_weighting: bool
    low_frequency_correction: bool
    time_s: float
    optimised_nodes: int = 0  # nodes of the solved problem: the free window and its fixed anchors

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class LoopStep:
    """What :meth:`LoopCloser.process_keyframe` decided for one keyframe.

    state: the loop state after this keyframe (graph poses = corrected poses when applied)
    corrected_T_wc: new poses of all keyframes when a correction was applied, else None   # [K, 4, 4] float64
    pgo_seconds: time spent in the optimiser (0 when it did not run)
    """

    state: LoopState
    candidates: tuple[CandidateReport, ...]
    optimisation: OptimisationReport | None
    corrected_T_wc: torch.Tensor | None
    pgo_seconds: float


class VerifiedEdge(NamedTuple):
    """A loop edge (candidate, query) whose registration passed verification, before it may join the graph."""

    report_index: int  # its row in the keyframe's candidate reports
    candidate: int  # keyframe i
    T_ij: torch.Tensor  # [4, 4] float64 CPU, the measured T_i^-1 T_k
    information: torch.Tensor  # [6, 6] float64, order [rho, phi]


# ----------------------------------------------------------------------------- odometry edges


def tracking_quality(tracking_loss: float, running_loss: float | None) -> float:
    """Quality in [MIN_QUALITY, 1]: the running tracking loss over this keyframe's loss (1 when unknown)."""
    if running_loss is None or not math.isfinite(running_loss) or not math.isfinite(tracking_loss) or tracking_loss <= 0:
        return 1.0
    return float(min(1.0, max(MIN_QUALITY, running_loss / tracking_loss)))


def path_motion(T_wc: torch.Tensor) -> tuple[float, float]:
    """Distance and rotation travelled along a sequence of poses: sums of the per-step translation
    (metres) and rotation angle (radians).  T_wc [F, 4, 4] (F >= 1) -> (metres, radians)"""
    if T_wc.shape[0] < 2:
        return 0.0, 0.0
    T = T_wc.to(torch.float64)
    steps = se3_inverse(T[:-1]) @ T[1:]  # [F-1, 4, 4]
    return float(steps[:, :3, 3].norm(dim=-1).sum()), float(rotation_angle(steps[:, :3, :3]).sum())


def odometry_sigmas(path_m: float, path_rad: float, sigma_m: float, sigma_deg: float,
                    drift_ratio: float) -> tuple[float, float]:
    """Standard deviations (metres, radians) of the odometry's drift over a path of ``path_m`` / ``path_rad``:
    ``sigma_m + drift_ratio * path_m`` and ``radians(sigma_deg) + drift_ratio * path_rad``."""
    return sigma_m + drift_ratio * path_m, math.radians(sigma_deg) + drift_ratio * path_rad


def odometry_information(path_m: float, path_rad: float, quality: float, sigma_m: float, sigma_deg: float,
                         drift_ratio: float) -> torch.Tensor:
    """Information of an odometry edge in the order [rho, phi].

    path_m / path_rad: distance and rotation travelled between the two keyframes (:func:`path_motion`
    over every frame in between, so a detour or a sweep that returns counts in full)
    -> diag(1/s_t^2 (x3), 1/s_r^2 (x3)) * quality   # [6, 6] float64, with
    ``s_t = sigma_m + drift_ratio * path_m`` and ``s_r = radians(sigma_deg) + drift_ratio * path_rad``:
    odometry drifts in proportion to the motion, and a keyframe tracked with a loss above the
    running level (quality < 1) is trusted less. The chain must be honest about its drift: a loop
    that disagrees with it by more than ~5-7 of the chain's standard deviations is taken for an
    outlier by the robust kernel (docs/pgo.md).
    """
    sigma_t, sigma_r = odometry_sigmas(path_m, path_rad, sigma_m, sigma_deg, drift_ratio)
    diagonal = torch.tensor([sigma_t**-2] * 3 + [sigma_r**-2] * 3, dtype=torch.float64)
    return torch.diag(diagonal) * quality


def loop_information(information: torch.Tensor, sigma_m: float, sigma_deg: float) -> torch.Tensor:
    """Information of a loop edge whose measurement carries, besides the registration's own uncertainty, an error
    floor of ``sigma_m`` (metres, per axis) and ``sigma_deg`` (degrees, per axis):
    ``(Omega^-1 + D)^-1 = Omega - Omega (Omega + D^-1)^-1 Omega`` with ``D = diag(sigma_m^2 (x3), sigma_rad^2 (x3))``
    (the form that holds for a singular ``Omega``).  information [6, 6] float64, order [rho, phi] -> [6, 6]

    No floor (both 0): ``information`` unchanged.
    """
    if sigma_m <= 0 and sigma_deg <= 0:
        return information
    # a floor on one half only: the other half's variance 1e-30 keeps the registration's information there
    variances = torch.tensor([sigma_m**2] * 3 + [math.radians(sigma_deg) ** 2] * 3, dtype=torch.float64)
    variances = variances.clamp_min(1e-30)
    omega = information.to(torch.float64)
    inflated = omega - omega @ torch.linalg.solve(omega + torch.diag(1.0 / variances), omega)
    return 0.5 * (inflated + inflated.T)


def refresh_odometry(graph: PoseGraph) -> PoseGraph:
    """The graph with every odometry measurement set to the current relative pose ``T_i^-1 T_j``
    (loop measurements unchanged): optimising it distributes only the loop errors."""
    i, j = graph.edge_nodes[:, 0], graph.edge_nodes[:, 1]
    current = se3_inverse(graph.poses[i]) @ graph.poses[j]  # [E, 4, 4]
    measurements = torch.where(graph.edge_is_loop[:, None, None], graph.measurements, current)
    return PoseGraph(graph.poses, graph.edge_nodes, measurements, graph.information, graph.edge_is_loop)


def pose_changes(T_old: torch.Tensor, T_new: torch.Tensor) -> tuple[float, float]:
    """Largest translation (m) and rotation (deg) of ``T_new @ inv(T_old)`` over keyframes.  [K, 4, 4] x2"""
    if T_old.shape[0] == 0:
        return 0.0, 0.0
    change = T_new.to(torch.float64) @ se3_inverse(T_old.to(torch.float64))
    return float(change[:, :3, 3].norm(dim=-1).max()), float(torch.rad2deg(rotation_angle(change[:, :3, :3])).max())


def implied_corrections(poses: torch.Tensor, k: int, candidates: list[int],
                        measurements: list[torch.Tensor]) -> torch.Tensor:
    """The world-frame correction ``C = T_i Z_ik T_k^-1`` that each loop edge (i, k) implies for keyframe k: the
    rigid motion that puts keyframe k where keyframe i and the registration place it. Drift that the old
    keyframes do not share moves neighbouring query keyframes by the same C; registration noise does not.

    poses [K, 4, 4] T_wc float64, candidates: i per edge, measurements: Z_ik [4, 4] per edge -> [E, 4, 4]
    """
    if not candidates:
        return torch.zeros(0, 4, 4, dtype=torch.float64)
    T_i = poses[torch.tensor(candidates, dtype=torch.int64)]
    return T_i @ torch.stack(measurements).to(torch.float64) @ se3_inverse(poses[k])


def correction_at_camera(C: torch.Tensor, T_wc: torch.Tensor) -> torch.Tensor:
    """A world-frame correction C [4, 4] as the motion it gives a camera at ``T_wc`` [4, 4], in that camera's frame:
    ``T_wc^-1 C T_wc`` [4, 4] (independent of where the world origin lies)."""
    return se3_inverse(T_wc) @ C @ T_wc


def corrections_agree(C_a: torch.Tensor, C_b: torch.Tensor, T_wc: torch.Tensor, tolerance_m: float,
                      tolerance_rad: float, relative: float) -> bool:
    """Whether two world-frame corrections C_a, C_b [4, 4] move a camera at ``T_wc`` [4, 4] alike: the pose
    ``C_a T_wc`` seen from ``C_b T_wc`` is within ``max(tolerance_m, relative * s_t)`` metres and
    ``max(tolerance_rad, relative * s_r)`` radians, where s_t, s_r are the smaller of the two corrections' own
    translation and rotation at that camera (origin-independent: both are measured in the camera's frame)."""
    A, B = correction_at_camera(C_a, T_wc), correction_at_camera(C_b, T_wc)
    D = se3_inverse(B) @ A
    size_t = min(float(A[:3, 3].norm()), float(B[:3, 3].norm()))
    size_r = min(float(rotation_angle(A[:3, :3])), float(rotation_angle(B[:3, :3])))
    return (float(D[:3, 3].norm()) <= max(tolerance_m, relative * size_t)
            and float(rotation_angle(D[:3, :3])) <= max(tolerance_rad, relative * size_r))


@dataclass(frozen=True)
class LoopOptions:
    """Everything the loop stage reads: the ``loop`` config section's keys (defaults there), the sensor's depth
    noise, and the stage's constants (defined here; evidence in docs/pgo.md and docs/tracking.md), with the
    option objects of the pure components they make (:meth:`registration_options`, :meth:`pgo_options`,
    :meth:`candidate_options`). Built from the config by :meth:`from_config`."""

    enabled: bool = LoopConfig.enabled
    fitness_threshold: float = LoopConfig.fitness_threshold  # registration: fraction of points with a correspondence
    # The sensor's depth noise power p (dataset.depth_noise_power): direct verification's depth residuals in units
    # of z^p (0: metres)
    depth_noise_power: float = 0.0
    # a loop candidate is at least this many keyframes older than the query
    min_keyframe_gap: int = CandidateOptions.min_gap
    # verification method: dense RGB-D alignment, tracking's Gauss-Newton (direct) or Open3D's (rgbd_odometry),
    # the most robust on the room scenes; direct verifies the same candidates 5x faster (docs/pgo.md)
    registration: Literal["direct", "rgbd_odometry", "point_to_plane", "colored"] = "direct"
    icp_rmse_threshold: float = RegistrationOptions.rmse_threshold  # verification: inlier RMSE, metres
    # finest voxel of ICP and of the fitness/RMSE checks (ICP starts at 2x)
    icp_voxel_m: float = RegistrationOptions.voxel_sizes[-1]
    icp_pixel_stride: int = RegistrationOptions.pixel_stride  # every n-th pixel of each keyframe goes into the clouds
    # odometry edge (keyframe k-1 -> k) standard deviation: floor + drift_ratio * distance (rotation)
    # travelled since keyframe k-1, divided by sqrt(tracking quality), quality = running tracking
    # loss / this keyframe's loss, in [0.1, 1]
    odometry_sigma_m: float = 0.01
    odometry_sigma_deg: float = 0.5
    odometry_drift_ratio: float = 0.05
    # A loop edge's covariance is the registration's plus this floor (standard deviations, per axis): Open3D's
    # information claims millimetres, and a pose graph that believes it bends the odometry chain at its weakest
    # link (docs/tracking.md, "Loop closure"); 0 and 0: the registration's information alone.
    loop_sigma_m: float = 0.0
    loop_sigma_deg: float = 0.0
    # SA-PGO's two switches (on; PGOOptions' defaults are the plain full-LM baseline they are measured against)
    spectral_edge_weighting: bool = True
    low_frequency_correction: bool = True
    num_eigenvectors: int = PGOOptions.num_eigenvectors  # low-frequency basis size K
    full_iterations: int = PGOOptions.full_iterations  # full LM iterations after the subspace stage
    # Mapping steps over the loop's keyframes right after the map moved with its anchors: Gaussians
    # that mapping had pulled towards drifted views do not move back with any anchor; this re-fits them.
    refine_iterations: int = 20
    # Verification also rejects a registration that moved the current estimate by more than this many
    # standard deviations of the drift the odometry edges allow over the keyframe path from the candidate
    # to the query (odometry_sigma + odometry_drift_ratio * path, translation and rotation): a loop 20
    # keyframes back cannot need a 20 cm correction. With one loop edge the pose graph has nothing to
    # outvote a wrong one. 0 turns the check off.
    max_drift_sigmas: float = 3.0
    # New loop edges that already agree with the current poses (every e^T Omega e at most this, chi-square
    # with 6 dof; 12.6 is its 95% quantile) join the graph without an optimisation: on a revisited route
    # nearly every keyframe verifies a loop, and re-optimising the whole graph for each made the pose-graph
    # time per frame grow with the run's length. 0 optimises on every new loop edge.
    consistent_chi2: float = 12.6
    # ... as do edges whose disagreement is below what tracking resolves (the registration information
    # claims millimetres; re-optimising for a 1-2 cm residual on every revisit keyframe only churns the map).
    min_correction_m: float = 0.02
    min_correction_deg: float = 1.0
    # A loop edge that disagrees with the current poses enters the graph only when a second registration implies
    # the same correction: another verified loop edge of this keyframe (to a different old keyframe) or of one of
    # the previous `confirm_keyframes` keyframes (ORB-SLAM's consistency check over consecutive keyframes). Real
    # drift moves neighbouring keyframes alike; registration noise does not. Two corrections C = T_i Z_ik T_k^-1
    # agree when, seen from keyframe k, they differ by at most max(confirm_tolerance_m, confirm_relative x the
    # smaller one) in translation and likewise in rotation. 0 turns the check off (every verified edge may
    # trigger the optimisation). docs/tracking.md, "Loop closure".
    confirm_keyframes: int = 2
    confirm_tolerance_m: float = 0.01
    confirm_tolerance_deg: float = 0.5
    confirm_relative: float = 0.5
    # The pose-graph optimisation frees only the newest keyframes (older ones that share an edge with
    # them stay fixed as anchors); 0 frees the whole graph. A whole-graph solve costs time in proportion
    # to the keyframes, and a revisited room optimises every other keyframe: on a 2000-frame run the
    # optimiser's time per frame grew 7x over 8 laps (docs/robustness.md, "Long runs").
    pgo_window_keyframes: int = 200
    # An applied correction is undone (and its new loop edges leave the graph) when the map, moved with it,
    # renders the loop's keyframes more than this many dB (mean PSNR) worse than before: a loop edge that
    # tears the map apart contradicts what tracking and mapping measured. Negative: no check. Right corrections
    # of the data_synth lap dropped it by 1.3-1.9 dB before the map was refined; 3 dB undoes only tears
    # (docs/tracking.md, "Loop closure").
    max_correction_psnr_drop_db: float = 3.0

    @classmethod
    def from_config(cls, section: LoopConfig, *, depth_noise_power: float = 0.0) -> "LoopOptions":
        """The options of a ``loop`` config section and the dataset's ``depth_noise_power``."""
        return section_options(cls, section, depth_noise_power=depth_noise_power)

    def pgo_options(self, base: PGOOptions = PGOOptions()) -> PGOOptions:
        """The SA-PGO switches and sizes; the remaining solver settings come from ``base``."""
        return replace(base, spectral_edge_weighting=self.spectral_edge_weighting,
                       low_frequency_correction=self.low_frequency_correction,
                       num_eigenvectors=self.num_eigenvectors, full_iterations=self.full_iterations)

    def candidate_options(self, base: CandidateOptions = CandidateOptions()) -> CandidateOptions:
        """Loop-candidate rules: the minimum keyframe gap."""
        return replace(base, min_gap=self.min_keyframe_gap)

    def registration_options(self, base: RegistrationOptions = RegistrationOptions()) -> RegistrationOptions:
        """Verification method, acceptance thresholds, voxel sizes (finest and 2x), pixel stride and the direct
        alignment's depth units (z^p)."""
        return replace(base, method=self.registration, fitness_threshold=self.fitness_threshold,
                       rmse_threshold=self.icp_rmse_threshold, pixel_stride=self.icp_pixel_stride,
                       direct_depth_noise_power=self.depth_noise_power,
                       voxel_sizes=(2 * self.icp_voxel_m, self.icp_voxel_m))


# ----------------------------------------------------------------------------- the stage


class LoopCloser:
    """Loop detection, verification and SA-PGO on keyframes (reads only its :class:`LoopOptions`)."""

    def __init__(self, config: LoopOptions, *, verification_hook: VerificationHook | None = None,
                 descriptor_options: DescriptorOptions = DescriptorOptions(), observer: Observer | None = None):
        self.config = config
        self.observer = observer or Observer()  # times the optimiser as stage "pgo"
        self.descriptor_options = descriptor_options
        self.candidate_options = config.candidate_options()
        self.registration_options = config.registration_options()
        self.pgo_options = config.pgo_options()
        self.verification_hook = verification_hook

    def process_keyframe(
        self,
        state: LoopState,
        keyframe: KeyframeView,
        keyframe_T_wc: torch.Tensor,  # [K, 4, 4] current poses of keyframes 0..k (k = keyframe.keyframe_id)
        odometry: tuple[float, float, float],
        load_keyframe: Callable[[int], KeyframeView],
    ) -> LoopStep:
        """Add keyframe k to the graph, look for loops, verify them and optimise (module docstring).

        odometry: (distance m, rotation rad travelled since keyframe k-1, tracking quality in (0, 1]),
        the evidence for the odometry edge's information (:func:`odometry_information`).
        """
        k = keyframe.keyframe_id
        if state.num_keyframes != k or state.graph.num_nodes != k or keyframe_T_wc.shape[0] != k + 1:
            raise MipslamError(
                f"loop closure got keyframe {k} but holds {state.num_keyframes} descriptors, {state.graph.num_nodes} "
                f"pose-graph nodes and {keyframe_T_wc.shape[0]} poses; keyframes must reach the stage in order, once each")
        poses = keyframe_T_wc.detach().to(dtype=torch.float64, device="cpu")
        descriptor = global_descriptor(keyframe.color.detach(), self.descriptor_options).cpu()
        descriptors = torch.cat([state.descriptors, descriptor[None]])
        graph = state.graph.add_node(poses[k]).with_poses(poses)
        if k > 0:
            T_rel = se3_inverse(poses[k - 1]) @ poses[k]
            cfg = self.config
            path_m, path_rad, quality = odometry
            information = odometry_information(path_m, path_rad, quality, cfg.odometry_sigma_m, cfg.odometry_sigma_deg,
                                               cfg.odometry_drift_ratio)
            graph = graph.add_edge(k - 1, k, T_rel, information, "odometry")

        reports: list[CandidateReport] = []
        verified: list[VerifiedEdge] = []
        for candidate in select_loop_candidates(k, descriptors, poses, self.candidate_options):
            i = candidate.keyframe
            other = load_keyframe(i)
            T_ij_init = se3_inverse(poses[i]) @ poses[k]
            result = register_rgbd_pair(other.color, other.depth, keyframe.color, keyframe.depth, keyframe.intrinsics,
                                        T_ij_init, self.registration_options)
            if self.verification_hook is not None:
                result = self.verification_hook(i, k, result)
            result = self._within_expected_drift(result, poses[i : k + 1])
            reports.append(CandidateReport(
                k, keyframe.frame_index, i, other.frame_index, candidate.similarity, candidate.distance_m,
                candidate.view_angle_deg, result.fitness, _finite_or_none(result.inlier_rmse_m),
                result.num_correspondences, _finite_or_none(result.correction_m),
                _finite_or_none(result.correction_deg), result.accepted,
                "verified: loop edge added" if result.accepted else result.reason, result.time_s,
                result.T_ij.detach().to(torch.float64).cpu().reshape(-1).tolist() if result.accepted else None,
                T_ij_init.reshape(-1).tolist() if result.accepted else None))
            if result.accepted:
                information = loop_information(result.information, self.config.loop_sigma_m, self.config.loop_sigma_deg)
                verified.append(VerifiedEdge(len(reports) - 1, i, result.T_ij.to(torch.float64).cpu(), information))
        if reports:
            logger.info("keyframe %d: %d loop candidate(s), %d verified", k, len(reports), len(verified))

        agrees = self._agrees_with_poses(poses, k, verified)
        corrections = implied_corrections(poses, k, [e.candidate for e in verified], [e.T_ij for e in verified])
        confirmed = self._confirmed(k, poses[k], corrections, agrees, state.recent_corrections)
        recent = self._recent_corrections(state.recent_corrections, k, corrections)
        for edge, keep, correction in zip(verified, confirmed, corrections):
            if keep:
                graph = graph.add_edge(edge.candidate, k, edge.T_ij, edge.information, "loop")
            else:
                reports[edge.report_index] = replace(reports[edge.report_index], accepted=False,
                                                     reason=self._unconfirmed_reason(poses[k], correction))
        kept = sum(confirmed)
        if kept < len(verified):
            logger.info("keyframe %d: %d verified loop edge(s) disagree with the poses and are not confirmed by another "
                        "loop edge; not used", k, len(verified) - kept)
        new_edges = list(range(graph.num_edges - kept, graph.num_edges))
        if not any(keep and not agree for agree, keep in zip(agrees, confirmed)):
            if new_edges:
                logger.info("keyframe %d: %d new loop edge(s) agree with the poses (chi2 <= %.1f or within %.3f m / "
                            "%.2f deg); no optimisation", k, len(new_edges), self.config.consistent_chi2,
                            self.config.min_correction_m, self.config.min_correction_deg)
            return LoopStep(LoopState(graph, descriptors, recent), tuple(reports), None, None, 0.0)
        return self._optimise(graph, descriptors, keyframe, new_edges, tuple(reports), recent)

    def keeps_correction(self, psnr_before_db: list[float], psnr_moved_db: list[float]) -> bool:
        """Whether an applied correction stands: the map moved with it renders the loop's keyframes (mean PSNR,
        dB) at most ``max_correction_psnr_drop_db`` worse than before it. A right loop closure brings the old
        and the new parts of the map together; a wrong one tears the map apart where the keyframes look."""
        limit = self.config.max_correction_psnr_drop_db
        if limit < 0 or not psnr_before_db or not psnr_moved_db:
            return True
        before = sum(psnr_before_db) / len(psnr_before_db)
        moved = sum(psnr_moved_db) / len(psnr_moved_db)
        return not moved < before - limit

    @staticmethod
    def without_loop_edges(state: LoopState, loop_edges: list[list[int]]) -> LoopState:
        """``state`` with the loop edges between the listed keyframe pairs ((i, j) each) removed from the graph."""
        pairs = {tuple(int(n) for n in pair) for pair in loop_edges}
        graph = state.graph
        drop = [e for e in range(graph.num_edges)
                if bool(graph.edge_is_loop[e]) and tuple(graph.edge_nodes[e].tolist()) in pairs]
        return replace(state, graph=graph.without_edges(drop))

    def _within_expected_drift(self, result: RegistrationResult, chain_T_wc: torch.Tensor) -> RegistrationResult:
        """``result`` rejected when its correction of the estimate exceeds ``max_drift_sigmas`` standard deviations
        of the odometry drift over the keyframe chain ``chain_T_wc`` [k - i + 1, 4, 4] (candidate to query)."""
        cfg = self.config
        if not result.accepted or cfg.max_drift_sigmas <= 0:
            return result
        path_m, path_rad = path_motion(chain_T_wc)
        sigma_m, sigma_rad = odometry_sigmas(path_m, path_rad, cfg.odometry_sigma_m, cfg.odometry_sigma_deg,
                                             cfg.odometry_drift_ratio)
        limit_m, limit_deg = cfg.max_drift_sigmas * sigma_m, cfg.max_drift_sigmas * math.degrees(sigma_rad)
        if result.correction_m <= limit_m and result.correction_deg <= limit_deg:
            return result
        reason = (f"registration moved the estimate {result.correction_m:.3f} m / {result.correction_deg:.1f} deg, more "
                  f"than the {limit_m:.3f} m / {limit_deg:.1f} deg ({cfg.max_drift_sigmas:g} sigma) the odometry can have "
                  f"drifted over {path_m:.2f} m / {math.degrees(path_rad):.0f} deg of keyframe path")
        return replace(result, accepted=False, reason=reason)

    def _agrees_with_poses(self, poses: torch.Tensor, k: int, verified: list[VerifiedEdge]) -> list[bool]:
        """Per verified edge (i, k): whether it already agrees with the current ``poses`` [K, 4, 4]: its
        e^T Omega e is at most ``consistent_chi2``, or its residual is within ``min_correction_m`` and
        ``min_correction_deg``."""
        if not verified:
            return []
        cfg = self.config
        nodes = torch.tensor([[e.candidate, k] for e in verified], dtype=torch.int64)
        residuals = edge_residuals(poses, nodes, torch.stack([e.T_ij for e in verified]))  # [E, 6]
        chi2 = mahalanobis_sq(residuals, torch.stack([e.information for e in verified]))
        small = (residuals[:, :3].norm(dim=-1) <= cfg.min_correction_m) & (
            torch.rad2deg(residuals[:, 3:].norm(dim=-1)) <= cfg.min_correction_deg)
        return ((chi2 <= cfg.consistent_chi2) | small).tolist()

    def _confirmed(self, k: int, T_wc: torch.Tensor, corrections: torch.Tensor, agrees: list[bool],
                   recent: torch.Tensor) -> list[bool]:
        """Per verified edge of keyframe k (at ``T_wc`` [4, 4]): whether it may enter the graph. An edge that agrees
        with the poses always may; one that disagrees only when another verified edge of this keyframe, or of one
        of the ``confirm_keyframes`` before it (``recent`` [P, 17]), implies the same correction
        (:func:`corrections_agree`). corrections [E, 4, 4]: :func:`implied_corrections` of the verified edges."""
        cfg = self.config
        if cfg.confirm_keyframes <= 0:
            return [True] * len(agrees)
        earlier = recent[(recent[:, 0] < k) & (recent[:, 0] >= k - cfg.confirm_keyframes), 1:].reshape(-1, 4, 4)
        keep = []
        for n, agree in enumerate(agrees):
            others = torch.cat([corrections[:n], corrections[n + 1 :], earlier])
            keep.append(agree or any(corrections_agree(corrections[n], other, T_wc, cfg.confirm_tolerance_m,
                                                       math.radians(cfg.confirm_tolerance_deg), cfg.confirm_relative)
                                     for other in others))
        return keep

    def _recent_corrections(self, recent: torch.Tensor, k: int, corrections: torch.Tensor) -> torch.Tensor:
        """``recent`` [P, 17] without the rows older than ``confirm_keyframes`` keyframes, plus keyframe k's."""
        if self.config.confirm_keyframes <= 0:
            return recent[:0]
        keep = recent[recent[:, 0] > k - self.config.confirm_keyframes]
        rows = torch.cat([torch.full((corrections.shape[0], 1), float(k), dtype=torch.float64),
                          corrections.reshape(-1, 16)], dim=1)
        return torch.cat([keep, rows])

    def _unconfirmed_reason(self, T_wc: torch.Tensor, correction: torch.Tensor) -> str:
        local = correction_at_camera(correction, T_wc)
        return (f"verified, but its correction of {float(local[:3, 3].norm()):.3f} m / "
                f"{math.degrees(float(rotation_angle(local[:3, :3]))):.1f} deg is not confirmed by another loop edge of "
                f"this keyframe or of the {self.config.confirm_keyframes} before it")

    def _optimise(self, graph: PoseGraph, descriptors: torch.Tensor, keyframe: KeyframeView, new_edges: list[int],
                  reports: tuple[CandidateReport, ...], recent_corrections: torch.Tensor) -> LoopStep:
        graph = refresh_odometry(graph)
        with self.observer.stage("pgo"):
            result = optimize_pose_graph_window(graph, self.pgo_options, self.config.pgo_window_keyframes)
        pruned = set(result.pruned_edges)
        inlier_limit = self.pgo_options.prune_chi2 if self.pgo_options.prune_chi2 is not None else self.pgo_options.kernel_scale
        inliers = [e for e in new_edges if e not in pruned and float(result.edge_chi2[e]) <= inlier_limit]
        applied = bool(inliers) and math.isfinite(result.final_cost)
        if applied:
            reason = f"{len(inliers)} of {len(new_edges)} new loop edge(s) are inliers at the solution"
        elif not math.isfinite(result.final_cost):
            reason = "the optimisation ended with a non-finite cost"
        else:
            reason = (f"no new loop edge is an inlier at the solution (pruned, or chi2 above {inlier_limit:g}): "
                      "the loop disagrees with the rest of the graph")
        T_before = graph.poses
        T_after = result.poses.to(torch.float64).cpu() if applied else T_before
        max_m, max_deg = pose_changes(T_before, result.poses.to(torch.float64).cpu())
        kept = graph.without_edges(sorted(pruned)).with_poses(T_after)
        report = OptimisationReport(
            query_keyframe=keyframe.keyframe_id, query_frame=keyframe.frame_index, nodes=graph.num_nodes,
            odometry_edges=int((~graph.edge_is_loop).sum()), loop_edges=int(graph.edge_is_loop.sum()),
            new_loop_edges=[graph.edge_nodes[e].tolist() for e in new_edges],
            initial_cost=_finite_or_none(result.initial_cost), final_cost=_finite_or_none(result.final_cost),
            iterations=result.iterations, subspace_iterations=result.subspace_iterations, converged=result.converged,
            pruned_edges=[graph.edge_nodes[e].tolist() for e in result.pruned_edges],
            loop_edge_weights=_loop_edge_summary(graph, result, [*new_edges, *result.pruned_edges]),
            applied=applied, reason=reason, max_correction_m=max_m, max_correction_deg=max_deg,
            spectral_edge_weighting=self.pgo_options.spectral_edge_weighting,
            low_frequency_correction=self.pgo_options.low_frequency_correction, time_s=result.time_s,
            optimised_nodes=result.problem_nodes)
        logger.info("keyframe %d: pose graph %d nodes / %d loops, cost %.4g -> %.4g in %d iterations, pruned %s; %s",
                    keyframe.keyframe_id, graph.num_nodes, report.loop_edges, result.initial_cost, result.final_cost,
                    result.iterations, report.pruned_edges, "applied" if applied else "not applied: " + reason)
        return LoopStep(LoopState(kept, descriptors, recent_corrections), reports, report,
                        T_after.clone() if applied else None, result.time_s)


def _loop_edge_summary(graph: PoseGraph, result: PGOResult, edges: list[int]) -> list[dict[str, Any]]:
    """Per loop edge of ``edges`` (the optimisation's new and pruned ones): its keyframes, final robust weight
    and chi-square (raw information). Not every loop edge: a row per loop edge per optimisation grows
    quadratically (2000 frames: 820 optimisations x up to 1535 loop edges = 640k rows, 51 MB of JSON in
    every checkpoint and ~300 MiB of Python objects)."""
    rows = []
    for e in sorted(set(edges)):
        if not bool(graph.edge_is_loop[e]):
            continue
        i, j = graph.edge_nodes[e].tolist()
        rows.append({"edge": [i, j], "weight": float(result.loop_weights[e]),
                     "chi2": _finite_or_none(float(result.edge_chi2[e]))})
    return rows


# ----------------------------------------------------------------------------- the step in the frame loop


def keyframe_view(state: "SLAMState", frames: "FrameCache", keyframe_id: int) -> KeyframeView:
    """Keyframe ``keyframe_id``'s RGB-D data as the stage reads it."""
    record = state.keyframe_record(keyframe_id)
    frame = frames[record.index]
    return KeyframeView(keyframe_id, record.index, frame.color, frame.depth, frame.intrinsics)


def close_loops(closer: LoopCloser, state: "SLAMState", frames: "FrameCache", render_config: RenderConfig,
                refit: MapRefit) -> LoopStep:
    """The loop-closure step on the newest keyframe of ``state``: :meth:`LoopCloser.process_keyframe` with the
    odometry evidence since the previous keyframe; the step's reports go into ``state.loop_log``, and an
    accepted correction moves the keyframes, the other frames and the map (:func:`correct_map`, which renders
    the map with ``render_config``, the mapping stage's, and refits it with ``refit``)."""
    keyframe_id = state.last_keyframe_id()
    record = state.keyframe_record(keyframe_id)
    since = state.keyframe_frames[keyframe_id - 1] if keyframe_id > 0 else len(state.frames) - 1
    path_m, path_rad = path_motion(torch.stack([f.T_wc for f in state.frames[since:]]))
    odometry = (path_m, path_rad, tracking_quality(record.tracking_loss, state.running_loss))
    step = closer.process_keyframe(state.loop, keyframe_view(state, frames, keyframe_id), state.keyframe_poses(),
                                   odometry, lambda other: keyframe_view(state, frames, other))
    state.loop = step.state
    state.loop_log["candidates"].extend(c.to_dict() for c in step.candidates)
    if step.optimisation is not None:
        entry = step.optimisation.to_dict()
        if step.corrected_T_wc is not None:
            entry.update(correct_map(closer, state, frames, step, render_config, refit))
        state.loop_log["optimisations"].append(entry)
    return step


def correct_map(closer: LoopCloser, state: "SLAMState", frames: "FrameCache", step: LoopStep,
                render_config: RenderConfig, refit: MapRefit) -> dict[str, Any]:
    """Apply an accepted pose-graph correction (:meth:`~mipslam.state.SLAMState.correct_keyframe_poses`), then
    ``LoopOptions.refine_iterations`` mapping steps over the loop's keyframes (the query and its loop partners) at
    their corrected, fixed poses (``refit``: :func:`~mipslam.mapping.refine_after_correction`, from the
    pipeline). Returns the loops.json entry: Gaussians moved, refinement steps and seconds.

    The map's PSNR (dB) at those keyframes against their images is measured before the correction at the old
    poses and after the Gaussians moved with their anchor keyframes: a correction whose moved map renders them
    worse by more than ``LoopOptions.max_correction_psnr_drop_db`` (:meth:`LoopCloser.keeps_correction`) is undone
    (poses and Gaussians back, its new loop edges removed from the graph). With ``observer.diagnostics`` the
    entry also has the PSNR at the new poses with the map not yet moved (what correcting only the poses
    would give) and after the refinement (a render per keyframe each).
    """
    check = sorted({step.optimisation.query_keyframe, *(i for i, _ in step.optimisation.new_loop_edges)})
    diagnostics = closer.observer.diagnostics
    start = time.perf_counter()

    def measure(poses) -> list[float]:
        return [_keyframe_psnr(render_config, state, frames, k, poses(k)) for k in check]

    before = measure(lambda k: state.keyframe_record(k).T_wc)
    poses_only = measure(lambda k: step.corrected_T_wc[k]) if diagnostics else None
    T_wc_old, poses_old = state.keyframe_poses(), state.poses()
    moved = state.correct_keyframe_poses(step.corrected_T_wc)
    moved_only = measure(lambda k: state.keyframe_record(k).T_wc)
    entry = {"gaussians_moved": moved, "psnr_keyframes": check, "psnr_before_db": before, "psnr_moved_db": moved_only}
    if not closer.keeps_correction(before, moved_only):
        state.correct_keyframe_poses(T_wc_old)  # the Gaussians back with their anchors
        state.set_poses(poses_old)  # every frame's pose back exactly
        state.loop = closer.without_loop_edges(state.loop, step.optimisation.new_loop_edges)
        logger.info("loop correction at keyframe %d undone: the moved map renders keyframes %s at %.2f dB, %.2f dB "
                    "before", step.optimisation.query_keyframe, check, sum(moved_only) / len(moved_only),
                    sum(before) / len(before))
        entry.update({"gaussians_moved": 0, "refine_iterations": 0, "applied": False, "undone": True,
                      "map_correction_s": time.perf_counter() - start})
        return entry
    refine_iterations = refit(check, closer.config.refine_iterations)
    entry["refine_iterations"] = refine_iterations
    if diagnostics:
        after = measure(lambda k: state.keyframe_record(k).T_wc)
        logger.info("loop correction at keyframe %d: moved %d Gaussians; map PSNR at keyframes %s %.2f -> %.2f dB "
                    "(%.2f dB with the poses alone corrected, %.2f dB with the map moved before refinement)",
                    step.optimisation.query_keyframe, moved, check, sum(before) / len(before), sum(after) / len(after),
                    sum(poses_only) / len(poses_only), sum(moved_only) / len(moved_only))
        entry.update({"psnr_poses_only_db": poses_only, "psnr_after_db": after})
    else:
        logger.info("loop correction at keyframe %d: moved %d Gaussians (map PSNR at keyframes %s %.2f -> %.2f dB), "
                    "%d refinement steps", step.optimisation.query_keyframe, moved, check,
                    sum(before) / len(before), sum(moved_only) / len(moved_only), refine_iterations)
    entry["map_correction_s"] = time.perf_counter() - start
    return entry


@torch.no_grad()
def _keyframe_psnr(render_config: RenderConfig, state: "SLAMState", frames: "FrameCache", keyframe_id: int,
                   T_wc: torch.Tensor) -> float:
    """PSNR (dB) of the map rendered at ``T_wc`` [4, 4] (camera-to-world) against keyframe ``keyframe_id``'s
    image, in the render config's footprint mode, with the keyframe's exposure."""
    record = state.keyframe_record(keyframe_id)
    frame = frames[record.index]
    gmap = state.gaussian_map
    out = render_view(gmap.activated(), se3_inverse(T_wc.to(torch.float64)).to(device=gmap.device, dtype=gmap.dtype),
                      frame.intrinsics, render_config)
    exposure = record.exposure.to(out.color)
    return float(psnr(apply_affine_exposure(out.color, exposure[0], exposure[1]).clamp(0, 1), frame.color))
